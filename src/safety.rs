//! What the daemon does to moving motors when nobody is in control any more:
//! a client's lease expired, or the daemon is stopping.

use serde::Deserialize;

use crate::bus::handle::JobOptions;
use crate::bus::{BusError, BusHandle, Priority, SourceId};
use crate::drive::{ConfigCommand, DriveReply, DriveRequest, Mode, Status};

/// How to stop a motor nobody controls.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StopAction {
    /// Leave it as it is.
    None,
    /// Speed setpoint 0 in speed mode, current 0 in torque mode (ramped stop).
    #[default]
    ZeroSpeed,
    /// Emergency brake.
    Brake,
}

impl StopAction {
    /// Stable name for logs and the API.
    pub fn name(self) -> &'static str {
        match self {
            StopAction::None => "none",
            StopAction::ZeroSpeed => "zero-speed",
            StopAction::Brake => "brake",
        }
    }

    /// The request that carries the action out on a drive in `mode`; `None`
    /// when there is nothing to send.
    pub fn request(self, mode: crate::drive::Mode) -> Option<DriveRequest> {
        use crate::drive::Mode;
        match (self, mode) {
            (StopAction::None, _) => None,
            (StopAction::Brake, _) => Some(DriveRequest::Config(ConfigCommand::EmergencyBrake)),
            (StopAction::ZeroSpeed, Mode::Torque) => Some(DriveRequest::Torque { counts: 0 }),
            (StopAction::ZeroSpeed, Mode::Speed) => Some(DriveRequest::Speed { rpm: 0 }),
            // Position mode holds its position; open loop has no setpoint to zero.
            (StopAction::ZeroSpeed, Mode::Position | Mode::OpenLoop) => None,
        }
    }
}

/// `[safety]` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    /// Applied to every moving drive when the daemon stops.
    pub on_shutdown: StopAction,
    /// Applied when a client's setpoint lease runs out.
    pub on_lease_expiry: StopAction,
}

impl Default for SafetyConfig {
    fn default() -> Self {
        Self {
            on_shutdown: StopAction::ZeroSpeed,
            on_lease_expiry: StopAction::ZeroSpeed,
        }
    }
}

/// True when the status shows the motor turning or pushing.
pub fn is_moving(status: &Status) -> bool {
    // 16 counts = 0.125 A: below that the current is sensor noise at rest.
    status.speed_rpm != 0 || status.current_counts.unsigned_abs() > 16
}

/// What [`stop_drive`] found and did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StopOutcome {
    /// The mode the decision was made on (`None` if it was not needed).
    pub mode: Option<Mode>,
    /// Whether the drive was moving (assumed when it could not be read).
    pub moving: bool,
    /// The request sent and confirmed, if any.
    pub sent: Option<DriveRequest>,
}

/// Applies `action` to the drive at `unit`, at emergency priority.
///
/// What to send depends on the drive's mode (zero speed is a zero current
/// setpoint in torque mode and nothing in position mode), so the mode is
/// read from the drive now: the polled copy may predate a mode command sent
/// a moment ago. If that read fails, `fallback` (or the polled copy) is used
/// and the drive is assumed to be moving. With `only_if_moving`, a drive
/// found standing is left alone.
pub async fn stop_drive(
    bus: &BusHandle,
    unit: u8,
    action: StopAction,
    only_if_moving: bool,
    fallback: Option<Mode>,
) -> Result<StopOutcome, BusError> {
    // From the daemon itself at emergency priority: the queue never refuses
    // these for its limits, so stopping every drive at once is not "busy".
    let options = JobOptions {
        source: SourceId::INTERNAL,
        ..JobOptions::with_priority(Priority::Emergency)
    };
    let mut outcome = StopOutcome {
        mode: None,
        moving: true,
        sent: None,
    };
    if action == StopAction::None {
        return Ok(outcome);
    }
    if action == StopAction::ZeroSpeed || only_if_moving {
        match bus.execute(unit, &DriveRequest::ReadStatus, options).await {
            Ok(DriveReply::Status(s)) => {
                outcome.mode = Some(s.mode());
                outcome.moving = is_moving(&s);
            }
            _ => {
                outcome.mode =
                    fallback.or_else(|| bus.drive(unit).and_then(|d| d.status).map(|s| s.mode()));
            }
        }
    }
    if only_if_moving && !outcome.moving {
        return Ok(outcome);
    }
    let request = match action {
        StopAction::Brake => Some(DriveRequest::Config(ConfigCommand::EmergencyBrake)),
        // Mode unknown (never read): zero both setpoints that can turn it.
        _ => match outcome.mode {
            Some(mode) => action.request(mode),
            None => Some(DriveRequest::Speed { rpm: 0 }),
        },
    };
    if let Some(request) = request {
        bus.execute(unit, &request, options).await?;
        outcome.sent = Some(request);
    }
    Ok(outcome)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::Mode;

    #[test]
    fn actions_by_mode() {
        assert_eq!(
            StopAction::ZeroSpeed.request(Mode::Speed),
            Some(DriveRequest::Speed { rpm: 0 })
        );
        assert_eq!(
            StopAction::ZeroSpeed.request(Mode::Torque),
            Some(DriveRequest::Torque { counts: 0 })
        );
        assert_eq!(StopAction::ZeroSpeed.request(Mode::Position), None);
        assert_eq!(
            StopAction::Brake.request(Mode::Position),
            Some(DriveRequest::Config(ConfigCommand::EmergencyBrake))
        );
        assert_eq!(StopAction::None.request(Mode::Speed), None);
    }
}
