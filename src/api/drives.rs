//! Reading drives: the list, one drive, and its decoded status, from the
//! poll cache (free: no bus time) or, with `?fresh=true`, read now.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::{Params, PathParams};
use super::problem_response::Problem;
use super::problem_response::{FreshReadProblems, ReadProblems};
use super::settings_diff::{DeclaredState, declared_state};
use super::state::{ApiState, Target};
use crate::bus::DriveSnapshot;
use crate::control::Caller;
use crate::faces_shared::command_messages::{LeaseInfo, lease_of};
use crate::faces_shared::status::{FreshnessView, LinkName, StatusReply, StatusView};
use crate::timestamp::rfc3339;

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
    /// Whether it answers its polls (`offline` too while its bus is
    /// down).
    pub link: LinkName,
    /// Same as `link == "online"`.
    pub online: bool,
    /// How fresh its status is: only a `live` one is current.
    #[serde(flatten)]
    pub freshness: FreshnessView,
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
    let verdict = crate::faces_shared::status::verdict(&target);
    let link = crate::faces_shared::status::link_of(snap.as_ref(), &verdict);
    DriveView {
        name: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        gear_ratio: target.drive.gear_ratio,
        link,
        online: link == LinkName::Online,
        freshness: FreshnessView::of(
            &verdict,
            target.bus.name(),
            target.drive.unit,
            target.bus.line().baud(),
        ),
        last_seen: snap.as_ref().and_then(|s| s.seen_at).map(rfc3339),
        age_ms: snap.as_ref().and_then(DriveSnapshot::age).map(millis),
        consecutive_failures: snap.as_ref().map_or(0, |s| s.consecutive_failures),
        status: snap
            .as_ref()
            .and_then(|s| s.status.as_ref())
            .map(StatusView::from),
        lease: lease_of(&state.control, target.index),
        declared_settings: declared_state(&state.control, &target),
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
    crate::faces_shared::status::status(&state.control, caller, &target, fresh).await
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
