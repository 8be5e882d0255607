//! What the daemon does to moving motors when nobody is in control any more:
//! a client's lease expired, or the daemon is stopping.

use serde::Deserialize;

use crate::bus::handle::JobOptions;
use crate::bus::{BusError, BusHandle, Origin, Priority, SourceId};
use crate::drive::{ConfigCommand, DriveReply, DriveRequest, Mode, Status};

/// How to stop a motor nobody controls.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StopAction {
    /// Leave it as it is.
    None,
    /// Speed setpoint 0 in speed mode, current 0 in torque mode (ramped
    /// stop); both when the mode is unknown.
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

    /// The requests that carry the action out on a drive whose mode is
    /// `mode`, in order. With the mode unknown (its status could not be
    /// read), zero-speed zeroes both setpoints that can turn the motor:
    /// zeroing only the speed would leave a drive in torque mode pushing.
    pub fn requests(self, mode: Option<Mode>) -> Vec<DriveRequest> {
        match (self, mode) {
            (StopAction::ZeroSpeed, None) => vec![
                DriveRequest::Speed { rpm: 0 },
                DriveRequest::Torque { counts: 0 },
            ],
            (StopAction::None, _) => Vec::new(),
            (StopAction::Brake, _) => vec![DriveRequest::Config(ConfigCommand::EmergencyBrake)],
            (StopAction::ZeroSpeed, Some(mode)) => self.request(mode).into_iter().collect(),
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
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    /// Applied to every moving drive when the daemon stops.
    pub on_shutdown: StopAction,
    /// Applied when a client's setpoint lease runs out.
    pub on_lease_expiry: StopAction,
    /// The lease of a jog from the web console, ms: how long the motor runs
    /// on after the page's last renewal (it renews three times a lease).
    /// Longer rides out a tablet's Wi-Fi hiccups; shorter stops sooner.
    #[serde(deserialize_with = "crate::config::values::int_in::<_, _, 100, 5000>")]
    pub jog_lease_ms: u64,
    /// Where the safety journal is kept (leases, stops owed, brakes), so
    /// a restart keeps every promise made about a motor. `None`: systemd's
    /// `$STATE_DIRECTORY`, else none (nothing survives a restart).
    pub state_dir: Option<std::path::PathBuf>,
    /// Applied at start-up to every drive found moving when the safety
    /// journal could not be read: who asked for what is unknown.
    pub on_unknown_state: StopAction,
}

impl SafetyConfig {
    /// The state directory: `state_dir`, else `$STATE_DIRECTORY` (the
    /// first, when systemd lists several).
    pub fn state_dir(&self) -> Option<std::path::PathBuf> {
        self.state_dir.clone().or_else(|| {
            let env = std::env::var_os("STATE_DIRECTORY")?;
            let first = env.to_string_lossy().split(':').next()?.to_string();
            (!first.is_empty()).then(|| first.into())
        })
    }
}

impl Default for SafetyConfig {
    fn default() -> Self {
        Self {
            on_shutdown: StopAction::ZeroSpeed,
            on_lease_expiry: StopAction::ZeroSpeed,
            jog_lease_ms: 300,
            state_dir: None,
            on_unknown_state: StopAction::ZeroSpeed,
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
/// a moment ago. If that read fails, `fallback` (or the polled copy) is used
/// and the drive is assumed to be moving; with no mode at all, zero-speed
/// zeroes both the speed and the torque setpoint (see
/// [`StopAction::requests`]). With `only_if_moving`, a drive found standing
/// is left alone. `origin` says why, for the bus monitor (a lease's end,
/// the shutdown).
///
/// Every request is tried even if one before it failed (a drive that
/// refused the speed setpoint may still take the torque one); the result is
/// `Ok` only when all of them were confirmed, else the first error.
pub async fn stop_drive(
    bus: &BusHandle,
    unit: u8,
    action: StopAction,
    only_if_moving: bool,
    fallback: Option<Mode>,
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
    if action == StopAction::ZeroSpeed || only_if_moving {
        match bus
            .execute(unit, &DriveRequest::ReadStatus, options.clone())
            .await
        {
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
    let mut failed = None;
    for request in action.requests(outcome.mode) {
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

    #[test]
    fn zero_speed_with_the_mode_unknown_zeroes_both_setpoints() {
        assert_eq!(
            StopAction::ZeroSpeed.requests(None),
            [
                DriveRequest::Speed { rpm: 0 },
                DriveRequest::Torque { counts: 0 }
            ]
        );
        // A known mode: the one setpoint that mode uses, or nothing.
        assert_eq!(
            StopAction::ZeroSpeed.requests(Some(Mode::Torque)),
            [DriveRequest::Torque { counts: 0 }]
        );
        assert!(
            StopAction::ZeroSpeed
                .requests(Some(Mode::Position))
                .is_empty()
        );
        assert_eq!(
            StopAction::Brake.requests(None),
            [DriveRequest::Config(ConfigCommand::EmergencyBrake)]
        );
        assert!(StopAction::None.requests(None).is_empty());
    }
}
