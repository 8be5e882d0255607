//! The status fields a capture records: every field of the status block
//! ([`StatusField`], with its name, unit and value) but `calibrated` and
//! `fault_code` (the scope's `fault` is the fault's code), and how a
//! client names them.

use std::borrow::Cow;
use std::fmt;

use serde::de::{self, Deserialize, Deserializer, Visitor};
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{ObjectBuilder, Schema, Type};
use utoipa::{PartialSchema, ToSchema};

use crate::drive::StatusField;

/// What a capture can record, in the order of the CSV's columns when a
/// client names none.
pub const RECORDED: [StatusField; 10] = [
    StatusField::SpeedRpm,
    StatusField::AngleDeg,
    StatusField::Turns,
    StatusField::CurrentA,
    StatusField::VoltageV,
    StatusField::TemperatureC,
    StatusField::Active,
    StatusField::Stalled,
    StatusField::Mode,
    StatusField::Fault,
];

/// Their names, for the refusal of any other.
const NAMES: [&str; RECORDED.len()] = {
    let mut names = [""; RECORDED.len()];
    let mut i = 0;
    while i < RECORDED.len() {
        names[i] = RECORDED[i].name();
        i += 1;
    }
    names
};

/// A field's value in a sample, a number in the field's unit (a flag 0
/// or 1, the mode its two STATUS bits, the fault its code).
pub fn value(field: StatusField, status: &crate::drive::Status) -> f64 {
    field.read(status).number()
}

/// A field's unit, empty for flags and codes.
pub fn unit(field: StatusField) -> &'static str {
    field.unit().unwrap_or("")
}

/// A field a capture records, as a client names it (`"speed_rpm"`): one
/// of [`RECORDED`], any other name refused with the list.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Field(pub StatusField);

impl<'de> Deserialize<'de> for Field {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Name;
        impl Visitor<'_> for Name {
            type Value = Field;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("the name of a status field")
            }

            fn visit_str<E: de::Error>(self, name: &str) -> Result<Field, E> {
                RECORDED
                    .into_iter()
                    .find(|f| f.name() == name)
                    .map(Field)
                    .ok_or_else(|| E::unknown_variant(name, &NAMES))
            }
        }
        deserializer.deserialize_str(Name)
    }
}

impl PartialSchema for Field {
    fn schema() -> RefOr<Schema> {
        ObjectBuilder::new()
            .schema_type(Type::String)
            .description(Some("One field of the status block (manual 1.7)."))
            .enum_values(Some(NAMES))
            .into()
    }
}

impl ToSchema for Field {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("Field")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::Status;

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
        let v: Vec<f64> = RECORDED.iter().map(|f| value(*f, &s)).collect();
        assert_eq!(v, [-120.0, -45.0, 2.0, 2.0, 24.0, 40.0, 1.0, 1.0, 2.0, 4.0]);
        assert_eq!(unit(StatusField::TemperatureC), "°C");
        assert_eq!(unit(StatusField::Fault), "");
    }

    #[test]
    fn a_client_names_the_recorded_fields_only() {
        let f: Field = serde_json::from_str("\"temperature_c\"").unwrap();
        assert_eq!(f.0, StatusField::TemperatureC);
        let e = serde_json::from_str::<Field>("\"calibrated\"").unwrap_err();
        assert!(
            e.to_string().starts_with(
                "unknown variant `calibrated`, expected one of `speed_rpm`, `angle_deg`,"
            ),
            "{e}"
        );
    }
}
