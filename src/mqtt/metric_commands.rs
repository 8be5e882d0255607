//! Commands from a host (DCMD metrics) into the control core, and their
//! results back into metrics. The face decides nothing: the units module
//! refuses values outside the drive's ranges naming the range, and the core
//! checks the role, that the drive is active, and takes the session's
//! communication-loss lease for a setpoint or a mode, exactly as for every
//! other face.

use super::metric::{self, Value, Writable};
use super::sparkplug_b::payload::Metric;
use crate::control::{Caller, Control, ControlRequest, Failure, Target};
use crate::drive::{ConfigCommand, DriveRequest, units};

/// A command a DCMD metric asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct Command {
    /// The metric it came as.
    pub metric: Writable,
    /// The drive request, its value checked against the drive's range.
    pub request: DriveRequest,
}

/// Why a DCMD metric is not a command, in words for `command/last_result`
/// (`.0`), and, when it named a write whose value the drive cannot take
/// (out of range, a mode it does not have), that write in words (`.1`):
/// the core audits it as a refused write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Malformed(pub String, pub Option<String>);

impl Malformed {
    fn shape(words: String) -> Self {
        Malformed(words, None)
    }
}

/// What a DCMD metric asks for; `Ok(None)`: nothing (a command metric
/// written false).
pub fn parse(m: &Metric) -> Result<Option<Command>, Malformed> {
    let name = m.name.as_deref().unwrap_or("");
    let Some(writable) = Writable::from_name(name) else {
        let names: Vec<&str> = Writable::ALL.iter().map(|w| w.name()).collect();
        return Err(Malformed::shape(format!(
            "\"{name}\" is not a writable metric: write one of {}",
            names.join(", ")
        )));
    };
    let request = match writable {
        Writable::Activate | Writable::Deactivate | Writable::Brake | Writable::FaultReset => {
            let Some(on) = metric::as_bool(m) else {
                return Err(Malformed::shape(format!(
                    "{name} takes a Boolean: true runs the command"
                )));
            };
            if !on {
                return Ok(None);
            }
            DriveRequest::Config(match writable {
                Writable::Activate => ConfigCommand::Activate,
                Writable::Deactivate => ConfigCommand::Deactivate,
                Writable::Brake => ConfigCommand::EmergencyBrake,
                _ => ConfigCommand::FaultReset,
            })
        }
        Writable::Mode => {
            let modes = ConfigCommand::modes_in_words();
            let Some(mode) = metric::as_str(m) else {
                return Err(Malformed::shape(format!("{name} takes a String: {modes}")));
            };
            DriveRequest::Config(ConfigCommand::mode_named(mode).ok_or_else(|| {
                Malformed(
                    format!("{name}: \"{mode}\" is not a mode of the drive: the mode is {modes}"),
                    Some(format!("mode \"{mode}\"")),
                )
            })?)
        }
        Writable::SpeedRpm | Writable::PositionDeg | Writable::TorqueA => {
            let Some(v) = metric::as_f64(m) else {
                return Err(Malformed::shape(format!("{name} takes a number")));
            };
            let range = |e: crate::drive::RangeError| {
                Malformed(format!("{name}: {e}"), Some(e.attempted()))
            };
            match writable {
                Writable::SpeedRpm => DriveRequest::Speed {
                    rpm: units::speed_setpoint(v).map_err(range)?,
                },
                Writable::PositionDeg => DriveRequest::Position {
                    centideg: units::position_setpoint(v).map_err(range)?,
                },
                _ => DriveRequest::Torque {
                    counts: units::torque_setpoint(v).map_err(range)?,
                },
            }
        }
    };
    Ok(Some(Command {
        metric: writable,
        request,
    }))
}

/// The value the drive confirmed, as the metric carries it.
pub fn confirmed_value(command: &Command) -> Value {
    match command.request {
        DriveRequest::Speed { rpm } => Value::Double(f64::from(rpm)),
        DriveRequest::Position { centideg } => Value::Double(f64::from(centideg) / 100.0),
        DriveRequest::Torque { counts } => Value::Double(f64::from(counts) / 128.0),
        DriveRequest::Config(
            ConfigCommand::SpeedMode | ConfigCommand::PositionMode | ConfigCommand::TorqueMode,
        ) => Value::Text(
            match command.request {
                DriveRequest::Config(ConfigCommand::SpeedMode) => "speed",
                DriveRequest::Config(ConfigCommand::PositionMode) => "position",
                _ => "torque",
            }
            .to_string(),
        ),
        // A command metric reads false again once it ran.
        _ => Value::Bool(false),
    }
}

/// Sends `command` to `target` through the core for `caller` (an MQTT
/// session's caller), and returns once the drive confirmed it or the
/// failure in words.
pub async fn run(
    control: &Control,
    caller: &Caller,
    target: Target,
    command: &Command,
) -> Result<(), Failure> {
    control
        .write(caller, target, ControlRequest::drive(command.request))
        .await
        .map(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mqtt::metric::metric as make;
    use crate::mqtt::sparkplug_b::DataType;

    #[test]
    fn setpoints_are_checked_against_the_drive_range() {
        let m = make(
            "setpoint/speed_rpm",
            DataType::Double,
            Value::Double(150.0),
            0,
        );
        let c = parse(&m).unwrap().unwrap();
        assert_eq!(c.request, DriveRequest::Speed { rpm: 150 });
        assert_eq!(confirmed_value(&c), Value::Double(150.0));
        let m = make("setpoint/speed_rpm", DataType::Int32, Value::Int(-3000), 0);
        let e = parse(&m).unwrap_err();
        assert!(e.0.contains("-2048"), "{}", e.0);
        assert_eq!(e.1.as_deref(), Some("speed setpoint -3000 rpm"));
    }

    #[test]
    fn commands_modes_and_nonsense() {
        let m = make("command/brake", DataType::Boolean, Value::Bool(true), 0);
        assert_eq!(
            parse(&m).unwrap().unwrap().request,
            DriveRequest::Config(ConfigCommand::EmergencyBrake)
        );
        let m = make("command/brake", DataType::Boolean, Value::Bool(false), 0);
        assert_eq!(parse(&m).unwrap(), None);
        let m = make("mode", DataType::String, Value::Text("torque".into()), 0);
        let c = parse(&m).unwrap().unwrap();
        assert_eq!(confirmed_value(&c), Value::Text("torque".into()));
        let m = make("mode", DataType::String, Value::Text("fast".into()), 0);
        let e = parse(&m).unwrap_err();
        assert!(e.0.contains("speed, position or torque"), "{}", e.0);
        assert_eq!(e.1.as_deref(), Some("mode \"fast\""));
        let m = make("status/speed_rpm", DataType::Int32, Value::Int(1), 0);
        let e = parse(&m).unwrap_err();
        assert!(e.0.contains("not a writable metric"));
        assert_eq!(e.1, None);
    }
}
