//! A drive's status as JSON: the decoded status block with its names
//! (the API's `GET .../status`, the stream's `status` messages, the MQTT
//! face's retained `<prefix>/<drive>/status`), and where and when it was
//! read.

use std::time::{Instant, SystemTime};

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::problem::{Kind, Problem};
use super::target::Target;
use super::writes;
use crate::bus::DriveSnapshot;
use crate::bus::cache::Link;
use crate::bus::freshness::{Cause, Freshness, Verdict};
use crate::control::{Caller, Control};
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

/// How fresh a drive's data is (the same answer on every face).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "kebab-case")]
pub enum FreshnessName {
    /// Polled within its expected period.
    Live,
    /// Polls missing for longer than its poll period allows; not yet
    /// offline.
    Stale,
    /// The drive stopped answering its polls.
    Offline,
    /// The drive has not answered once since its bus opened.
    Never,
    /// Its bus's port is gone (adapter unplugged, device server
    /// unreachable).
    BusDown,
}

impl From<Freshness> for FreshnessName {
    fn from(f: Freshness) -> Self {
        match f {
            Freshness::Live => FreshnessName::Live,
            Freshness::Stale => FreshnessName::Stale,
            Freshness::Offline => FreshnessName::Offline,
            Freshness::Never => FreshnessName::Never,
            Freshness::BusDown => FreshnessName::BusDown,
        }
    }
}

/// A drive's freshness as the API, the stream and MQTT's JSON show it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct FreshnessView {
    /// `live`, `stale`, `offline`, `never` or `bus-down`: only `live`
    /// values are current; the others are the last the drive sent.
    pub freshness: FreshnessName,
    /// Since when the data has not been live (for `never`: since the bus
    /// opened), RFC 3339; `null` when live.
    pub freshness_since: Option<String>,
    /// Why it is not live, in words; `null` when live.
    pub freshness_reason: Option<String>,
}

impl FreshnessView {
    /// `verdict` of drive `unit` on bus `bus` at `baud`, in words.
    pub fn of(verdict: &Verdict, bus: &str, unit: u8, baud: u32) -> Self {
        FreshnessView {
            freshness: verdict.freshness.into(),
            freshness_since: verdict.since.map(rfc3339),
            freshness_reason: verdict.words(bus, unit, baud),
        }
    }

    /// The freshness of `target`'s data now.
    pub fn now(target: &Target) -> Self {
        let verdict = verdict(target);
        Self::of(
            &verdict,
            target.bus.name(),
            target.drive.unit,
            target.bus.line().baud(),
        )
    }
}

/// The freshness of `target`'s data now (a drive the bus does not know
/// counts as never heard).
pub(crate) fn verdict(target: &Target) -> Verdict {
    target
        .bus
        .freshness_at(target.drive.unit, Instant::now())
        .unwrap_or(Verdict {
            freshness: Freshness::Never,
            since: None,
            age: None,
            cause: Cause::NotPolledYet,
            stale_at: None,
        })
}

/// The link as the API shows it: the cache's, except that no drive
/// answers on a bus whose port is gone.
pub(crate) fn link_of(snapshot: Option<&DriveSnapshot>, verdict: &Verdict) -> LinkName {
    if verdict.freshness == Freshness::BusDown {
        return LinkName::Offline;
    }
    snapshot.map_or(Link::Unknown, |s| s.link).into()
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
    /// Whether it answers its polls (`offline` too while its bus is down).
    pub link: LinkName,
    /// How fresh the status is: only a `live` one is current.
    #[serde(flatten)]
    pub freshness: FreshnessView,
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

fn millis(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

fn snapshot(target: &Target) -> Option<DriveSnapshot> {
    target.bus.drive(target.drive.unit)
}

/// The latest polled status of `target` as a reply (`source: cache`), or
/// the problem saying it has not answered yet (with what to check, and
/// how to find the drive with `drivegate probe` on `port`).
pub(crate) fn cached(target: &Target) -> Result<StatusReply, Problem> {
    cached_on(target, None)
}

/// [`cached`], naming the bus's `port` in the hint for a drive that never
/// answered.
pub(crate) fn cached_on(target: &Target, port: Option<&str>) -> Result<StatusReply, Problem> {
    let snap = snapshot(target);
    let cached = snap
        .as_ref()
        .and_then(|s| Some((s.status?, s.seen_at?, s.age()?)));
    let Some((status, seen_at, age)) = cached else {
        return Err(
            Problem::new(Kind::DriveOffline, no_status_yet(target, port))
                .for_drive(&target.drive.name)
                .retry_after(1),
        );
    };
    Ok(reply(
        target,
        &status,
        StatusSource::Cache,
        seen_at,
        millis(age),
    ))
}

/// Why `target` has no status yet, and what to do about it: a drive that
/// was polled and never answered is most often at another baud rate or
/// address than the configuration says.
fn no_status_yet(target: &Target, port: Option<&str>) -> String {
    let (name, unit) = (&target.drive.name, target.drive.unit);
    let (bus, baud) = (target.bus.name(), target.bus.line().baud());
    let verdict = verdict(target);
    match &verdict.cause {
        Cause::NeverAnswered { failures, .. } => {
            let polls = if *failures == 1 { "poll" } else { "polls" };
            let probe = format!(
                "drivegate probe --port {} --try-bauds",
                port.unwrap_or("<the bus's port>")
            );
            format!(
                "drive \"{name}\" has not answered once since bus {bus} opened ({failures} {polls} \
                 failed): check the baud rate (bus {bus} runs at {baud} baud; the drives leave \
                 the factory at 115200) and the unit address ({unit}); `{probe}` (with the \
                 daemon stopped) finds the drives on the line and their rate; then the drive's \
                 power and wiring"
            )
        }
        _ => match verdict.words(bus, unit, baud) {
            Some(why) => format!("drive \"{name}\" has no status yet: {why}"),
            None => format!("drive \"{name}\" has no status yet"),
        },
    }
}

/// `status` of `target`, read at `seen_at`, as a reply.
pub(crate) fn reply(
    target: &Target,
    status: &Status,
    source: StatusSource,
    seen_at: SystemTime,
    age_ms: u64,
) -> StatusReply {
    // Read after the status: a fresh read may just have brought it online.
    let verdict = verdict(target);
    let link = link_of(snapshot(target).as_ref(), &verdict);
    StatusReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        link,
        freshness: FreshnessView::of(
            &verdict,
            target.bus.name(),
            target.drive.unit,
            target.bus.line().baud(),
        ),
        source,
        seen_at: rfc3339(seen_at),
        age_ms,
        status: StatusView::from(status),
    }
}

/// The status of `target`, from the cache or (`fresh`) read from the
/// drive now for `caller`.
pub(crate) async fn status(
    control: &Control,
    caller: &Caller,
    target: &Target,
    fresh: bool,
) -> Result<StatusReply, Problem> {
    if fresh {
        let status = writes::read_status(control, caller, target.clone()).await?;
        Ok(reply(
            target,
            &status,
            StatusSource::Bus,
            SystemTime::now(),
            0,
        ))
    } else {
        let plant = control.plant().bus(target.bus.name());
        let port = plant
            .as_ref()
            .filter(|b| !b.config.is_simulated())
            .map(|b| b.config.port.get_ref().as_str());
        cached_on(target, port)
    }
}
