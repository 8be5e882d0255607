//! The stream's commands: each `op` a client sends on the stream runs the
//! operation of its REST route (the same code, the same reply, the same
//! problem), and those every face with command messages offers run in
//! [`crate::faces_shared::command_messages`]. This is the stream's table of operations, as
//! the router ([`super::openapi`]) is HTTP's: both stand above the routes.

use serde_json::Value;

use super::problem_response::Problem;
use super::setpoints::{self, RenewBody};
use super::state::ApiState;
use super::{alarms, buses, document, replacement, scope, settings};
use crate::control::Caller;
use crate::drive::DriveRequest;
use crate::faces_shared::command_messages::{
    body_as, is_drive_op, json, parse_command, run_drive_op,
};

/// A command a client sent: `op` on `drive` (or `bus`), with `body`.
#[derive(Debug, Clone, PartialEq)]
pub struct Command {
    /// The operation.
    pub op: String,
    /// The drive (name, or unit number on a single bus).
    pub drive: Option<String>,
    /// The bus, for `scan`, `set-address` and the `scope-` operations.
    pub bus: Option<String>,
    /// The operation's body, as for the REST route.
    pub body: Option<Value>,
}

impl Command {
    /// True for a write that stops the motor (a brake): the core's meaning
    /// of it says it is carried out even if the socket closes first.
    pub fn survives_its_caller(&self) -> bool {
        parse_command(&self.op).is_ok_and(|c| {
            crate::control::policy::of_request(&DriveRequest::Config(c)).survives_caller()
        })
    }
}

/// Every `op`, as a refusal lists them.
const OPS: &str = "a command name (activate, deactivate, calibrate, fine-tune, set-zero, brake, factory-reset, soft-reset, fault-reset), mode, setpoint, lease-renew, lease-release, status, protection, speed-ramp, position-ramp, inertia, rs485-control, replacement, settings, scan, set-address, scope-arm, scope-trigger, scope-cancel, alarm-ack";

/// Runs `command` for `caller` through the same code as its REST route:
/// the route's reply as JSON, or its problem.
pub async fn run(state: &ApiState, caller: &Caller, command: Command) -> Result<Value, Problem> {
    let Command {
        op,
        drive,
        bus,
        body,
    } = command;
    let op = op.as_str();
    if op == "alarm-ack" {
        let b: alarms::AckBody = body_as(op, body)?;
        return json(alarms::acknowledge(state, caller, b.alarm).await?);
    }
    if matches!(
        op,
        "scan" | "set-address" | "scope-arm" | "scope-trigger" | "scope-cancel"
    ) {
        let bus = bus.ok_or_else(|| Problem::invalid(format!("\"{op}\" needs \"bus\"")))?;
        return match op {
            "scan" => json(buses::scan(state, caller, &bus, &body_as(op, body)?).await?),
            "scope-arm" => json(scope::arm(state, caller, &bus, &body_as(op, body)?)?),
            "scope-trigger" => json(scope::trigger(state, caller, &bus)?),
            "scope-cancel" => json(scope::cancel(state, caller, &bus)?),
            _ => json(buses::set_address(state, caller, &bus, &body_as(op, body)?).await?),
        };
    }
    let known = matches!(
        op,
        "mode"
            | "setpoint"
            | "lease-renew"
            | "lease-release"
            | "status"
            | "protection"
            | "speed-ramp"
            | "position-ramp"
            | "inertia"
            | "rs485-control"
            | "replacement"
            | "settings"
    );
    if !known && parse_command(op).is_err() {
        return Err(Problem::invalid(format!("unknown op \"{op}\": use {OPS}")));
    }
    let key = drive.ok_or_else(|| Problem::invalid(format!("\"{op}\" needs \"drive\"")))?;
    let key = key.as_str();
    if is_drive_op(op) {
        // The operations every face with command messages offers.
        return run_drive_op(
            &state.control,
            caller,
            key,
            op,
            body,
            state.config.lease_default,
        )
        .await;
    }
    match op {
        "lease-renew" => {
            let b: RenewBody = body_as(op, body)?;
            json(setpoints::renew(state, caller, key, &b).await?)
        }
        "lease-release" => json(setpoints::release(state, caller, key).await?),
        "protection" => json(settings::protection(state, caller, key, &body_as(op, body)?).await?),
        "speed-ramp" => json(settings::speed_ramp(state, caller, key, &body_as(op, body)?).await?),
        "position-ramp" => {
            json(settings::position_ramp(state, caller, key, &body_as(op, body)?).await?)
        }
        "inertia" => json(settings::inertia(state, caller, key, &body_as(op, body)?).await?),
        "rs485-control" => {
            json(settings::rs485_control(state, caller, key, &body_as(op, body)?).await?)
        }
        "replacement" => json(replacement::record(state, caller, key, body_as(op, body)?)?),
        "settings" => json(document::apply(state, caller, key, &body_as(op, body)?, false).await?),
        _ => Err(Problem::invalid(format!("unknown op \"{op}\": use {OPS}"))),
    }
}
