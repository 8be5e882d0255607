//! The twelve values of the CONFIG register (manual 1.3).

use crate::listed::listed_enum;

listed_enum! {
    /// A config command written to CONFIG (0x0002); the drive echoes it.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum ConfigCommand {
        /// 0x0: enable the drive; only an active drive takes setpoints. Kept over power loss.
        Activate,
        /// 0x1: disable the drive. Kept over power loss.
        Deactivate,
        /// 0x2: calibrate the encoder angle (about 4 s).
        Calibrate,
        /// 0x3: fine-tune the calibration (the motor turns both ways); only after 0x2.
        FineTuneCalibration,
        /// 0x4: make the current position zero (lost at power-off).
        SetZero,
        /// 0x5: emergency brake.
        EmergencyBrake,
        /// 0x6: factory reset of ramps, stall protection and load inertia.
        FactoryReset,
        /// 0x7: software reset of the drive.
        SoftReset,
        /// 0x8: clear a fault (a stall needs this before the drive works again).
        FaultReset,
        /// 0xA: speed closed loop.
        SpeedMode,
        /// 0xB: position closed loop.
        PositionMode,
        /// 0xC: torque (current) closed loop.
        TorqueMode,
    }
}

impl ConfigCommand {
    /// The value written to CONFIG.
    pub const fn code(self) -> u16 {
        match self {
            ConfigCommand::Activate => 0x0,
            ConfigCommand::Deactivate => 0x1,
            ConfigCommand::Calibrate => 0x2,
            ConfigCommand::FineTuneCalibration => 0x3,
            ConfigCommand::SetZero => 0x4,
            ConfigCommand::EmergencyBrake => 0x5,
            ConfigCommand::FactoryReset => 0x6,
            ConfigCommand::SoftReset => 0x7,
            ConfigCommand::FaultReset => 0x8,
            ConfigCommand::SpeedMode => 0xA,
            ConfigCommand::PositionMode => 0xB,
            ConfigCommand::TorqueMode => 0xC,
        }
    }

    /// The command for a CONFIG value, if it is one of the manual's twelve.
    pub fn from_code(code: u16) -> Option<Self> {
        Self::ALL.iter().copied().find(|c| c.code() == code)
    }

    /// Stable name used by the API, logs and the command line.
    pub const fn name(self) -> &'static str {
        match self {
            ConfigCommand::Activate => "activate",
            ConfigCommand::Deactivate => "deactivate",
            ConfigCommand::Calibrate => "calibrate",
            ConfigCommand::FineTuneCalibration => "fine-tune",
            ConfigCommand::SetZero => "set-zero",
            ConfigCommand::EmergencyBrake => "brake",
            ConfigCommand::FactoryReset => "factory-reset",
            ConfigCommand::SoftReset => "soft-reset",
            ConfigCommand::FaultReset => "fault-reset",
            ConfigCommand::SpeedMode => "speed-mode",
            ConfigCommand::PositionMode => "position-mode",
            ConfigCommand::TorqueMode => "torque-mode",
        }
    }

    /// The command with this [`name`](Self::name).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|c| c.name() == name)
    }

    /// The closed-loop modes a client names (`speed`, `position`,
    /// `torque`), in the manual's order (0xA, 0xB, 0xC).
    pub const MODES: [(&'static str, ConfigCommand); 3] = [
        ("speed", ConfigCommand::SpeedMode),
        ("position", ConfigCommand::PositionMode),
        ("torque", ConfigCommand::TorqueMode),
    ];

    /// The mode command a client names by its mode (`speed`), the name
    /// every face takes.
    pub fn mode_named(mode: &str) -> Option<Self> {
        Self::MODES
            .iter()
            .find(|(name, _)| *name == mode)
            .map(|(_, c)| *c)
    }

    /// The mode this command puts the drive in (`speed`), if it is one.
    pub fn mode_name(self) -> Option<&'static str> {
        Self::MODES
            .iter()
            .find(|(_, c)| *c == self)
            .map(|(name, _)| *name)
    }

    /// The modes, in words: "speed, position or torque".
    pub fn modes_in_words() -> String {
        let names: Vec<&str> = Self::MODES.iter().map(|(n, _)| *n).collect();
        format!(
            "{} or {}",
            names[..names.len() - 1].join(", "),
            names[names.len() - 1]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_and_names_round_trip() {
        for c in ConfigCommand::ALL {
            assert_eq!(ConfigCommand::from_code(c.code()), Some(c));
            assert_eq!(ConfigCommand::from_name(c.name()), Some(c));
        }
        assert_eq!(ConfigCommand::from_code(0x9), None);
        assert_eq!(ConfigCommand::from_code(0xD), None);
    }

    #[test]
    fn modes_are_named_as_clients_name_them() {
        for (name, c) in ConfigCommand::MODES {
            assert_eq!(ConfigCommand::mode_named(name), Some(c));
            assert_eq!(c.mode_name(), Some(name));
        }
        assert_eq!(ConfigCommand::mode_named("fast"), None);
        assert_eq!(ConfigCommand::Activate.mode_name(), None);
        assert_eq!(ConfigCommand::modes_in_words(), "speed, position or torque");
    }
}
