//! The address space as data: the namespace, the variables of `DriveType`
//! and of a bus, with their types, engineering units and ranges, where
//! each value comes from, the methods, and the node ids. Pure; the floor
//! every other file of the face stands on.

use opcua::types::{Identifier, NodeId};

use crate::drive::StatusField;
use crate::drive::units::{COUNTS_PER_AMP, SPEED_RPM, TORQUE_COUNTS};
use crate::drive::wanted::Setting;

/// The server's own namespace: the same on every drivegate, so a SCADA's
/// tags made on one gateway fit the next.
pub const NAMESPACE: &str = "urn:drivegate:drives";

/// How a variable's value is typed on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Double.
    Double,
    /// Int32.
    Int32,
    /// UInt16.
    UInt16,
    /// UInt32.
    UInt32,
    /// Boolean.
    Boolean,
    /// String.
    String,
    /// The drive's control mode: an Int32 of the `DriveMode` enumeration
    /// ([`MODES`]).
    Mode,
}

/// An engineering unit: its UNECE common code (OPC UA Part 8, 5.6.3) and
/// how it is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Unit {
    /// The UNECE common code ("RPM").
    pub code: &'static str,
    /// Its symbol ("r/min").
    pub symbol: &'static str,
    /// Its name ("revolutions per minute").
    pub name: &'static str,
}

/// Revolutions per minute.
pub const RPM: Unit = Unit {
    code: "RPM",
    symbol: "r/min",
    name: "revolutions per minute",
};
/// Degree (of angle).
pub const DEGREE: Unit = Unit {
    code: "DD",
    symbol: "°",
    name: "degree",
};
/// Ampere.
pub const AMPERE: Unit = Unit {
    code: "AMP",
    symbol: "A",
    name: "ampere",
};
/// Volt.
pub const VOLT: Unit = Unit {
    code: "VLT",
    symbol: "V",
    name: "volt",
};
/// Degree Celsius.
pub const CELSIUS: Unit = Unit {
    code: "CEL",
    symbol: "°C",
    name: "degree Celsius",
};
/// Millisecond.
pub const MILLISECOND: Unit = Unit {
    code: "C26",
    symbol: "ms",
    name: "millisecond",
};
/// Percent.
pub const PERCENT: Unit = Unit {
    code: "P1",
    symbol: "%",
    name: "percent",
};

impl Unit {
    /// The `UnitId` of its `EUInformation`: the code's characters folded
    /// into an integer (Part 8, 5.6.3).
    pub fn unit_id(self) -> i32 {
        self.code
            .bytes()
            .fold(0i32, |acc, b| (acc << 8) | i32::from(b))
    }
}

/// A setpoint a session may write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Setpoint {
    /// Speed, rpm.
    Speed,
    /// Position, degrees.
    Position,
    /// Torque, as the motor current, A.
    Torque,
}

/// Where a variable's value comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// The drive's polled status.
    Status(StatusField),
    /// Whether its data is live (always `Good`: it is the answer).
    Online,
    /// What the drive holds, read from it: a setpoint (writable by an
    /// operator, through the core).
    Setpoint(Setpoint),
    /// A setting of the `Settings` object (writable by an admin, as a
    /// settings document through the core).
    Setting(Setting),
}

/// One variable of `DriveType`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Variable {
    /// Its browse name (and the last part of its node id).
    pub name: &'static str,
    /// Its data type.
    pub kind: Kind,
    /// Its engineering unit, if it has one.
    pub unit: Option<Unit>,
    /// Its `EURange`: the range of the drive's register.
    pub range: Option<(f64, f64)>,
    /// Where its value comes from.
    pub source: Source,
    /// Its trend in the history, for `HistoryRead`.
    pub history: Option<StatusField>,
    /// Its `Description`: what it is, in plain words, from the manual.
    pub description: &'static str,
}

impl Variable {
    /// True when a session may write it (the core still decides).
    pub fn writable(&self) -> bool {
        matches!(self.source, Source::Setpoint(_) | Source::Setting(_))
    }

    /// Its node id's path under its drive (`Speed`, `Settings/StallTime`).
    pub fn path(&self) -> String {
        match self.source {
            Source::Setting(_) => format!("{SETTINGS}/{}", self.name),
            _ => self.name.to_string(),
        }
    }

    /// A number it shows (`Double`).
    pub fn is_analog(&self) -> bool {
        self.kind == Kind::Double
    }
}

/// A variable of the status block, with its trend when `trended`.
const fn status(
    name: &'static str,
    kind: Kind,
    (unit, range): (Option<Unit>, Option<(f64, f64)>),
    field: StatusField,
    trended: bool,
    description: &'static str,
) -> Variable {
    Variable {
        name,
        kind,
        unit,
        range,
        source: Source::Status(field),
        history: if trended { Some(field) } else { None },
        description,
    }
}

/// The current's range, A: the register's -2048..2047 counts.
const AMPS: (f64, f64) = (
    TORQUE_COUNTS.0 as f64 / COUNTS_PER_AMP,
    TORQUE_COUNTS.1 as f64 / COUNTS_PER_AMP,
);
const RPMS: (f64, f64) = (SPEED_RPM.0 as f64, SPEED_RPM.1 as f64);
const DEGREES: (f64, f64) = (-180.0, 180.0);
const PLAIN: (Option<Unit>, Option<(f64, f64)>) = (None, None);

/// The name of a drive's settings object.
pub const SETTINGS: &str = "Settings";

/// The variables of `DriveType`, in the order they are browsed, which is
/// the manual's: the status block's registers (1.7, CYCLE_NUM to TEMP),
/// then its STATUS flags from bit 7 down, `Online`, the setpoints (1.4 to
/// 1.6); then the `Settings` object's (1.8 to 1.12).
pub const VARIABLES: [Variable; 22] = [
    status(
        "Turns",
        Kind::Int32,
        PLAIN,
        StatusField::Turns,
        false,
        "Whole turns of the output counted by the drive (status register CYCLE_NUM, manual 1.7); with Angle, the position.",
    ),
    status(
        "Angle",
        Kind::Double,
        (Some(DEGREE), Some(DEGREES)),
        StatusField::AngleDeg,
        true,
        "The angle within the turn at the gearbox output, -180 to 180 degrees (status register ANGLE, in 0.01 degree, manual 1.7).",
    ),
    status(
        "Speed",
        Kind::Double,
        (Some(RPM), Some(RPMS)),
        StatusField::SpeedRpm,
        true,
        "The speed at the gearbox output, r/min (status register SPEED, manual 1.7).",
    ),
    status(
        "Current",
        Kind::Double,
        (Some(AMPERE), Some(AMPS)),
        StatusField::CurrentA,
        true,
        "The motor current, which makes its torque, A (status register IQ, 128 counts to the ampere, manual 1.7).",
    ),
    status(
        "Voltage",
        Kind::Double,
        (Some(VOLT), Some((0.0, 255.0))),
        StatusField::VoltageV,
        true,
        "The drive's supply voltage, V (status register VOLT, manual 1.7).",
    ),
    status(
        "Temperature",
        Kind::Double,
        (Some(CELSIUS), Some((-128.0, 127.0))),
        StatusField::TemperatureC,
        true,
        "The drive's temperature, degrees Celsius (status register TEMP, manual 1.7).",
    ),
    status(
        "Active",
        Kind::Boolean,
        PLAIN,
        StatusField::Active,
        false,
        "True while the drive is activated and takes setpoints (STATUS bit 7, manual 1.7): set by Activate, cleared by Deactivate; kept over power loss.",
    ),
    status(
        "Calibrated",
        Kind::Boolean,
        PLAIN,
        StatusField::Calibrated,
        false,
        "True once the encoder angle has been calibrated (STATUS bit 6, manual 1.7).",
    ),
    status(
        "Stalled",
        Kind::Boolean,
        PLAIN,
        StatusField::Stalled,
        false,
        "True when the stall protection stopped the motor (STATUS bit 5, manual 1.7): the current stayed above CurrentLimit for StallTime. FaultReset clears it.",
    ),
    status(
        "Mode",
        Kind::Mode,
        PLAIN,
        StatusField::Mode,
        false,
        "The control mode (STATUS bits 4..3, manual 1.7), a DriveMode: 0 OpenLoop (open-loop voltage control, the mode at power-on), 1 Speed, 2 Position, 3 Torque closed loop. SetMode changes it.",
    ),
    status(
        "Fault",
        Kind::String,
        PLAIN,
        StatusField::Fault,
        false,
        "The drive's fault in words (STATUS bits 2..0, manual 1.7): none, or what failed.",
    ),
    status(
        "FaultCode",
        Kind::UInt16,
        PLAIN,
        StatusField::FaultCode,
        false,
        "The drive's fault code (STATUS bits 2..0, manual 1.7): 0 none, 1 current-sense fault, 2 encoder fault, 3 power stage fault, 4 drive over-temperature, 5 supply under-voltage, 6 supply over-voltage.",
    ),
    Variable {
        name: "Online",
        kind: Kind::Boolean,
        unit: None,
        range: None,
        source: Source::Online,
        history: None,
        description: "True while the drive's data is live: it answers its polls. While false, the other values are the last ones read, with an Uncertain or Bad status saying why.",
    },
    held(
        "SpeedSetpoint",
        Kind::Double,
        (Some(RPM), Some(RPMS)),
        Source::Setpoint(Setpoint::Speed),
        "The speed setpoint at the gearbox output, r/min (SPEED_REF, manual 1.4). Written by an operator; the drive must be active and in speed mode. The session holds a lease: when it ends, the motor stops.",
    ),
    held(
        "PositionSetpoint",
        Kind::Double,
        (Some(DEGREE), Some(DEGREES)),
        Source::Setpoint(Setpoint::Position),
        "The position setpoint at the gearbox output, degrees (POSITION_REF, in 0.01 degree, manual 1.5). Written by an operator; the drive must be active and in position mode.",
    ),
    held(
        "TorqueSetpoint",
        Kind::Double,
        (Some(AMPERE), Some(AMPS)),
        Source::Setpoint(Setpoint::Torque),
        "The torque setpoint as the motor current, A (IQ_REF, 128 counts to the ampere, manual 1.6). Written by an operator; the drive must be active and in torque mode.",
    ),
    held(
        "CurrentLimit",
        Kind::Double,
        (Some(AMPERE), Some((0.0, 2047.0 / COUNTS_PER_AMP))),
        Source::Setting(Setting::CurrentLimit),
        "The stall protection's current limit, A (STALLED_CURR, manual 1.8): above it for StallTime, the drive stops the motor and reports Stalled. Written by an admin.",
    ),
    held(
        "StallTime",
        Kind::UInt32,
        (Some(MILLISECOND), Some((0.0, 60_000.0))),
        Source::Setting(Setting::StallTime),
        "How long the current may stay above CurrentLimit before the stall protection stops the motor, ms (STALLED_DURATION_MS, manual 1.8). Written by an admin.",
    ),
    held(
        "SpeedRampAlpha",
        Kind::UInt32,
        PLAIN,
        Source::Setting(Setting::SpeedRamp),
        "The speed ramp's alpha (SPEED_TD_R, manual 1.9): 0 turns the ramp off, larger is faster; from standstill the ramp takes t = 2 sqrt(r n / (9.55 alpha)) s for n r/min through a gearbox of ratio r. Written by an admin.",
    ),
    held(
        "PositionRampAlpha",
        Kind::UInt32,
        PLAIN,
        Source::Setting(Setting::PositionRamp),
        "The position ramp's alpha (POSITION_TD_R, manual 1.10): 0 turns the ramp off, larger is faster; a move of theta degrees takes t = 2 sqrt(pi theta / (180 alpha)) s. Written by an admin.",
    ),
    held(
        "InertiaRatio",
        Kind::UInt32,
        (None, Some((1.0, 65_535.0))),
        Source::Setting(Setting::InertiaRatio),
        "The load's inertia as a multiple of the rotor's (INERTIA_RATIO, manual 1.11). Written by an admin.",
    ),
    held(
        "Rs485Control",
        Kind::Boolean,
        PLAIN,
        Source::Setting(Setting::Rs485Control),
        "True: the drive takes its commands from RS-485 and ignores CAN; false: CAN controls it (USE_485_CONTROL, manual 1.12). Written by an admin.",
    ),
];

/// A variable the drive holds (a setpoint or a setting).
const fn held(
    name: &'static str,
    kind: Kind,
    (unit, range): (Option<Unit>, Option<(f64, f64)>),
    source: Source,
    description: &'static str,
) -> Variable {
    Variable {
        name,
        kind,
        unit,
        range,
        source,
        history: None,
        description,
    }
}

/// The drive's control modes, as `Mode`'s enumeration (`DriveMode`):
/// each the value of STATUS bits 4..3 (manual 1.7), its name, and what it
/// is.
pub const MODES: [(i32, &str, &str); 4] = [
    (
        0,
        "OpenLoop",
        "Open-loop voltage control: the mode at power-on, before a mode command.",
    ),
    (1, "Speed", "Speed closed loop: follows SpeedSetpoint."),
    (
        2,
        "Position",
        "Position closed loop: follows PositionSetpoint.",
    ),
    (
        3,
        "Torque",
        "Torque (current) closed loop: follows TorqueSetpoint.",
    ),
];

/// The node id path of `Mode`'s enumeration data type.
pub const MODE_TYPE: &str = "DriveMode";

/// A method of a drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Activates the drive (it then takes setpoints).
    Activate,
    /// Deactivates it.
    Deactivate,
    /// The emergency brake.
    Brake,
    /// Clears a fault or a stall.
    FaultReset,
    /// Sets the control mode: `speed`, `position` or `torque`.
    SetMode,
    /// Saves what the drive holds to its flash (the `Settings` object's
    /// method; only at standstill).
    Save,
}

impl Method {
    /// Every method, in the order they are browsed.
    pub const ALL: [Method; 6] = [
        Method::Activate,
        Method::Deactivate,
        Method::Brake,
        Method::FaultReset,
        Method::SetMode,
        Method::Save,
    ];

    /// Its browse name.
    pub fn name(self) -> &'static str {
        match self {
            Method::Activate => "Activate",
            Method::Deactivate => "Deactivate",
            Method::Brake => "Brake",
            Method::FaultReset => "FaultReset",
            Method::SetMode => "SetMode",
            Method::Save => "Save",
        }
    }

    /// Its node id's path under its drive (`Activate`, `Settings/Save`).
    pub fn path(self) -> String {
        match self {
            Method::Save => format!("{SETTINGS}/{}", self.name()),
            _ => self.name().to_string(),
        }
    }

    /// Its `Description`, from the manual.
    pub fn description(self) -> &'static str {
        match self {
            Method::Activate => {
                "Activates the drive (CONFIG 0x0, manual 1.3): it then takes setpoints. Kept over power loss. Operator."
            }
            Method::Deactivate => {
                "Deactivates the drive (CONFIG 0x1, manual 1.3): it no longer takes setpoints, and any lease on it ends. Kept over power loss. Operator."
            }
            Method::Brake => {
                "The emergency brake (CONFIG 0x5, manual 1.3), sent ahead of everything else on the bus: the motor is held and any lease on it ends; a setpoint or a mode command releases it. Operator."
            }
            Method::FaultReset => {
                "Clears a stall or a fault (CONFIG 0x8, manual 1.3); a fault whose cause remains comes back. Operator."
            }
            Method::SetMode => {
                "Sets the control mode (CONFIG 0xA, 0xB or 0xC, manual 1.3). Its argument Mode is the String speed, position or torque. Operator."
            }
            Method::Save => {
                "Writes what the drive holds (current limit, stall time, ramps, inertia ratio) to its flash, so that it is kept over power loss. Only while the motor stands still, as the manual requires. Admin."
            }
        }
    }
}

/// `SetMode`'s input argument: its name and what it takes.
pub const SET_MODE_ARGUMENT: (&str, &str) = (
    "Mode",
    "The mode, as a String: speed, position or torque (the drive's closed-loop modes).",
);

/// A variable of a bus object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusVariable {
    /// `opening`, `up` or `down`.
    State,
    /// Why it is down (empty when up).
    Reason,
    /// The share of the last 10 s the wire was busy, percent.
    Utilisation,
    /// Transactions that timed out.
    Timeouts,
    /// Replies with a bad CRC.
    CrcErrors,
    /// Replies that did not answer their request.
    BadReplies,
    /// Retries made.
    Retries,
    /// Times the port was reopened after a failure.
    Reopens,
    /// Drives whose data is live.
    DrivesOnline,
}

impl BusVariable {
    /// Every variable of a bus, in the order they are browsed.
    pub const ALL: [BusVariable; 9] = [
        BusVariable::State,
        BusVariable::Reason,
        BusVariable::Utilisation,
        BusVariable::Timeouts,
        BusVariable::CrcErrors,
        BusVariable::BadReplies,
        BusVariable::Retries,
        BusVariable::Reopens,
        BusVariable::DrivesOnline,
    ];

    /// Its browse name.
    pub fn name(self) -> &'static str {
        match self {
            BusVariable::State => "State",
            BusVariable::Reason => "Reason",
            BusVariable::Utilisation => "Utilisation",
            BusVariable::Timeouts => "Timeouts",
            BusVariable::CrcErrors => "CrcErrors",
            BusVariable::BadReplies => "BadReplies",
            BusVariable::Retries => "Retries",
            BusVariable::Reopens => "Reopens",
            BusVariable::DrivesOnline => "DrivesOnline",
        }
    }

    /// Its data type.
    pub fn kind(self) -> Kind {
        match self {
            BusVariable::State | BusVariable::Reason => Kind::String,
            BusVariable::Utilisation => Kind::Double,
            _ => Kind::UInt32,
        }
    }

    /// Its unit.
    pub fn unit(self) -> Option<Unit> {
        (self == BusVariable::Utilisation).then_some(PERCENT)
    }

    /// Its `Description`.
    pub fn description(self) -> &'static str {
        match self {
            BusVariable::State => {
                "The port's state: opening, up (carrying transactions) or down (see Reason)."
            }
            BusVariable::Reason => "Why the port is down, in words; empty while it is up.",
            BusVariable::Utilisation => {
                "The share of the last 10 s the wire was busy with frames and the silences between them, percent."
            }
            BusVariable::Timeouts => {
                "Transactions whose reply did not come in time, since the daemon started."
            }
            BusVariable::CrcErrors => "Replies with a bad CRC, since the daemon started.",
            BusVariable::BadReplies => {
                "Replies that did not answer their request (another unit, function or register), since the daemon started."
            }
            BusVariable::Retries => {
                "Requests sent again after a failed attempt, since the daemon started."
            }
            BusVariable::Reopens => {
                "Times the port was opened again after it failed, since the daemon started."
            }
            BusVariable::DrivesOnline => "Drives on this bus whose data is live.",
        }
    }
}

/// The `Description` of the object types, the folders, a drive's settings
/// object, and `Mode`'s data type.
pub mod described {
    /// `DriveType`.
    pub const DRIVE_TYPE: &str = "A servo drive on an RS-485 bus: its status, polled by the gateway, its setpoints, settings and commands (the maker's manual, sections 1.3 to 1.12).";
    /// `BusType`.
    pub const BUS_TYPE: &str =
        "An RS-485 bus (a serial adapter, or a serial device server) and its wire's counters.";
    /// `Objects/Drives`.
    pub const DRIVES: &str = "The configured drives, by name.";
    /// `Objects/Buses`.
    pub const BUSES: &str = "The configured buses, by name.";
    /// A drive's `Settings`.
    pub const SETTINGS: &str = "The drive's settings (manual 1.8 to 1.12), written by an admin; Save puts them in the drive's flash.";
    /// `DriveMode`.
    pub const MODE_TYPE: &str = "The drive's control modes (STATUS bits 4..3, manual 1.7).";
}

/// The node id path of the drives' folder.
pub const DRIVES: &str = "Drives";
/// The node id path of the buses' folder.
pub const BUSES: &str = "Buses";
/// The node id of the object type.
pub const DRIVE_TYPE: &str = "DriveType";
/// The node id of the buses' object type.
pub const BUS_TYPE: &str = "BusType";

/// The node id path of drive `drive` (`Drives/conveyor`).
pub fn drive_path(drive: &str) -> String {
    format!("{DRIVES}/{drive}")
}

/// The node id path of a variable of `drive` (`Drives/conveyor/Speed`).
pub fn variable_path(drive: &str, variable: &Variable) -> String {
    format!("{DRIVES}/{drive}/{}", variable.path())
}

/// The node id path of a method of `drive`.
pub fn method_path(drive: &str, method: Method) -> String {
    format!("{DRIVES}/{drive}/{}", method.path())
}

/// The node id path of the object a method of `drive` is called on: the
/// drive, or its `Settings`.
pub fn method_object_path(drive: &str, method: Method) -> String {
    match method {
        Method::Save => format!("{DRIVES}/{drive}/{SETTINGS}"),
        _ => drive_path(drive),
    }
}

/// The node id path of bus `bus` (`Buses/line1`).
pub fn bus_path(bus: &str) -> String {
    format!("{BUSES}/{bus}")
}

/// The node id path of condition (alarm) `id`.
pub fn alarm_path(id: u64) -> String {
    format!("Alarms/{id}")
}

/// The alarm number of a condition's node id path.
pub fn alarm_of(path: &str) -> Option<u64> {
    path.strip_prefix("Alarms/")?.parse().ok()
}

/// The string path of a node id (the namespace's ids are all strings).
pub fn path_of(id: &NodeId) -> Option<&str> {
    match &id.identifier {
        Identifier::String(s) => Some(s.as_ref()),
        _ => None,
    }
}

/// What a node id path under `Drives/` names: the drive and the rest.
pub fn split_drive_path(path: &str) -> Option<(&str, &str)> {
    path.strip_prefix("Drives/")?.split_once('/')
}

/// The variable at `rest` of a drive's path (`Speed`, `Settings/StallTime`).
pub fn variable_at(rest: &str) -> Option<&'static Variable> {
    VARIABLES.iter().find(|v| v.path() == rest)
}

/// The method at `rest` of a drive's path.
pub fn method_at(rest: &str) -> Option<Method> {
    Method::ALL.into_iter().find(|m| m.path() == rest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unece_codes_fold_into_unit_ids() {
        // The values UaExpert and the OPC Foundation's table show.
        assert_eq!(RPM.unit_id(), 5_394_509);
        assert_eq!(DEGREE.unit_id(), 17_476);
        assert_eq!(AMPERE.unit_id(), 4_279_632);
        assert_eq!(VOLT.unit_id(), 5_655_636);
        assert_eq!(CELSIUS.unit_id(), 4_408_652);
    }

    #[test]
    fn paths_find_their_variables_and_methods() {
        for v in &VARIABLES {
            let path = variable_path("conveyor", v);
            let (drive, rest) = split_drive_path(&path).unwrap();
            assert_eq!(drive, "conveyor");
            assert_eq!(variable_at(rest), Some(v));
        }
        let path = method_path("lift", Method::SetMode);
        let (_, rest) = split_drive_path(&path).unwrap();
        assert_eq!(method_at(rest), Some(Method::SetMode));
        assert_eq!(split_drive_path("Drives/lift"), None);
        assert_eq!(alarm_of(&alarm_path(17)), Some(17));
        assert_eq!(alarm_of("Alarms/x"), None);
        // Names are unique.
        for (i, v) in VARIABLES.iter().enumerate() {
            assert!(VARIABLES[..i].iter().all(|o| o.path() != v.path()));
        }
    }

    #[test]
    fn writable_variables_are_the_setpoints_and_settings() {
        let writable: Vec<&str> = VARIABLES
            .iter()
            .filter(|v| v.writable())
            .map(|v| v.name)
            .collect();
        assert_eq!(
            writable,
            [
                "SpeedSetpoint",
                "PositionSetpoint",
                "TorqueSetpoint",
                "CurrentLimit",
                "StallTime",
                "SpeedRampAlpha",
                "PositionRampAlpha",
                "InertiaRatio",
                "Rs485Control"
            ]
        );
        assert!((AMPS.0 + 16.0).abs() < 1e-9);
    }
}
