//! Who may do what: the three roles a token carries and the role each
//! operation needs.
//!
//! - `viewer` reads (drives, status, buses) and watches the stream,
//! - `operator` runs the machine: activation, modes, setpoints and their
//!   leases, the brake, set-zero and the resets that do not touch flash,
//! - `admin` commissions it: protection, ramps, inertia, saves to flash,
//!   calibration, factory reset, RS-485 control, bus scans and addresses.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::drive::ConfigCommand;

/// A token's role; each includes the rights of the ones before it.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize, Serialize, ToSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Reads and the stream.
    Viewer,
    /// Viewer, plus setpoints, modes, brake and resets.
    Operator,
    /// Operator, plus protection, ramps, inertia, saves, calibration,
    /// factory reset, RS-485 control, scans and address setting.
    Admin,
}

impl Role {
    /// Stable name for messages and logs.
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }

    /// True when this role includes `needed`.
    pub fn allows(self, needed: Role) -> bool {
        self >= needed
    }
}

/// The role a config command needs: calibration moves the motor on its own
/// and factory reset rewrites flash, so they are commissioning work.
pub fn for_command(command: ConfigCommand) -> Role {
    match command {
        ConfigCommand::Calibrate
        | ConfigCommand::FineTuneCalibration
        | ConfigCommand::FactoryReset => Role::Admin,
        ConfigCommand::Activate
        | ConfigCommand::Deactivate
        | ConfigCommand::SetZero
        | ConfigCommand::EmergencyBrake
        | ConfigCommand::SoftReset
        | ConfigCommand::FaultReset
        | ConfigCommand::SpeedMode
        | ConfigCommand::PositionMode
        | ConfigCommand::TorqueMode => Role::Operator,
    }
}

/// The role a settings write needs: any write to flash is admin work, and so
/// are the settings themselves (they change how the motor reacts).
pub const SETTINGS: Role = Role::Admin;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles_are_ordered() {
        assert!(Role::Admin.allows(Role::Operator));
        assert!(Role::Operator.allows(Role::Viewer));
        assert!(!Role::Viewer.allows(Role::Operator));
        assert!(!Role::Operator.allows(Role::Admin));
    }

    #[test]
    fn commissioning_commands_need_admin() {
        assert_eq!(for_command(ConfigCommand::FactoryReset), Role::Admin);
        assert_eq!(for_command(ConfigCommand::Calibrate), Role::Admin);
        assert_eq!(for_command(ConfigCommand::EmergencyBrake), Role::Operator);
        assert_eq!(for_command(ConfigCommand::FaultReset), Role::Operator);
    }
}
