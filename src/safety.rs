//! What the daemon does to moving motors when nobody is in control any more:
//! a client's lease expired, or the daemon is stopping.

use serde::Deserialize;

use crate::drive::{ConfigCommand, DriveRequest};

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
