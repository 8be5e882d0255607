//! Reading drives: the list, one drive, and its decoded status, from the
//! poll cache (free: no bus time) or, with `?fresh=true`, read now.

use std::time::SystemTime;

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::auth::Caller;
use super::control;
use super::document::{DeclaredState, declared_state};
use super::extract::{Params, PathParams};
use super::openapi::{FreshReadProblems, ReadProblems};
use super::problem::{Kind, Problem};
use super::setpoints::{LeaseInfo, lease_of};
use super::state::{ApiState, Target};
use crate::bus::DriveSnapshot;
use crate::bus::cache::Link;
use crate::drive::{Fault, Mode, Status};
use crate::timestamp::rfc3339;

/// Control mode (STATUS bits 4..3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModeName {
    /// Open-loop voltage control (power-on, before a mode command).
    OpenLoop,
    /// Speed closed loop.
    Speed,
    /// Position closed loop.
    Position,
    /// Torque (current) closed loop.
    Torque,
}

impl From<Mode> for ModeName {
    fn from(m: Mode) -> Self {
        match m {
            Mode::OpenLoop => ModeName::OpenLoop,
            Mode::Speed => ModeName::Speed,
            Mode::Position => ModeName::Position,
            Mode::Torque => ModeName::Torque,
        }
    }
}

/// Fault (STATUS bits 2..0); `none` when healthy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FaultName {
    /// 0: healthy.
    None,
    /// 1: current feedback fault.
    CurrentSense,
    /// 2: encoder feedback fault.
    Encoder,
    /// 3: power stage fault.
    PowerStage,
    /// 4: drive over-temperature.
    OverTemperature,
    /// 5: supply under-voltage.
    UnderVoltage,
    /// 6: supply over-voltage.
    OverVoltage,
    /// 7: reserved by the maker.
    Reserved,
}

impl From<Fault> for FaultName {
    fn from(f: Fault) -> Self {
        match f {
            Fault::None => FaultName::None,
            Fault::CurrentSense => FaultName::CurrentSense,
            Fault::Encoder => FaultName::Encoder,
            Fault::PowerStage => FaultName::PowerStage,
            Fault::OverTemperature => FaultName::OverTemperature,
            Fault::UnderVoltage => FaultName::UnderVoltage,
            Fault::OverVoltage => FaultName::OverVoltage,
            Fault::Reserved => FaultName::Reserved,
        }
    }
}

/// Whether a drive answers its polls.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum LinkName {
    /// Not polled yet.
    Unknown,
    /// Answering.
    Online,
    /// Stopped answering; polled with backoff.
    Offline,
}

impl From<Link> for LinkName {
    fn from(l: Link) -> Self {
        match l {
            Link::Unknown => LinkName::Unknown,
            Link::Online => LinkName::Online,
            Link::Offline => LinkName::Offline,
        }
    }
}

/// A decoded status block (manual 1.7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StatusView {
    /// Whole turns of the output, 0..65535 (wraps).
    pub turns: u16,
    /// Angle within the turn, degrees (-180..180).
    pub angle_deg: f64,
    /// Speed at the gearbox output, rpm.
    pub speed_rpm: i16,
    /// Motor current, amps.
    pub current_a: f64,
    /// Motor current, raw counts (1 A = 128).
    pub current_counts: i16,
    /// Supply voltage, volts.
    pub voltage_v: u16,
    /// Drive temperature, degrees Celsius.
    pub temperature_c: i16,
    /// The drive is activated (takes setpoints).
    pub active: bool,
    /// The encoder is calibrated.
    pub calibrated: bool,
    /// The motor stalled (needs the fault-reset command).
    pub stalled: bool,
    /// Control mode.
    pub mode: ModeName,
    /// Fault by name, `none` when healthy.
    pub fault: FaultName,
    /// Fault code 0..7.
    pub fault_code: u16,
    /// The raw STATUS register.
    pub flags: u16,
}

impl From<&Status> for StatusView {
    fn from(s: &Status) -> Self {
        StatusView {
            turns: s.turns,
            angle_deg: s.angle_deg(),
            speed_rpm: s.speed_rpm,
            current_a: s.current_a(),
            current_counts: s.current_counts,
            voltage_v: s.voltage_v,
            temperature_c: s.temperature_c,
            active: s.active(),
            calibrated: s.calibrated(),
            stalled: s.stalled(),
            mode: s.mode().into(),
            fault: s.fault().into(),
            fault_code: s.fault().code(),
            flags: s.flags,
        }
    }
}

/// Where a status came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum StatusSource {
    /// The latest background poll.
    Cache,
    /// Read from the drive for this request (`?fresh=true`).
    Bus,
}

/// A drive's status with where and when it was read.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct StatusReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// Whether it answers its polls.
    pub link: LinkName,
    /// Cache or bus.
    pub source: StatusSource,
    /// When the status was read (RFC 3339, UTC).
    pub seen_at: String,
    /// How old the status is, ms.
    pub age_ms: u64,
    /// The decoded status.
    #[serde(flatten)]
    pub status: StatusView,
}

/// A configured drive and what is known of it.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct DriveView {
    /// Its name (use it in paths; on a single bus the unit number works too).
    pub name: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// Its gearbox ratio (motor turns per output turn).
    pub gear_ratio: f64,
    /// Whether it answers its polls.
    pub link: LinkName,
    /// Same as `link == "online"`.
    pub online: bool,
    /// When it last answered (RFC 3339, UTC).
    pub last_seen: Option<String>,
    /// Age of its latest status, ms.
    pub age_ms: Option<u64>,
    /// Polls failed in a row.
    pub consecutive_failures: u32,
    /// Its latest status.
    pub status: Option<StatusView>,
    /// The motor-safety lease on it, if any.
    pub lease: Option<LeaseInfo>,
    /// Its declared settings (`[bus.drive.settings]`) and whether it holds
    /// them (the console's drift badge); absent without a declaration.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub declared_settings: Option<DeclaredState>,
}

fn millis(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

fn snapshot(target: Target) -> Option<DriveSnapshot> {
    target.bus.drive(target.drive.unit)
}

fn view(state: &ApiState, target: Target) -> DriveView {
    let snap = snapshot(target.clone());
    let link = snap.as_ref().map_or(Link::Unknown, |s| s.link);
    DriveView {
        name: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        gear_ratio: target.drive.gear_ratio,
        link: link.into(),
        online: link == Link::Online,
        last_seen: snap.as_ref().and_then(|s| s.seen_at).map(rfc3339),
        age_ms: snap.as_ref().and_then(DriveSnapshot::age).map(millis),
        consecutive_failures: snap.as_ref().map_or(0, |s| s.consecutive_failures),
        status: snap
            .as_ref()
            .and_then(|s| s.status.as_ref())
            .map(StatusView::from),
        lease: lease_of(state, target.index),
        declared_settings: declared_state(state, &target),
    }
}

/// Every configured drive with its latest status.
#[utoipa::path(
    get,
    path = "/api/v1/drives",
    tag = "drives",
    security(("bearer" = ["viewer"])),
    responses(
        (status = 200, description = "Every configured drive, in configuration order", body = [DriveView]),
        ReadProblems,
    )
)]
pub async fn list_drives(
    State(state): State<ApiState>,
    _caller: Caller,
) -> Result<Json<Vec<DriveView>>, Problem> {
    let views = (0..state.plant.now().drive_slots())
        .filter_map(|i| state.target_at(i))
        .map(|t| view(&state, t))
        .collect();
    Ok(Json(views))
}

/// One drive with its latest status and lease.
#[utoipa::path(
    get,
    path = "/api/v1/drives/{drive}",
    tag = "drives",
    security(("bearer" = ["viewer"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    responses(
        (status = 200, description = "The drive", body = DriveView),
        ReadProblems,
    )
)]
pub async fn get_drive(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(key): PathParams<String>,
) -> Result<Json<DriveView>, Problem> {
    let target = state.target(&key)?;
    Ok(Json(view(&state, target)))
}

/// `?fresh=`.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct StatusQuery {
    /// Read the drive now (one bus transaction, command priority) instead of
    /// returning the latest poll.
    #[serde(default)]
    pub fresh: bool,
}

/// The status of `key`, from the cache or (`fresh`) from the drive.
pub async fn status(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    fresh: bool,
) -> Result<StatusReply, Problem> {
    let target = state.target(key)?;
    let (status, source, seen_at, age_ms) = if fresh {
        let status = control::read_status(state, caller, target.clone()).await?;
        (status, StatusSource::Bus, SystemTime::now(), 0)
    } else {
        let snap = snapshot(target.clone());
        let cached = snap
            .as_ref()
            .and_then(|s| Some((s.status?, s.seen_at?, s.age()?)));
        let Some((status, seen_at, age)) = cached else {
            return Err(Problem::new(
                Kind::DriveOffline,
                format!(
                    "drive \"{}\" has not answered a status poll yet; check its power, wiring and unit address ({})",
                    target.drive.name, target.drive.unit
                ),
            )
            .for_drive(&target.drive.name)
            .retry_after(1));
        };
        (status, StatusSource::Cache, seen_at, millis(age))
    };
    // Read after the status: a fresh read may just have brought it online.
    let link = snapshot(target.clone()).map_or(Link::Unknown, |s| s.link);
    Ok(StatusReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        link: link.into(),
        source,
        seen_at: rfc3339(seen_at),
        age_ms,
        status: StatusView::from(&status),
    })
}

/// The drive's decoded status and its age; `?fresh=true` reads the drive now.
#[utoipa::path(
    get,
    path = "/api/v1/drives/{drive}/status",
    tag = "drives",
    security(("bearer" = ["viewer"])),
    params(
        ("drive" = String, Path, description = "Drive name, or its unit number on a single bus"),
        StatusQuery,
    ),
    responses(
        (status = 200, description = "The status", body = StatusReply),
        FreshReadProblems,
    )
)]
pub async fn get_status(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    Params(query): Params<StatusQuery>,
) -> Result<Json<StatusReply>, Problem> {
    status(&state, &caller, &key, query.fresh).await.map(Json)
}
