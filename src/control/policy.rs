//! Who may do what, and what a write means for the motor: the facts every
//! rule of the core is decided on, worked out once for a request whichever
//! face it came from. Pure functions.
//!
//! Roles, each including the ones before it:
//! - `viewer` reads (drives, status, buses, Modbus TCP reads) and watches
//!   the stream,
//! - `operator` runs the machine: activation, modes, setpoints and their
//!   leases, the brake, set-zero and the resets that do not touch flash,
//! - `admin` commissions it: protection, ramps, inertia, saves to flash,
//!   calibration, factory reset, RS-485 control, bus scans, addresses, and
//!   Modbus writes of registers the drive's table cannot explain.
//!
//! A write whose effect the core cannot decode at all (a function code no
//! register table describes, a mask write keeping bits of a value nobody
//! read) has no role that allows it: see [`Undecoded`].

pub use crate::config::Role;
use crate::drive::registers::Register;
use crate::drive::writes::PduMeaning;
use crate::drive::{ConfigCommand, DriveRequest, Mode};

/// What is not a write but still needs a role.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Operation {
    /// Reading drives, status and buses.
    Read,
    /// Renewing or releasing a lease.
    Lease,
    /// Scanning a bus for units (each silent unit costs bus time).
    Scan,
    /// Arming, triggering or cancelling a scope capture: it changes how the
    /// bus polls (its drives get every poll, the others the floor rate).
    Capture,
    /// Noting the start or end of a drive replacement in the audit log
    /// (commissioning work).
    Replacement,
    /// Acknowledging an alarm: the operator on duty says they saw it.
    AcknowledgeAlarm,
    /// Reloading the configuration file (drives and buses added or
    /// removed, tokens, roles of networks): commissioning work.
    Reload,
    /// Reading, checking and changing the configuration file itself, its
    /// API tokens included: it names every token's source and every
    /// role, and what it says the daemon becomes.
    Configure,
    /// Trusting, removing and renewing certificates (OPC UA clients, the
    /// server's own): who may connect with a certificate, and as whom.
    Certificates,
}

impl Operation {
    /// The role it needs.
    pub fn needs(self) -> Role {
        match self {
            Operation::Read => Role::Viewer,
            Operation::Lease => Role::Operator,
            Operation::Scan => Role::Admin,
            Operation::Capture => Role::Operator,
            Operation::Replacement => Role::Admin,
            Operation::AcknowledgeAlarm => Role::Operator,
            Operation::Reload => Role::Admin,
            Operation::Configure => Role::Admin,
            Operation::Certificates => Role::Admin,
        }
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

/// Why a write needs the motor standing still.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StillReason {
    /// A save flag of 1.8 to 1.11 writes flash, which the manual allows only
    /// at standstill.
    Save,
    /// Factory reset rewrites flash.
    FactoryReset,
    /// A drive taking a new address drops off the bus mid-motion.
    Address,
    /// Calibration and fine-tuning move the motor on their own.
    Calibration,
    /// drivegate writes a drive's declared settings on its own
    /// (`apply_settings = "on-drift"`): nobody is watching the machine.
    Unattended,
}

impl StillReason {
    /// In words, as the subject of "is refused while the motor turns".
    pub fn what(self) -> &'static str {
        match self {
            StillReason::Save => "a save to flash",
            StillReason::FactoryReset => "a factory reset",
            StillReason::Address => "address setting",
            StillReason::Calibration => "calibration",
            StillReason::Unattended => "applying the declared settings",
        }
    }

    /// Why, in words.
    pub fn why(self) -> &'static str {
        match self {
            StillReason::Save | StillReason::FactoryReset => {
                "the manual allows writing flash only at standstill"
            }
            StillReason::Address => {
                "a drive that takes a new address stops answering at the old one mid-motion"
            }
            StillReason::Calibration => "calibration turns the motor on its own",
            StillReason::Unattended => {
                "drivegate changes a drive's settings on its own only at standstill"
            }
        }
    }
}

/// Why the core cannot tell what a write does, so that no rule can be
/// checked on it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Undecoded {
    /// A function code whose effect no register table describes (coils,
    /// file records, diagnostics that restart, silence or clear a device,
    /// vendor codes, codes the specification does not define). Refused,
    /// unless the face lets an admin send it unchecked, never as a
    /// broadcast.
    Function {
        /// The function code.
        code: u8,
    },
    /// A mask write (0x16) whose AND mask keeps bits of the register's
    /// current value: what it writes depends on a value nobody read (the
    /// command and save-flag registers cannot be read at all), and the
    /// drive has no mask write of its own to do it in one transaction.
    /// Refused: the same write with an AND mask of 0, or as a 0x06, is
    /// decided like any other.
    MaskedValue {
        /// The register.
        register: Register,
    },
}

impl Undecoded {
    /// In words, for the refusal.
    pub fn what(self) -> String {
        match self {
            Undecoded::Function { code } => format!(
                "Modbus function 0x{code:02X} ({}) is not decoded by drivegate: it may change the device in ways no rule can check",
                crate::modbus::function::name(code)
            ),
            Undecoded::MaskedValue { register } => format!(
                "a mask write of {} keeps bits of its current value, which drivegate has not read, so what it writes is unknown; write the whole value (0x06, or an AND mask of 0)",
                register.name()
            ),
        }
    }
}

/// A write that stops the motor itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stopper {
    /// The emergency brake.
    Brake,
    /// Deactivation.
    Deactivate,
}

impl Stopper {
    /// In words ("the brake").
    pub fn name(self) -> &'static str {
        match self {
            Stopper::Brake => "the brake",
            Stopper::Deactivate => "the deactivation",
        }
    }
}

/// What a write means for the motor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Meaning {
    /// The role it needs.
    pub needs: Role,
    /// Set when it needs the motor standing still.
    pub still: Option<StillReason>,
    /// The mode of the setpoint it writes, if it writes one.
    pub setpoint: Option<Mode>,
    /// Set when it stops the motor itself.
    pub stops: Option<Stopper>,
    /// The mode a mode command puts the drive in.
    pub mode: Option<Mode>,
    /// True when it releases a brake (setpoints, mode commands).
    pub releases_brake: bool,
    /// True when it goes ahead of everything on the bus (the brake).
    pub emergency: bool,
    /// True when it sets a drive's address.
    pub address: bool,
    /// Set when the core cannot tell what it does.
    pub undecoded: Option<Undecoded>,
}

impl Meaning {
    /// True when the write is carried out even if its caller goes away
    /// before it is settled (a WebSocket closing, a Modbus TCP client
    /// disconnecting): a write that stops the motor. The core follows it
    /// to its end, and a face must not cancel it.
    pub fn survives_caller(&self) -> bool {
        self.stops.is_some()
    }

    fn new(needs: Role) -> Self {
        Meaning {
            needs,
            still: None,
            setpoint: None,
            stops: None,
            mode: None,
            releases_brake: false,
            emergency: false,
            address: false,
            undecoded: None,
        }
    }

    /// Folds in another register's meaning: the stricter of each fact.
    fn and(mut self, other: Meaning) -> Self {
        self.needs = self.needs.max(other.needs);
        self.still = self.still.or(other.still);
        self.setpoint = self.setpoint.or(other.setpoint);
        self.stops = self.stops.or(other.stops);
        self.mode = self.mode.or(other.mode);
        self.releases_brake |= other.releases_brake;
        self.emergency |= other.emergency;
        self.address |= other.address;
        self.undecoded = self.undecoded.or(other.undecoded);
        self
    }
}

/// What a config command means.
fn command(command: ConfigCommand) -> Meaning {
    let mut m = Meaning::new(for_command(command));
    match command {
        ConfigCommand::EmergencyBrake => {
            m.stops = Some(Stopper::Brake);
            m.emergency = true;
        }
        ConfigCommand::Deactivate => m.stops = Some(Stopper::Deactivate),
        ConfigCommand::Calibrate | ConfigCommand::FineTuneCalibration => {
            m.still = Some(StillReason::Calibration);
        }
        ConfigCommand::FactoryReset => m.still = Some(StillReason::FactoryReset),
        ConfigCommand::SpeedMode => {
            m.mode = Some(Mode::Speed);
            m.releases_brake = true;
        }
        ConfigCommand::PositionMode => {
            m.mode = Some(Mode::Position);
            m.releases_brake = true;
        }
        ConfigCommand::TorqueMode => {
            m.mode = Some(Mode::Torque);
            m.releases_brake = true;
        }
        ConfigCommand::Activate
        | ConfigCommand::SetZero
        | ConfigCommand::SoftReset
        | ConfigCommand::FaultReset => {}
    }
    m
}

fn setpoint(mode: Mode) -> Meaning {
    let mut m = Meaning::new(Role::Operator);
    m.setpoint = Some(mode);
    m.releases_brake = true;
    m
}

/// The role a drive's settings (1.8 to 1.12) need: commissioning work.
pub fn for_settings() -> Role {
    Role::Admin
}

fn settings(save: bool) -> Meaning {
    let mut m = Meaning::new(for_settings());
    if save {
        m.still = Some(StillReason::Save);
    }
    m
}

/// What one of the manual's messages means.
pub fn of_request(request: &DriveRequest) -> Meaning {
    match *request {
        DriveRequest::SetAddress { .. } => {
            let mut m = Meaning::new(Role::Admin);
            m.still = Some(StillReason::Address);
            m.address = true;
            m
        }
        DriveRequest::Config(c) => command(c),
        DriveRequest::Speed { .. } => setpoint(Mode::Speed),
        DriveRequest::Position { .. } => setpoint(Mode::Position),
        DriveRequest::Torque { .. } => setpoint(Mode::Torque),
        DriveRequest::ReadStatus => Meaning::new(Role::Viewer),
        DriveRequest::OverCurrent { save, .. }
        | DriveRequest::SpeedRamp { save, .. }
        | DriveRequest::PositionRamp { save, .. }
        | DriveRequest::LoadInertia { save, .. } => settings(save),
        DriveRequest::Rs485Control { .. } => settings(false),
    }
}

/// What a write of `value` to `register` means on its own.
pub fn of_register(register: Register, value: u16) -> Meaning {
    match register {
        Register::SlaveAddr => of_request(&DriveRequest::SetAddress {
            address: u8::try_from(value).unwrap_or(0),
        }),
        Register::Config => match ConfigCommand::from_code(value) {
            Some(c) => command(c),
            // A code the drive refuses: nothing the core can vouch for.
            None => Meaning::new(Role::Admin),
        },
        Register::SpeedRef => setpoint(Mode::Speed),
        Register::PositionRef => setpoint(Mode::Position),
        Register::IqRef => setpoint(Mode::Torque),
        Register::StalledCurrSaveFlag
        | Register::SpeedTdRSaveFlag
        | Register::PositionTdRSaveFlag
        | Register::InertiaRatioSaveFlag => settings(value != 0),
        _ => Meaning::new(Role::Admin),
    }
}

/// What a Modbus write PDU means, as the drive would read it; a write the
/// register table cannot explain needs the admin role; one the core cannot
/// decode at all is [`Undecoded`].
pub fn of_pdu(meaning: &PduMeaning) -> Meaning {
    match meaning {
        PduMeaning::Message(request) => of_request(request),
        PduMeaning::Registers(writes) => writes
            .iter()
            .map(|&(r, v)| of_register(r, v))
            .reduce(Meaning::and)
            .unwrap_or(Meaning::new(Role::Admin)),
        PduMeaning::Unknown => Meaning::new(Role::Admin),
        &PduMeaning::Masked { register, .. } => undecoded(Undecoded::MaskedValue { register }),
        &PduMeaning::NotDecoded { function } => undecoded(Undecoded::Function { code: function }),
    }
}

/// A write nobody can decode: if it goes at all, it goes unchecked, for an
/// admin.
fn undecoded(why: Undecoded) -> Meaning {
    let mut m = Meaning::new(Role::Admin);
    m.undecoded = Some(why);
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles_are_ordered() {
        assert!(Role::Admin.allows(Role::Operator));
        assert!(Role::Operator.allows(Role::Viewer));
        assert!(!Role::Viewer.allows(Role::Operator));
        assert!(!Role::Operator.allows(Role::Admin));
        assert_eq!(Operation::Scan.needs(), Role::Admin);
        assert_eq!(Operation::Lease.needs(), Role::Operator);
        assert_eq!(Operation::Read.needs(), Role::Viewer);
        assert_eq!(Operation::Capture.needs(), Role::Operator);
    }

    #[test]
    fn commissioning_commands_need_admin() {
        assert_eq!(for_command(ConfigCommand::FactoryReset), Role::Admin);
        assert_eq!(for_command(ConfigCommand::Calibrate), Role::Admin);
        assert_eq!(for_command(ConfigCommand::EmergencyBrake), Role::Operator);
        assert_eq!(for_command(ConfigCommand::FaultReset), Role::Operator);
    }

    #[test]
    fn the_brake_stops_the_motor_at_emergency_priority() {
        let m = of_request(&DriveRequest::Config(ConfigCommand::EmergencyBrake));
        assert_eq!(m.stops, Some(Stopper::Brake));
        assert!(m.emergency && !m.releases_brake);
        assert_eq!(m.needs, Role::Operator);
        let m = of_request(&DriveRequest::Config(ConfigCommand::Deactivate));
        assert_eq!(m.stops, Some(Stopper::Deactivate));
        assert!(!m.emergency);
    }

    #[test]
    fn setpoints_and_mode_commands_release_the_brake() {
        let m = of_request(&DriveRequest::Torque { counts: 128 });
        assert_eq!((m.setpoint, m.releases_brake), (Some(Mode::Torque), true));
        let m = of_request(&DriveRequest::Config(ConfigCommand::SpeedMode));
        assert_eq!(
            (m.setpoint, m.mode, m.releases_brake),
            (None, Some(Mode::Speed), true)
        );
        for (c, mode) in [
            (ConfigCommand::PositionMode, Mode::Position),
            (ConfigCommand::TorqueMode, Mode::Torque),
        ] {
            assert_eq!(of_request(&DriveRequest::Config(c)).mode, Some(mode));
        }
        let m = of_request(&DriveRequest::Config(ConfigCommand::FaultReset));
        assert!(!m.releases_brake && m.mode.is_none());
    }

    #[test]
    fn still_checks() {
        let save = DriveRequest::LoadInertia {
            ratio: 5,
            save: true,
        };
        assert_eq!(of_request(&save).still, Some(StillReason::Save));
        let no_save = DriveRequest::LoadInertia {
            ratio: 5,
            save: false,
        };
        assert_eq!(of_request(&no_save).still, None);
        assert_eq!(of_request(&no_save).needs, Role::Admin);
        for (c, reason) in [
            (ConfigCommand::FactoryReset, StillReason::FactoryReset),
            (ConfigCommand::Calibrate, StillReason::Calibration),
            (ConfigCommand::FineTuneCalibration, StillReason::Calibration),
        ] {
            assert_eq!(of_request(&DriveRequest::Config(c)).still, Some(reason));
        }
        let address = of_request(&DriveRequest::SetAddress { address: 4 });
        assert_eq!(address.still, Some(StillReason::Address));
        assert!(address.address);
        assert_eq!(of_request(&DriveRequest::Speed { rpm: 0 }).still, None);
    }

    #[test]
    fn register_writes_mean_what_the_message_would() {
        // A save flag written on its own is a save.
        let m = of_register(Register::SpeedTdRSaveFlag, 1);
        assert_eq!((m.needs, m.still), (Role::Admin, Some(StillReason::Save)));
        assert_eq!(of_register(Register::SpeedTdRSaveFlag, 0).still, None);
        // One half of a ramp alpha: a setting.
        let m = of_register(Register::SpeedTdRLow, 7);
        assert_eq!((m.needs, m.still), (Role::Admin, None));
        // Setpoints by register.
        assert_eq!(
            of_register(Register::PositionRef, 9000).setpoint,
            Some(Mode::Position)
        );
        // CONFIG by code; an unknown code needs admin.
        assert_eq!(of_register(Register::Config, 5).stops, Some(Stopper::Brake));
        assert_eq!(of_register(Register::Config, 9).needs, Role::Admin);
        // A write to a read-only register.
        assert_eq!(of_register(Register::Speed, 1).needs, Role::Admin);
        // A block: the stricter of each register.
        let block = PduMeaning::Registers(vec![
            (Register::SpeedRef, 100),
            (Register::PositionRef, 0),
            (Register::IqRef, 0),
            (Register::StalledCurr, 1000),
        ]);
        let m = of_pdu(&block);
        assert_eq!((m.needs, m.setpoint), (Role::Admin, Some(Mode::Speed)));
        assert_eq!(of_pdu(&PduMeaning::Unknown).needs, Role::Admin);
        assert_eq!(of_pdu(&PduMeaning::Unknown).undecoded, None);
    }

    #[test]
    fn what_cannot_be_decoded_says_why() {
        let coil = of_pdu(&PduMeaning::NotDecoded { function: 0x05 });
        assert_eq!(coil.needs, Role::Admin);
        let why = coil.undecoded.unwrap();
        assert_eq!(why, Undecoded::Function { code: 0x05 });
        assert!(
            why.what()
                .starts_with("Modbus function 0x05 (Write Single Coil) is not decoded"),
            "{}",
            why.what()
        );
        let masked = of_pdu(&PduMeaning::Masked {
            register: Register::Config,
            and: 0xFFF0,
            or: 6,
        });
        assert_eq!(
            masked.undecoded,
            Some(Undecoded::MaskedValue {
                register: Register::Config
            })
        );
        assert!(masked.undecoded.unwrap().what().contains("CONFIG"));
    }
}
