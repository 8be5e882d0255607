//! `GET /api/v1/drives/{drive}/settings`: what the drive holds now, read from
//! it (its setpoints, protection, ramps, inertia and RS-485 control), so a
//! settings form starts from the drive's values and not from a guess.
//!
//! Six reads at command priority (see `drive::settings::BLOCKS`), by the
//! core (`Control::read_settings`, which declared settings use too); a
//! read changes nothing, so it is not audited. The same document is what
//! `PUT` takes ([`super::document`]).

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::{Params, PathParams};
use super::problem_response::FreshReadProblems;
use super::problem_response::{BusContext, Problem};
use super::state::ApiState;
use crate::control::Caller;
use crate::drive::settings::DriveSettings;
use crate::drive::units::{self, COUNTS_PER_AMP};
use crate::timestamp::rfc3339;

/// The setpoint registers, as last written (by anyone).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SetpointsView {
    /// SPEED_REF, rpm.
    pub speed_rpm: i16,
    /// POSITION_REF, degrees.
    pub position_deg: f64,
    /// IQ_REF, amps.
    pub torque_a: f64,
    /// IQ_REF, counts.
    pub torque_counts: i16,
}

/// Over-current protection (manual 1.8).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ProtectionView {
    /// Current limit, amps.
    pub limit_a: f64,
    /// Current limit, counts (1 A = 128).
    pub limit_counts: u16,
    /// How long the current may stay over the limit, ms.
    pub stall_ms: u16,
}

/// A ramp (manual 1.9, 1.10).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct RampView {
    /// Alpha; 0 turns the ramp off.
    pub alpha: u32,
}

/// What a drive holds, read from it.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct DriveSettingsView {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// The configured gear ratio (for the speed ramp's formula).
    pub gear_ratio: f64,
    /// When the registers were read (RFC 3339, UTC).
    pub read_at: String,
    /// The setpoint registers.
    pub setpoints: SetpointsView,
    /// Over-current protection.
    pub protection: ProtectionView,
    /// Speed ramp.
    pub speed_ramp: RampView,
    /// Position ramp.
    pub position_ramp: RampView,
    /// Load inertia, times the rotor's.
    pub inertia_ratio: u16,
    /// True when RS-485 controls the motor (false: CAN).
    pub rs485_control: bool,
}

impl DriveSettingsView {
    fn new(state: &ApiState, key: &str, s: &DriveSettings) -> Result<Self, Problem> {
        let target = state.target(key)?;
        Ok(DriveSettingsView {
            drive: target.drive.name.clone(),
            bus: target.bus.name().to_string(),
            unit: target.drive.unit,
            gear_ratio: target.drive.gear_ratio,
            read_at: rfc3339(std::time::SystemTime::now()),
            setpoints: SetpointsView {
                speed_rpm: s.speed_rpm,
                position_deg: units::centideg_to_degrees(s.position_centideg),
                torque_a: units::counts_to_amps(s.torque_counts),
                torque_counts: s.torque_counts,
            },
            protection: ProtectionView {
                limit_a: f64::from(s.limit_counts) / COUNTS_PER_AMP,
                limit_counts: s.limit_counts,
                stall_ms: s.stall_ms,
            },
            speed_ramp: RampView {
                alpha: s.speed_alpha,
            },
            position_ramp: RampView {
                alpha: s.position_alpha,
            },
            inertia_ratio: s.inertia_ratio,
            rs485_control: s.rs485_control,
        })
    }
}

/// Reads the settings of `key` from the drive, through the core.
pub async fn read(
    state: &ApiState,
    caller: &Caller,
    key: &str,
) -> Result<DriveSettingsView, Problem> {
    let target = state.target(key)?;
    let offline = crate::faces_shared::writes::is_offline(&target);
    let held = state
        .control
        .read_settings(caller, target.control())
        .await
        .map_err(|e| {
            Problem::bus(
                &e,
                BusContext {
                    drive: Some(&target.drive.name),
                    offline,
                    setpoint: false,
                },
            )
        })?;
    DriveSettingsView::new(state, key, &held)
}

/// `?download=`.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct DownloadQuery {
    /// `1` (or `true`): answer as a file to save (`Content-Disposition:
    /// attachment; filename="<drive>-settings.json"`), which `PUT
    /// .../settings` takes back as it is.
    #[serde(default)]
    pub download: Option<DownloadFlag>,
}

/// A yes or no in a query: `1` or `true`, `0` or `false`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ToSchema)]
pub enum DownloadFlag {
    /// Yes.
    #[serde(rename = "1")]
    One,
    /// Yes.
    #[serde(rename = "true")]
    True,
    /// No.
    #[serde(rename = "0")]
    Zero,
    /// No.
    #[serde(rename = "false")]
    False,
}

impl DownloadFlag {
    /// True for yes.
    pub fn on(flag: Option<DownloadFlag>) -> bool {
        matches!(flag, Some(DownloadFlag::One | DownloadFlag::True))
    }
}

/// The drive's setpoints and settings, read from it now (six reads at
/// command priority): the settings document `PUT .../settings` takes.
/// `?download=1` answers it as a file to save.
#[utoipa::path(
    get,
    path = "/api/v1/drives/{drive}/settings",
    tag = "settings",
    security(("bearer" = ["viewer"])),
    params(
        ("drive" = String, Path, description = "Drive name, or its unit number on a single bus"),
        DownloadQuery,
    ),
    responses(
        (status = 200, description = "The values the drive holds", body = DriveSettingsView),
        FreshReadProblems,
    )
)]
pub async fn get_settings(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    Params(query): Params<DownloadQuery>,
) -> Result<Response, Problem> {
    let view = read(&state, &caller, &key).await?;
    if !DownloadFlag::on(query.download) {
        return Ok(Json(view).into_response());
    }
    // Drive names are letters, digits, '-', '_' and '.': safe in a header.
    let disposition = format!("attachment; filename=\"{}-settings.json\"", view.drive);
    let mut response = Json(view).into_response();
    if let Ok(value) = HeaderValue::from_str(&disposition) {
        response
            .headers_mut()
            .insert(header::CONTENT_DISPOSITION, value);
    }
    Ok(response)
}
