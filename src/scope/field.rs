//! The status fields a capture records, each in engineering units with the
//! unit in its name (as the CSV columns are named).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::drive::Status;
use crate::listed::listed_enum;

listed_enum! {
    /// One field of the status block (manual 1.7).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
    #[serde(rename_all = "snake_case")]
    pub enum Field {
        /// Speed at the gearbox output, rpm.
        SpeedRpm,
        /// Angle, degrees (-180..180).
        AngleDeg,
        /// Whole turns counted by the drive (0..65535, wraps).
        Turns,
        /// Motor current, A (1 A = 128 counts).
        CurrentA,
        /// Supply voltage, V.
        VoltageV,
        /// Drive temperature, °C.
        TemperatureC,
        /// 1 while the drive is active.
        Active,
        /// 1 while the drive is stalled (until a fault reset).
        Stalled,
        /// Control mode: 0 open loop, 1 speed, 2 position, 3 torque.
        Mode,
        /// Fault code: 0 none, 1 current sense, 2 encoder, 3 power stage,
        /// 4 over-temperature, 5 under-voltage, 6 over-voltage.
        Fault,
    }
}

impl Field {
    /// The field's name, its unit in it: `speed_rpm`.
    pub fn name(self) -> &'static str {
        match self {
            Field::SpeedRpm => "speed_rpm",
            Field::AngleDeg => "angle_deg",
            Field::Turns => "turns",
            Field::CurrentA => "current_a",
            Field::VoltageV => "voltage_v",
            Field::TemperatureC => "temperature_c",
            Field::Active => "active",
            Field::Stalled => "stalled",
            Field::Mode => "mode",
            Field::Fault => "fault",
        }
    }

    /// The unit, in words (empty for flags and codes).
    pub fn unit(self) -> &'static str {
        match self {
            Field::SpeedRpm => "rpm",
            Field::AngleDeg => "deg",
            Field::Turns => "turns",
            Field::CurrentA => "A",
            Field::VoltageV => "V",
            Field::TemperatureC => "°C",
            Field::Active | Field::Stalled | Field::Mode | Field::Fault => "",
        }
    }

    /// The field named `name`.
    pub fn from_name(name: &str) -> Option<Field> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Its value in `status`.
    pub fn value(self, s: &Status) -> f64 {
        match self {
            Field::SpeedRpm => f64::from(s.speed_rpm),
            Field::AngleDeg => s.angle_deg(),
            Field::Turns => f64::from(s.turns),
            Field::CurrentA => s.current_a(),
            Field::VoltageV => f64::from(s.voltage_v),
            Field::TemperatureC => f64::from(s.temperature_c),
            Field::Active => f64::from(u8::from(s.active())),
            Field::Stalled => f64::from(u8::from(s.stalled())),
            Field::Mode => f64::from(s.mode().bits()),
            Field::Fault => f64::from(s.fault().code()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_engineering_units() {
        let s = Status {
            turns: 2,
            angle_centideg: -4500,
            speed_rpm: -120,
            current_counts: 256,
            voltage_v: 24,
            temperature_c: 40,
            flags: 0x80 | 0x20 | (2 << 3) | 4,
        };
        let v: Vec<f64> = Field::ALL.iter().map(|f| f.value(&s)).collect();
        assert_eq!(v, [-120.0, -45.0, 2.0, 2.0, 24.0, 40.0, 1.0, 1.0, 2.0, 4.0]);
        for f in Field::ALL {
            assert_eq!(Field::from_name(f.name()), Some(f));
        }
        assert_eq!(
            serde_json::to_string(&Field::TemperatureC).unwrap(),
            "\"temperature_c\""
        );
    }
}
