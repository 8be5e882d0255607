//! What the daemon does to moving motors when nobody is in control any more:
//! a client's lease expired, or the daemon is stopping.

use crate::bus::handle::JobOptions;
use crate::bus::{BusError, BusHandle, Origin, Priority, SourceId};
pub use crate::config::{SafetyConfig, StopAction};
use crate::drive::{ConfigCommand, DriveReply, DriveRequest, Mode, Status};

/// The requests that carry `action` out on a drive whose mode is
/// `mode`, in order. With the mode unknown (its status could not be
/// read), zero-speed zeroes both setpoints that can turn the motor:
/// zeroing only the speed would leave a drive in torque mode pushing.
pub fn requests(action: StopAction, mode: Option<Mode>) -> Vec<DriveRequest> {
    match (action, mode) {
        (StopAction::ZeroSpeed, None) => vec![
            DriveRequest::Speed { rpm: 0 },
            DriveRequest::Torque { counts: 0 },
        ],
        (StopAction::None, _) => Vec::new(),
        (StopAction::Brake, _) => vec![DriveRequest::Config(ConfigCommand::EmergencyBrake)],
        (StopAction::ZeroSpeed, Some(mode)) => request(action, mode).into_iter().collect(),
    }
}

/// The request that carries `action` out on a drive in `mode`; `None`
/// when there is nothing to send.
pub fn request(action: StopAction, mode: Mode) -> Option<DriveRequest> {
    match (action, mode) {
        (StopAction::None, _) => None,
        (StopAction::Brake, _) => Some(DriveRequest::Config(ConfigCommand::EmergencyBrake)),
        (StopAction::ZeroSpeed, Mode::Torque) => Some(DriveRequest::Torque { counts: 0 }),
        (StopAction::ZeroSpeed, Mode::Speed) => Some(DriveRequest::Speed { rpm: 0 }),
        // Position mode holds its position; open loop has no setpoint to zero.
        (StopAction::ZeroSpeed, Mode::Position | Mode::OpenLoop) => None,
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
    /// A second request, confirmed after `sent`: with the mode unknown,
    /// zero-speed zeroes the torque setpoint too.
    pub also_sent: Option<DriveRequest>,
}

impl StopOutcome {
    /// Every request sent and confirmed, in order (for the audit log).
    pub fn requests(&self) -> impl Iterator<Item = &DriveRequest> {
        self.sent.iter().chain(self.also_sent.iter())
    }
}

/// Applies `action` to the drive at `unit`, at emergency priority.
///
/// What to send depends on the drive's mode (zero speed is a zero current
/// setpoint in torque mode and nothing in position mode), so the mode is
/// read from the drive now: the polled copy may predate a mode command sent
/// a moment ago. If that read fails, the mode is unknown and the drive is
/// assumed to be moving: zero-speed zeroes both the speed and the torque
/// setpoint (see [`requests`]). No mode is guessed: the one a lease was
/// taken in, or the last poll's, may be out of date (a mode command the
/// drive did not confirm, another face's since), and zeroing the wrong
/// setpoint leaves the motor turning. With `only_if_moving`, a drive found
/// standing is left alone. `origin` says why, for the bus monitor (a
/// lease's end, the shutdown).
///
/// Every request is tried even if one before it failed (a drive that
/// refused the speed setpoint may still take the torque one); the result is
/// `Ok` only when all of them were confirmed, else the first error.
pub async fn stop_drive(
    bus: &BusHandle,
    unit: u8,
    action: StopAction,
    only_if_moving: bool,
    origin: Origin,
) -> Result<StopOutcome, BusError> {
    // From the daemon itself at emergency priority: the queue never refuses
    // these for its limits, so stopping every drive at once is not "busy".
    let options = JobOptions {
        source: SourceId::INTERNAL,
        origin,
        ..JobOptions::with_priority(Priority::Emergency)
    };
    let mut outcome = StopOutcome {
        mode: None,
        moving: true,
        sent: None,
        also_sent: None,
    };
    if action == StopAction::None {
        return Ok(outcome);
    }
    if (action == StopAction::ZeroSpeed || only_if_moving)
        && let Ok(DriveReply::Status(s)) = bus
            .execute(unit, &DriveRequest::ReadStatus, options.clone())
            .await
    {
        outcome.mode = Some(s.mode());
        outcome.moving = is_moving(&s);
    }
    if only_if_moving && !outcome.moving {
        return Ok(outcome);
    }
    let mut failed = None;
    for request in requests(action, outcome.mode) {
        match bus.execute(unit, &request, options.clone()).await {
            Ok(_) if outcome.sent.is_none() => outcome.sent = Some(request),
            Ok(_) => outcome.also_sent = Some(request),
            Err(e) => {
                failed.get_or_insert(e);
            }
        }
    }
    match failed {
        Some(e) => Err(e),
        None => Ok(outcome),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::Mode;

    #[test]
    fn actions_by_mode() {
        assert_eq!(
            request(StopAction::ZeroSpeed, Mode::Speed),
            Some(DriveRequest::Speed { rpm: 0 })
        );
        assert_eq!(
            request(StopAction::ZeroSpeed, Mode::Torque),
            Some(DriveRequest::Torque { counts: 0 })
        );
        assert_eq!(request(StopAction::ZeroSpeed, Mode::Position), None);
        assert_eq!(
            request(StopAction::Brake, Mode::Position),
            Some(DriveRequest::Config(ConfigCommand::EmergencyBrake))
        );
        assert_eq!(request(StopAction::None, Mode::Speed), None);
    }

    #[test]
    fn zero_speed_with_the_mode_unknown_zeroes_both_setpoints() {
        assert_eq!(
            requests(StopAction::ZeroSpeed, None),
            [
                DriveRequest::Speed { rpm: 0 },
                DriveRequest::Torque { counts: 0 }
            ]
        );
        // A known mode: the one setpoint that mode uses, or nothing.
        assert_eq!(
            requests(StopAction::ZeroSpeed, Some(Mode::Torque)),
            [DriveRequest::Torque { counts: 0 }]
        );
        assert!(requests(StopAction::ZeroSpeed, Some(Mode::Position)).is_empty());
        assert_eq!(
            requests(StopAction::Brake, None),
            [DriveRequest::Config(ConfigCommand::EmergencyBrake)]
        );
        assert!(requests(StopAction::None, None).is_empty());
    }
}
