//! Drive settings (manual 1.8 to 1.12): over-current protection, the speed
//! and position ramps (by alpha, or by a ramp time solved with the manual's
//! formulas), load inertia, and RS-485 control. All need the admin role;
//! a save to flash is refused while the motor turns unless forced.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::extract::{JsonBody, PathParams};
use super::problem_response::Problem;
use super::problem_response::WriteProblems;
use super::state::{ApiState, Target};
use crate::control::written::{Written, written};
use crate::control::{Caller, ControlRequest};
use crate::drive::{DriveRequest, RangeError, units};
use crate::faces_shared::integers;
use crate::faces_shared::writes;

/// What a settings write did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SettingsReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// What was written (engineering units and raw); the drive acknowledged it.
    pub written: Vec<Written>,
    /// True when the values were also written to flash.
    pub saved: bool,
}

async fn write_settings(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    save: bool,
    force: bool,
    build: impl FnOnce(Target) -> Result<DriveRequest, Problem>,
) -> Result<SettingsReply, Problem> {
    let target = state.target(key)?;
    let request = build(target.clone())?;
    request.validate()?;
    writes::send(
        &state.control,
        caller,
        target.clone(),
        ControlRequest::drive(request).forced(force),
    )
    .await?;
    Ok(SettingsReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        written: written(&request),
        saved: save,
    })
}

/// `PUT .../protection` body. Its OpenAPI schema is in
/// [`super::body_schemas`].
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProtectionBody {
    /// Current limit, amps (0..15.99); or give `limit_counts`.
    pub limit_a: Option<f64>,
    /// Current limit, raw counts (0..2047; 1 A = 128).
    #[serde(default, deserialize_with = "integers::optional")]
    pub limit_counts: Option<i64>,
    /// How long the current may stay over the limit before the drive
    /// stalls the motor, ms (0..60000).
    #[serde(deserialize_with = "integers::integer")]
    pub stall_ms: i64,
    /// Also write to flash (motor must stand still).
    #[serde(default)]
    pub save: bool,
    /// Save even while the motor turns.
    #[serde(default)]
    pub force: bool,
}

/// Writes drive `key`'s over-current protection.
pub async fn protection(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &ProtectionBody,
) -> Result<SettingsReply, Problem> {
    let build = |_: Target| {
        let limit_counts = match (body.limit_a, body.limit_counts) {
            (Some(a), None) => units::current_limit(a)?,
            (None, Some(c)) => units::current_limit_counts(c)?,
            _ => {
                return Err(Problem::invalid(
                    "give exactly one of limit_a or limit_counts",
                ));
            }
        };
        Ok(DriveRequest::OverCurrent {
            limit_counts,
            stall_ms: units::stall_time_ms(body.stall_ms)?,
            save: body.save,
        })
    };
    write_settings(state, caller, key, body.save, body.force, build).await
}

/// Sets the over-current (stall) protection (admin).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/protection",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = ProtectionBody, example = json!({"limit_a": 12.0, "stall_ms": 3000, "save": false})),
    responses(
        (status = 200, description = "The drive acknowledged the protection", body = SettingsReply),
        WriteProblems,
    )
)]
pub async fn put_protection(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<ProtectionBody>,
) -> Result<Json<SettingsReply>, Problem> {
    protection(&state, &caller, &key, &body).await.map(Json)
}

/// `PUT .../ramps/speed` body: `alpha`, or `time_s` with `step_rpm`. Its
/// OpenAPI schema is in [`super::body_schemas`].
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpeedRampBody {
    /// Ramp alpha (0 = ramp off; larger = faster; power-on default 500000).
    #[serde(default, deserialize_with = "integers::optional")]
    pub alpha: Option<i64>,
    /// Time to reach `step_rpm` from standstill, seconds: alpha is solved
    /// with the manual's formula (2) and the drive's gear ratio.
    pub time_s: Option<f64>,
    /// The speed step `time_s` is for, rpm at the gearbox output (1..2047).
    pub step_rpm: Option<f64>,
    /// Also write to flash (motor must stand still).
    #[serde(default)]
    pub save: bool,
    /// Save even while the motor turns.
    #[serde(default)]
    pub force: bool,
}

/// `PUT .../ramps/position` body: `alpha`, or `time_s` with `step_deg`.
/// Its OpenAPI schema is in [`super::body_schemas`].
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PositionRampBody {
    /// Ramp alpha (0 = ramp off; larger = faster; power-on default 500000).
    #[serde(default, deserialize_with = "integers::optional")]
    pub alpha: Option<i64>,
    /// Time to move `step_deg` from standstill, seconds: alpha is solved
    /// with the manual's formula (3).
    pub time_s: Option<f64>,
    /// The move `time_s` is for, degrees at the gearbox output (0.01..360).
    pub step_deg: Option<f64>,
    /// Also write to flash (motor must stand still).
    #[serde(default)]
    pub save: bool,
    /// Save even while the motor turns.
    #[serde(default)]
    pub force: bool,
}

/// What a ramp write did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct RampReply {
    /// `speed` or `position`.
    pub ramp: String,
    /// The alpha written.
    pub alpha: u32,
    /// The step the time is for (rpm or degrees), when one was given.
    pub step: Option<f64>,
    /// Unit of `step`: `rpm` or `deg`.
    pub step_unit: String,
    /// Time the ramp takes over `step` from standstill with this alpha,
    /// seconds (`null` when no step was given or the ramp is off).
    pub time_s: Option<f64>,
    /// The gear ratio used (speed ramps).
    pub gear_ratio: f64,
    /// The write itself.
    #[serde(flatten)]
    pub settings: SettingsReply,
}

fn alpha_value(alpha: i64) -> Result<u32, Problem> {
    let v = RangeError::check_int("ramp alpha", alpha, 0, i64::from(u32::MAX), "")?;
    u32::try_from(v).map_err(|_| Problem::invalid("ramp alpha does not fit 32 bits"))
}

/// Alpha from the body: given, or solved from a time and a step.
fn solve(
    alpha: Option<i64>,
    time_s: Option<f64>,
    step: Option<f64>,
    step_name: &str,
    solve: impl FnOnce(f64, f64) -> Result<u32, RangeError>,
    check_step: impl FnOnce(f64) -> Result<f64, RangeError>,
) -> Result<u32, Problem> {
    match (alpha, time_s, step) {
        (Some(a), None, step) => {
            if let Some(s) = step {
                check_step(s)?;
            }
            alpha_value(a)
        }
        (None, Some(t), Some(s)) => Ok(solve(t, s)?),
        (None, Some(_), None) => Err(Problem::invalid(format!(
            "time_s needs {step_name}: the step the ramp time is for"
        ))),
        _ => Err(Problem::invalid(format!(
            "give either alpha, or time_s with {step_name}"
        ))),
    }
}

/// Writes drive `key`'s speed ramp.
pub async fn speed_ramp(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &SpeedRampBody,
) -> Result<RampReply, Problem> {
    let mut alpha = 0;
    let mut gear = 1.0;
    let build = |t: Target| {
        gear = t.drive.gear_ratio;
        alpha = solve(
            body.alpha,
            body.time_s,
            body.step_rpm,
            "step_rpm",
            |time, rpm| units::speed_ramp_alpha(time, rpm, t.drive.gear_ratio),
            |rpm| {
                RangeError::check(
                    "ramp target speed",
                    rpm.abs(),
                    1.0,
                    units::SPEED_RPM.1 as f64,
                    "rpm",
                )
            },
        )?;
        Ok(DriveRequest::SpeedRamp {
            alpha,
            save: body.save,
        })
    };
    let settings = write_settings(state, caller, key, body.save, body.force, build).await?;
    Ok(RampReply {
        ramp: "speed".to_string(),
        alpha,
        step: body.step_rpm,
        step_unit: "rpm".to_string(),
        time_s: body
            .step_rpm
            .and_then(|rpm| units::speed_ramp_time(alpha, rpm, gear)),
        gear_ratio: gear,
        settings,
    })
}

/// Sets the speed ramp by alpha, or by the time to reach a speed (admin).
///
/// Example: `{"time_s": 0.5, "step_rpm": 200}` solves formula (2),
/// t = 2 * sqrt(r * n / (9.55 * alpha)), with the drive's gear ratio r.
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/ramps/speed",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = SpeedRampBody, examples(
        ("by time" = (value = json!({"time_s": 0.5, "step_rpm": 200}))),
        ("by alpha" = (value = json!({"alpha": 5000, "save": true}))),
    )),
    responses(
        (status = 200, description = "The drive acknowledged the ramp", body = RampReply),
        WriteProblems,
    )
)]
pub async fn put_speed_ramp(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<SpeedRampBody>,
) -> Result<Json<RampReply>, Problem> {
    speed_ramp(&state, &caller, &key, &body).await.map(Json)
}

/// Writes drive `key`'s position ramp.
pub async fn position_ramp(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &PositionRampBody,
) -> Result<RampReply, Problem> {
    let mut alpha = 0;
    let mut gear = 1.0;
    let build = |t: Target| {
        gear = t.drive.gear_ratio;
        alpha = solve(
            body.alpha,
            body.time_s,
            body.step_deg,
            "step_deg",
            units::position_ramp_alpha,
            |deg| RangeError::check("ramp target angle", deg.abs(), 0.01, 360.0, "deg"),
        )?;
        Ok(DriveRequest::PositionRamp {
            alpha,
            save: body.save,
        })
    };
    let settings = write_settings(state, caller, key, body.save, body.force, build).await?;
    Ok(RampReply {
        ramp: "position".to_string(),
        alpha,
        step: body.step_deg,
        step_unit: "deg".to_string(),
        time_s: body
            .step_deg
            .and_then(|deg| units::position_ramp_time(alpha, deg)),
        gear_ratio: gear,
        settings,
    })
}

/// Sets the position ramp by alpha, or by the time to move an angle (admin).
///
/// Example: `{"time_s": 0.25, "step_deg": 180}` solves formula (3),
/// t = 2 * sqrt(pi * theta / (180 * alpha)).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/ramps/position",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = PositionRampBody, examples(
        ("by time" = (value = json!({"time_s": 0.25, "step_deg": 180}))),
        ("by alpha" = (value = json!({"alpha": 200}))),
    )),
    responses(
        (status = 200, description = "The drive acknowledged the ramp", body = RampReply),
        WriteProblems,
    )
)]
pub async fn put_position_ramp(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<PositionRampBody>,
) -> Result<Json<RampReply>, Problem> {
    position_ramp(&state, &caller, &key, &body).await.map(Json)
}

/// `PUT .../inertia` body.
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct InertiaBody {
    /// Load inertia as a multiple of the rotor's (1..65535).
    #[serde(deserialize_with = "integers::integer")]
    #[schema(minimum = 1, maximum = 65535)]
    pub ratio: i64,
    /// Also write to flash (motor must stand still).
    #[serde(default)]
    pub save: bool,
    /// Save even while the motor turns.
    #[serde(default)]
    pub force: bool,
}

/// Writes drive `key`'s load inertia ratio.
pub async fn inertia(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &InertiaBody,
) -> Result<SettingsReply, Problem> {
    let build = |_: Target| {
        Ok(DriveRequest::LoadInertia {
            ratio: units::inertia_ratio(body.ratio)?,
            save: body.save,
        })
    };
    write_settings(state, caller, key, body.save, body.force, build).await
}

/// Sets the load inertia ratio (admin).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/inertia",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = InertiaBody, example = json!({"ratio": 5, "save": true})),
    responses(
        (status = 200, description = "The drive acknowledged the ratio", body = SettingsReply),
        WriteProblems,
    )
)]
pub async fn put_inertia(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<InertiaBody>,
) -> Result<Json<SettingsReply>, Problem> {
    inertia(&state, &caller, &key, &body).await.map(Json)
}

/// `PUT .../rs485-control` body.
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Rs485Body {
    /// True: RS-485 (drivegate) controls the motor and CAN is ignored;
    /// false: CAN controls it and setpoints from here are ignored.
    pub enabled: bool,
}

/// Writes drive `key`'s RS-485 control switch.
pub async fn rs485_control(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &Rs485Body,
) -> Result<SettingsReply, Problem> {
    let build = |_: Target| {
        Ok(DriveRequest::Rs485Control {
            enabled: body.enabled,
        })
    };
    write_settings(state, caller, key, false, false, build).await
}

/// Hands motor control to RS-485 (drivegate) or to CAN (admin).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/rs485-control",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = Rs485Body, example = json!({"enabled": true})),
    responses(
        (status = 200, description = "The drive echoed the switch", body = SettingsReply),
        WriteProblems,
    )
)]
pub async fn put_rs485_control(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<Rs485Body>,
) -> Result<Json<SettingsReply>, Problem> {
    rs485_control(&state, &caller, &key, &body).await.map(Json)
}
