//! The stream's command messages translated once for every face that
//! takes them (the WebSocket stream, MQTT's JSON format): an operation's
//! name and body into a request for the control core, and the reply it
//! gets (what was written, the lease now covering the motor, a status).
//! The refusals are [`Problem`]s, worded as the REST API words them.

use std::time::Duration;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;

use super::integers;
use super::problem::{Kind, Problem};
use super::status;
use super::target::Target;
use super::writes;
use crate::control::lease_book::Holder;
use crate::control::policy::of_request as request_meaning;
use crate::control::written::{Written, written};
use crate::control::{Caller, Control, ControlRequest, LeaseView};
use crate::drive::{ConfigCommand, DriveRequest, units};

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

/// Sends config command `command` to `target` for `caller`.
pub(crate) async fn run(
    control: &Control,
    caller: &Caller,
    target: &Target,
    command: ConfigCommand,
    force: bool,
) -> Result<CommandReply, Problem> {
    let request = DriveRequest::Config(command);
    writes::send(
        control,
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
        written: written(&request),
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
    // Read as a string, so that a mode the drive does not have is refused
    // by `set_mode`, audited like any refused write.
    /// The mode.
    #[schema(value_type = ModeChoice)]
    pub mode: String,
}

/// Puts `target` in the mode `body` names, for `caller`. A mode the
/// drive does not have is refused naming the modes, and audited.
pub(crate) async fn set_mode(
    control: &Control,
    caller: &Caller,
    target: &Target,
    body: &ModeBody,
) -> Result<CommandReply, Problem> {
    let Some(command) = ConfigCommand::mode_named(&body.mode) else {
        let why = format!(
            "\"{}\" is not a mode of the drive: the mode is {}",
            body.mode,
            ConfigCommand::modes_in_words()
        );
        writes::refused(
            control,
            caller,
            target,
            format!("mode \"{}\"", body.mode),
            &why,
        );
        return Err(Problem::invalid(why));
    };
    run(control, caller, target, command, false).await
}

/// A lease as clients see it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct LeaseInfo {
    /// The drive it covers.
    pub drive: String,
    /// Who holds it: a token's name, or a Modbus TCP client's face and
    /// address ("modbus-tcp 10.1.2.3:50412").
    pub owner: String,
    /// Its length: each renewal pushes the deadline this far ahead.
    pub lease_ms: u64,
    /// Time left before the stop action, ms.
    pub expires_in_ms: u64,
    /// What its end sends: `zero-speed`, `brake`, or `none`.
    pub action: String,
    /// True when it also ends as soon as its WebSocket closes.
    pub websocket: bool,
    /// True for a lease of a Modbus TCP client's communication-loss
    /// function (`comm_loss_ms` of its network): any request on its
    /// connection renews it; `lease_ms` without one, or the connection
    /// closing, ends it with `action`.
    pub comm_loss: bool,
}

impl LeaseInfo {
    /// The core's view of a lease on drive `drive`.
    pub fn new(drive: &str, view: &LeaseView) -> Self {
        let session = matches!(view.holder, Holder::Session(_));
        LeaseInfo {
            drive: drive.to_string(),
            owner: view.owner.to_string(),
            lease_ms: millis_u64(view.length),
            expires_in_ms: millis_u64(view.expires_in),
            action: view.action.name().to_string(),
            websocket: session && !view.comm_loss && view.comm_loss_face.is_none(),
            comm_loss: view.comm_loss,
        }
    }
}

/// `PUT .../setpoint` body: exactly one setpoint, and optionally a lease.
/// Its OpenAPI schema is in `api::body_schemas`.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetpointBody {
    /// Speed at the gearbox output, rpm (-2048..2047, rounded to 1 rpm).
    pub speed_rpm: Option<f64>,
    /// Position at the gearbox output, degrees (-180..180, rounded to 0.01).
    pub position_deg: Option<f64>,
    /// Motor current, amps (-16..15.99, rounded to 1/128 A).
    pub torque_a: Option<f64>,
    /// Motor current, raw counts (-2048..2047; 1 A = 128).
    #[serde(default, deserialize_with = "integers::optional")]
    pub torque_counts: Option<i64>,
    /// Stop the motor (`[safety] on_lease_expiry`) unless the setpoint is
    /// repeated or the lease renewed within this many ms.
    #[serde(default, deserialize_with = "integers::optional")]
    pub lease_ms: Option<i64>,
}

impl SetpointBody {
    /// What the body asks for, in words ("speed setpoint 5000 rpm"): the
    /// audit's account of a refused setpoint.
    pub fn attempted(&self) -> String {
        let asked: Vec<String> = [
            self.speed_rpm.map(|v| format!("speed setpoint {v} rpm")),
            self.position_deg
                .map(|v| format!("position setpoint {v} deg")),
            self.torque_a.map(|v| format!("torque setpoint {v} A")),
            self.torque_counts
                .map(|v| format!("torque setpoint {v} counts")),
        ]
        .into_iter()
        .flatten()
        .collect();
        if asked.is_empty() {
            "a setpoint without a value".to_string()
        } else {
            asked.join(" and ")
        }
    }

    /// The drive request, with values checked against the manual's ranges.
    pub fn request(&self) -> Result<DriveRequest, Problem> {
        let given: Vec<&str> = [
            self.speed_rpm.map(|_| "speed_rpm"),
            self.position_deg.map(|_| "position_deg"),
            self.torque_a.map(|_| "torque_a"),
            self.torque_counts.map(|_| "torque_counts"),
        ]
        .into_iter()
        .flatten()
        .collect();
        if given.len() != 1 {
            return Err(Problem::invalid(format!(
                "give exactly one of speed_rpm, position_deg, torque_a or torque_counts (found {})",
                if given.is_empty() {
                    "none".to_string()
                } else {
                    given.join(" and ")
                }
            )));
        }
        Ok(match self {
            SetpointBody {
                speed_rpm: Some(rpm),
                ..
            } => DriveRequest::Speed {
                rpm: units::speed_setpoint(*rpm)?,
            },
            SetpointBody {
                position_deg: Some(deg),
                ..
            } => DriveRequest::Position {
                centideg: units::position_setpoint(*deg)?,
            },
            SetpointBody {
                torque_a: Some(a), ..
            } => DriveRequest::Torque {
                counts: units::torque_setpoint(*a)?,
            },
            SetpointBody {
                torque_counts: Some(c),
                ..
            } => DriveRequest::Torque {
                counts: units::torque_setpoint_counts(*c)?,
            },
            _ => return Err(Problem::invalid("no setpoint given")),
        })
    }
}

/// What a setpoint did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SetpointReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// What was written (engineering units and raw); the drive echoed it.
    pub written: Vec<Written>,
    /// The lease now covering the motor, if any.
    pub lease: Option<LeaseInfo>,
}

/// Sends a setpoint to `target` for `caller`, with a lease of `lease_ms`
/// (or `lease_default`) when one is asked for; a lease taken in a session
/// (a WebSocket, MQTT) ends with its session too.
pub(crate) async fn apply(
    control: &Control,
    caller: &Caller,
    target: &Target,
    body: &SetpointBody,
    lease_default: Option<Duration>,
) -> Result<SetpointReply, Problem> {
    let request = body.request().inspect_err(|p| {
        writes::refused(control, caller, target, body.attempted(), &p.detail);
    })?;
    let lease = body.lease_ms.map(lease_length).or(lease_default);
    let sent = writes::send(
        control,
        caller,
        target.clone(),
        ControlRequest::drive(request).with_lease(lease),
    )
    .await;
    let lease = lease_of(control, target.index);
    sent?;
    Ok(SetpointReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        written: written(&request),
        lease,
    })
}

/// A lease length a client asked for (`lease_ms` of a setpoint or a
/// renewal), which the core checks against its bounds. A negative length
/// asks for 0 ms, which no bound allows.
pub(crate) fn lease_length(ms: i64) -> Duration {
    Duration::from_millis(u64::try_from(ms).unwrap_or(0))
}

/// The lease on drive `index` of the plant, as clients see it.
pub(crate) fn lease_of(control: &Control, index: usize) -> Option<LeaseInfo> {
    let view = control.lease(index)?;
    let name = control.plant().now().drive_at(index)?.name.clone();
    Some(LeaseInfo::new(&name, &view))
}

fn millis_u64(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// A command message, as the WebSocket stream takes it:
/// `{"type": "command", "id": 1, "op": "setpoint", "drive": "conveyor",
/// "body": {"speed_rpm": 100}}` (the MQTT face takes the drive from the
/// topic, so `drive` may be left out there).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case", deny_unknown_fields)]
pub(crate) enum CommandMessage {
    /// Run an operation; answered with a reply carrying the same `id`.
    Command {
        /// Any JSON value; echoed in the reply.
        #[serde(default)]
        id: Value,
        /// The operation.
        op: String,
        /// The drive.
        #[serde(default)]
        drive: Option<String>,
        /// The operation's body, as for the REST route.
        #[serde(default)]
        body: Option<Value>,
    },
}

/// `{"force": bool}`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ForceBody {
    #[serde(default)]
    force: bool,
}

/// `{"fresh": bool}`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FreshBody {
    #[serde(default)]
    fresh: bool,
}

/// The body of a command message as `T`: none is `{}`, anything but an
/// object is refused.
pub(crate) fn body_as<T: DeserializeOwned>(op: &str, body: Option<Value>) -> Result<T, Problem> {
    let body = match body {
        None => Value::Object(Default::default()),
        // serde would read a struct from an array, field by field.
        Some(object @ Value::Object(_)) => object,
        Some(_) => {
            return Err(Problem::invalid(format!(
                "the body of \"{op}\" must be a JSON object ({{...}})"
            )));
        }
    };
    serde_json::from_value(body)
        .map_err(|e| Problem::invalid(format!("the body of \"{op}\" is not valid: {e}")))
}

/// `value` as a reply's JSON.
pub(crate) fn json<T: serde::Serialize>(value: T) -> Result<Value, Problem> {
    serde_json::to_value(value)
        .map_err(|e| Problem::new(Kind::Internal, format!("cannot encode the reply: {e}")))
}

/// The operations on one drive that every face with command messages
/// offers (the stream, MQTT's JSON format).
pub(crate) const DRIVE_OPS: &str = "a command name (activate, deactivate, calibrate, fine-tune, set-zero, brake, factory-reset, soft-reset, fault-reset), mode, setpoint, status";

/// Whether `op` is one of [`DRIVE_OPS`].
pub(crate) fn is_drive_op(op: &str) -> bool {
    matches!(op, "mode" | "setpoint" | "status") || ConfigCommand::from_name(op).is_some()
}

/// Runs drive operation `op` (one of [`DRIVE_OPS`]) with `body` on the
/// drive named `key` for `caller`: its reply as JSON, or the problem. The
/// body is read before the drive is looked up, as the REST routes do.
pub(crate) async fn run_drive_op(
    control: &Control,
    caller: &Caller,
    key: &str,
    op: &str,
    body: Option<Value>,
    lease_default: Option<Duration>,
) -> Result<Value, Problem> {
    let target = || Target::find(control.plant(), key);
    match op {
        "mode" => {
            let b: ModeBody = body_as(op, body)?;
            json(set_mode(control, caller, &target()?, &b).await?)
        }
        "setpoint" => {
            let b: SetpointBody = body_as(op, body)?;
            json(apply(control, caller, &target()?, &b, lease_default).await?)
        }
        "status" => {
            let b: FreshBody = body_as(op, body)?;
            json(status::status(control, caller, &target()?, b.fresh).await?)
        }
        name => {
            let command = parse_command(name)?;
            let b: ForceBody = body_as(op, body)?;
            json(run(control, caller, &target()?, command, b.force).await?)
        }
    }
}
