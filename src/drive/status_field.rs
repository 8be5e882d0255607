//! The fields of the status block (manual 1.7) as every face names them:
//! one list, with each field's name, unit and how it is read from a
//! [`Status`], so the history, the scope, MQTT and any other face cannot
//! name a field, give its unit or scale its value differently. Which of
//! them a face shows is the face's choice.

use super::status::{Fault, Mode, Status};
use super::units;
use crate::listed::listed_enum;

listed_enum! {
    /// A field of the status block, in engineering units (the unit in its
    /// name), in the order the faces list them.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum StatusField {
        /// SPEED: at the gearbox output, rpm.
        SpeedRpm,
        /// ANGLE: within the turn, degrees (-180..180).
        AngleDeg,
        /// CYCLE_NUM: whole turns (0..65535, wraps).
        Turns,
        /// IQ: motor current, amps (1 A = 128 counts).
        CurrentA,
        /// VOLT: supply voltage, volts.
        VoltageV,
        /// TEMP: drive temperature, °C.
        TemperatureC,
        /// STATUS bit 7: active (takes setpoints).
        Active,
        /// STATUS bit 5: stalled (until a fault reset).
        Stalled,
        /// STATUS bit 6: the encoder is calibrated.
        Calibrated,
        /// STATUS bits 4..3: the control mode.
        Mode,
        /// STATUS bits 2..0: the fault.
        Fault,
        /// STATUS bits 2..0 as a number: 0 none, 1 current sense, 2
        /// encoder, 3 power stage, 4 over-temperature, 5 under-voltage, 6
        /// over-voltage.
        FaultCode,
    }
}

/// A field's value in one status, typed as the drive reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reading {
    /// A signed register in the field's unit (rpm, °C).
    Signed(i16),
    /// An unsigned register in the field's unit (turns, V), or the
    /// fault's code.
    Unsigned(u16),
    /// A register scaled to the field's unit (degrees from 0.01 degree,
    /// amps from 1/128 A).
    Scaled(f64),
    /// A STATUS flag.
    Flag(bool),
    /// The control mode.
    Mode(Mode),
    /// The fault.
    Fault(Fault),
}

impl Reading {
    /// As a number in the field's unit: a flag 0 or 1, a mode its two
    /// STATUS bits, a fault its code.
    pub fn number(self) -> f64 {
        match self {
            Reading::Signed(v) => f64::from(v),
            Reading::Unsigned(v) => f64::from(v),
            Reading::Scaled(v) => v,
            Reading::Flag(on) => f64::from(u8::from(on)),
            Reading::Mode(mode) => f64::from(mode.bits()),
            Reading::Fault(fault) => f64::from(fault.code()),
        }
    }
}

impl StatusField {
    /// Its name, the unit in it: `speed_rpm` (the API's, the CSV column's,
    /// MQTT's `status/speed_rpm`).
    pub const fn name(self) -> &'static str {
        match self {
            StatusField::SpeedRpm => "speed_rpm",
            StatusField::AngleDeg => "angle_deg",
            StatusField::Turns => "turns",
            StatusField::CurrentA => "current_a",
            StatusField::VoltageV => "voltage_v",
            StatusField::TemperatureC => "temperature_c",
            StatusField::Active => "active",
            StatusField::Stalled => "stalled",
            StatusField::Calibrated => "calibrated",
            StatusField::Mode => "mode",
            StatusField::Fault => "fault",
            StatusField::FaultCode => "fault_code",
        }
    }

    /// The field named `name`.
    pub fn from_name(name: &str) -> Option<StatusField> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Its engineering unit; `None` for flags, the mode and the fault.
    pub const fn unit(self) -> Option<&'static str> {
        match self {
            StatusField::SpeedRpm => Some("rpm"),
            StatusField::AngleDeg => Some("deg"),
            StatusField::Turns => Some("turns"),
            StatusField::CurrentA => Some("A"),
            StatusField::VoltageV => Some("V"),
            StatusField::TemperatureC => Some("°C"),
            _ => None,
        }
    }

    /// Its value in `status`.
    pub fn read(self, status: &Status) -> Reading {
        match self {
            StatusField::SpeedRpm => Reading::Signed(status.speed_rpm),
            StatusField::AngleDeg => Reading::Scaled(status.angle_deg()),
            StatusField::Turns => Reading::Unsigned(status.turns),
            StatusField::CurrentA => Reading::Scaled(status.current_a()),
            StatusField::VoltageV => Reading::Unsigned(status.voltage_v),
            StatusField::TemperatureC => Reading::Signed(status.temperature_c),
            StatusField::Active => Reading::Flag(status.active()),
            StatusField::Stalled => Reading::Flag(status.stalled()),
            StatusField::Calibrated => Reading::Flag(status.calibrated()),
            StatusField::Mode => Reading::Mode(status.mode()),
            StatusField::Fault => Reading::Fault(status.fault()),
            StatusField::FaultCode => Reading::Unsigned(status.fault().code()),
        }
    }

    /// The register behind a measurement, as the drive sent it (0.01
    /// degree, current counts ...): what a store keeps compactly. `None`
    /// for flags, the mode and the fault.
    pub fn counts(self, status: &Status) -> Option<i32> {
        match self {
            StatusField::SpeedRpm => Some(i32::from(status.speed_rpm)),
            StatusField::AngleDeg => Some(i32::from(status.angle_centideg)),
            StatusField::Turns => Some(i32::from(status.turns)),
            StatusField::CurrentA => Some(i32::from(status.current_counts)),
            StatusField::VoltageV => Some(i32::from(status.voltage_v)),
            StatusField::TemperatureC => Some(i32::from(status.temperature_c)),
            _ => None,
        }
    }

    /// A number of [`counts`](Self::counts) (a mean, say) in the field's
    /// unit.
    pub fn from_counts(self, counts: f64) -> f64 {
        match self {
            StatusField::AngleDeg => counts / 100.0,
            StatusField::CurrentA => counts / units::COUNTS_PER_AMP,
            _ => counts,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status() -> Status {
        Status {
            turns: 2,
            angle_centideg: -4500,
            speed_rpm: -120,
            current_counts: 256,
            voltage_v: 24,
            temperature_c: 40,
            flags: Status::flags_from(true, false, true, Mode::Position, Fault::OverTemperature),
        }
    }

    #[test]
    fn every_field_is_read_in_its_unit() {
        let s = status();
        let numbers: Vec<f64> = StatusField::ALL
            .iter()
            .map(|f| f.read(&s).number())
            .collect();
        assert_eq!(
            numbers,
            [
                -120.0, -45.0, 2.0, 2.0, 24.0, 40.0, 1.0, 1.0, 0.0, 2.0, 4.0, 4.0
            ]
        );
        assert_eq!(StatusField::Mode.read(&s), Reading::Mode(Mode::Position));
        assert_eq!(
            StatusField::Fault.read(&s),
            Reading::Fault(Fault::OverTemperature)
        );
        for f in StatusField::ALL {
            assert_eq!(StatusField::from_name(f.name()), Some(f));
        }
        assert_eq!(StatusField::from_name("rpm"), None);
    }

    #[test]
    fn counts_scale_to_the_value_read() {
        let s = status();
        for f in StatusField::ALL {
            match f.counts(&s) {
                Some(c) => assert_eq!(f.from_counts(f64::from(c)), f.read(&s).number(), "{f:?}"),
                None => assert_eq!(f.unit(), None, "{f:?} is a measurement"),
            }
        }
        assert_eq!(StatusField::AngleDeg.from_counts(4500.5), 45.005);
    }
}
