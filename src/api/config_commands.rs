//! Config commands (manual 1.3): activate, deactivate, calibrate,
//! fine-tune, set zero, brake, the resets, and the mode changes.

use axum::Json;
use axum::extract::State;
use serde::Deserialize;
use utoipa::IntoParams;

use super::extract::{JsonBody, Params, PathParams};
use super::problem_response::Problem;
use super::problem_response::WriteProblems;
use super::state::ApiState;
use crate::control::Caller;
use crate::drive::ConfigCommand;
use crate::faces_shared::command_messages::set_mode;
pub use crate::faces_shared::command_messages::{
    CommandReply, ModeBody, ModeChoice, parse_command,
};

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

/// Sends config command `command` to drive `key` for `caller`.
pub async fn run(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    command: ConfigCommand,
    force: bool,
) -> Result<CommandReply, Problem> {
    let target = state.target(key)?;
    crate::faces_shared::command_messages::run(&state.control, caller, &target, command, force)
        .await
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
    let target = state.target(&key)?;
    set_mode(&state.control, &caller, &target, &body)
        .await
        .map(Json)
}
