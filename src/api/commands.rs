//! Config commands (manual 1.3): activate, deactivate, calibrate,
//! fine-tune, set zero, brake, the resets, and the mode changes.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::auth::Caller;
use super::control::{self, Written};
use super::extract::{JsonBody, Params, PathParams};
use super::openapi::WriteProblems;
use super::problem::{Kind, Problem};
use super::state::ApiState;
use crate::control::ControlRequest;
use crate::control::policy::of_request as request_meaning;
use crate::drive::{ConfigCommand, DriveRequest};

/// What a command did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct CommandReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// The command's name.
    pub command: String,
    /// What was written; the drive echoed it.
    pub written: Vec<Written>,
    /// Bus priority it went with: `emergency` for the brake, else `command`.
    pub priority: String,
    /// What to expect next, when there is something to know.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// `?force=`.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct CommandQuery {
    /// factory-reset writes flash, which the manual allows only at
    /// standstill, and calibrate and fine-tune turn the motor on their
    /// own: `force=true` sends them while the motor turns.
    #[serde(default)]
    pub force: bool,
}

fn note(command: ConfigCommand) -> Option<&'static str> {
    Some(match command {
        ConfigCommand::Activate => "activation is kept over power loss",
        ConfigCommand::Deactivate => "the drive no longer takes setpoints; any lease on it ended",
        ConfigCommand::Calibrate => {
            "calibration takes about 4 s and nudges the motor; the status's calibrated flag is set when it is done"
        }
        ConfigCommand::FineTuneCalibration => {
            "fine-tuning takes about 2 s and turns the motor both ways"
        }
        ConfigCommand::SetZero => "the new zero is lost when the drive loses power",
        ConfigCommand::EmergencyBrake => {
            "the motor is held; any setpoint or mode command releases the brake; any lease on it ended"
        }
        ConfigCommand::FactoryReset => {
            "ramps, stall protection and load inertia are back to factory values, in flash too"
        }
        ConfigCommand::SoftReset => "the drive restarts and does not answer for a moment",
        ConfigCommand::FaultReset => "a stall is cleared; a fault whose cause remains comes back",
        ConfigCommand::SpeedMode | ConfigCommand::PositionMode | ConfigCommand::TorqueMode => {
            return None;
        }
    })
}

/// Sends config command `command` to drive `key` for `caller`.
pub async fn run(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    command: ConfigCommand,
    force: bool,
) -> Result<CommandReply, Problem> {
    let target = state.target(key)?;
    let request = DriveRequest::Config(command);
    control::send(
        state,
        caller,
        target.clone(),
        ControlRequest::drive(request).forced(force),
    )
    .await?;
    Ok(CommandReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        command: command.name().to_string(),
        written: control::written(&request),
        priority: if request_meaning(&request).emergency {
            "emergency"
        } else {
            "command"
        }
        .to_string(),
        note: note(command).map(str::to_string),
    })
}

/// The command named `name`, or 404 listing the valid names.
pub fn parse_command(name: &str) -> Result<ConfigCommand, Problem> {
    ConfigCommand::from_name(name).ok_or_else(|| {
        let names: Vec<&str> = ConfigCommand::ALL.iter().map(|c| c.name()).collect();
        Problem::new(
            Kind::UnknownCommand,
            format!(
                "no command named \"{name}\": valid commands are {}",
                names.join(", ")
            ),
        )
    })
}

/// Sends a config command; it returns once the drive echoed it.
///
/// `activate`, `deactivate`, `set-zero`, `brake`, `soft-reset`,
/// `fault-reset` and the mode commands need the operator role; `calibrate`,
/// `fine-tune` and `factory-reset` the admin role. The brake goes ahead of
/// everything else on the bus.
#[utoipa::path(
    post,
    path = "/api/v1/drives/{drive}/commands/{command}",
    tag = "commands",
    security(("bearer" = ["operator"])),
    params(
        ("drive" = String, Path, description = "Drive name, or its unit number on a single bus"),
        ("command" = String, Path, description = "activate, deactivate, calibrate, fine-tune, set-zero, brake, factory-reset, soft-reset, fault-reset (also speed-mode, position-mode, torque-mode)"),
        CommandQuery,
    ),
    responses(
        (status = 200, description = "The drive confirmed the command", body = CommandReply),
        WriteProblems,
    )
)]
pub async fn post_command(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams((key, name)): PathParams<(String, String)>,
    Params(query): Params<CommandQuery>,
) -> Result<Json<CommandReply>, Problem> {
    let command = parse_command(&name)?;
    run(&state, &caller, &key, command, query.force)
        .await
        .map(Json)
}

/// A closed-loop mode the drive can be put in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModeChoice {
    /// Speed closed loop (setpoint `speed_rpm`).
    Speed,
    /// Position closed loop (setpoint `position_deg`).
    Position,
    /// Torque closed loop (setpoint `torque_a` or `torque_counts`).
    Torque,
}

/// `PUT .../mode` body.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ModeBody {
    /// The mode.
    pub mode: ModeChoice,
}

impl ModeChoice {
    /// The config command that selects it.
    pub fn command(self) -> ConfigCommand {
        match self {
            ModeChoice::Speed => ConfigCommand::SpeedMode,
            ModeChoice::Position => ConfigCommand::PositionMode,
            ModeChoice::Torque => ConfigCommand::TorqueMode,
        }
    }
}

/// Puts the drive in speed, position or torque mode (operator).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/mode",
    tag = "commands",
    security(("bearer" = ["operator"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body = ModeBody,
    responses(
        (status = 200, description = "The drive confirmed the mode command", body = CommandReply),
        WriteProblems,
    )
)]
pub async fn put_mode(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<ModeBody>,
) -> Result<Json<CommandReply>, Problem> {
    run(&state, &caller, &key, body.mode.command(), false)
        .await
        .map(Json)
}
