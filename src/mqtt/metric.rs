//! A drive as a Sparkplug device: the metrics of its status (read only:
//! `status/<name>` of every [`StatusField`], with its unit) and the ones
//! a host may write, their values from a status, and their protobuf form.
//! Pure: no I/O.

use super::sparkplug_b::DataType;
use super::sparkplug_b::payload::{
    self, Metric, PropertySet, PropertyValue, metric, property_value,
};
use crate::config::mqtt::Deadbands;
use crate::drive::{Reading, Status, StatusField};

/// A metric's value, typed as Sparkplug sends it.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// A signed integer of `DataType` Int32 or Int64.
    Int(i64),
    /// An unsigned integer (UInt32).
    UInt(u32),
    /// A floating point number (Double).
    Double(f64),
    /// A boolean.
    Bool(bool),
    /// A string.
    Text(String),
    /// No value yet (a setpoint never written since start).
    Null,
}

/// A status field's metric name: `status/speed_rpm`.
pub fn status_name(field: StatusField) -> String {
    format!("status/{}", field.name())
}

/// A status field's Sparkplug data type: a signed register Int32, an
/// unsigned one (and the fault code) UInt32, a scaled one Double, a flag
/// Boolean, the mode and the fault their names.
pub fn status_datatype(field: StatusField) -> DataType {
    match field {
        StatusField::SpeedRpm | StatusField::TemperatureC => DataType::Int32,
        StatusField::Turns | StatusField::VoltageV | StatusField::FaultCode => DataType::UInt32,
        StatusField::AngleDeg | StatusField::CurrentA => DataType::Double,
        StatusField::Active | StatusField::Stalled | StatusField::Calibrated => DataType::Boolean,
        StatusField::Mode | StatusField::Fault => DataType::String,
    }
}

/// A status field's value in `status`, as its metric carries it.
pub fn status_value(field: StatusField, status: &Status) -> Value {
    match field.read(status) {
        Reading::Signed(v) => Value::Int(i64::from(v)),
        Reading::Unsigned(v) => Value::UInt(u32::from(v)),
        Reading::Scaled(v) => Value::Double(v),
        Reading::Flag(on) => Value::Bool(on),
        Reading::Mode(mode) => Value::Text(mode.name().to_string()),
        Reading::Fault(fault) => Value::Text(fault.name().to_string()),
    }
}

/// The metric of status field `field` with `value` (at `timestamp`, ms).
pub fn status_metric(field: StatusField, value: Value, timestamp: u64) -> Metric {
    metric(
        &status_name(field),
        status_datatype(field),
        value,
        timestamp,
    )
}

/// How far a status field must move before it is published again;
/// `None`: on every change.
pub fn deadband(field: StatusField, deadbands: &Deadbands) -> Option<f64> {
    match field {
        StatusField::SpeedRpm => Some(deadbands.speed_rpm),
        StatusField::AngleDeg => Some(deadbands.angle_deg),
        StatusField::CurrentA => Some(deadbands.current_a),
        StatusField::VoltageV => Some(deadbands.voltage_v),
        StatusField::TemperatureC => Some(deadbands.temperature_c),
        _ => None,
    }
}

/// A metric a host may write (DCMD), and the drive's answer in DDATA.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Writable {
    /// `command/activate`: true activates the drive.
    Activate,
    /// `command/deactivate`.
    Deactivate,
    /// `command/brake`: the emergency brake.
    Brake,
    /// `command/fault_reset`.
    FaultReset,
    /// `mode`: `speed`, `position` or `torque`.
    Mode,
    /// `setpoint/speed_rpm`.
    SpeedRpm,
    /// `setpoint/position_deg`.
    PositionDeg,
    /// `setpoint/torque_a`.
    TorqueA,
}

impl Writable {
    /// Every writable metric, in the order of the births.
    pub const ALL: [Writable; 8] = [
        Writable::Activate,
        Writable::Deactivate,
        Writable::Brake,
        Writable::FaultReset,
        Writable::Mode,
        Writable::SpeedRpm,
        Writable::PositionDeg,
        Writable::TorqueA,
    ];

    /// The metric's name.
    pub fn name(self) -> &'static str {
        match self {
            Writable::Activate => "command/activate",
            Writable::Deactivate => "command/deactivate",
            Writable::Brake => "command/brake",
            Writable::FaultReset => "command/fault_reset",
            Writable::Mode => "mode",
            Writable::SpeedRpm => "setpoint/speed_rpm",
            Writable::PositionDeg => "setpoint/position_deg",
            Writable::TorqueA => "setpoint/torque_a",
        }
    }

    /// The writable metric named `name`.
    pub fn from_name(name: &str) -> Option<Writable> {
        Writable::ALL.into_iter().find(|w| w.name() == name)
    }

    /// Its engineering unit, if it has one.
    pub fn unit(self) -> Option<&'static str> {
        match self {
            Writable::SpeedRpm => Some("rpm"),
            Writable::PositionDeg => Some("deg"),
            Writable::TorqueA => Some("A"),
            _ => None,
        }
    }

    /// Its Sparkplug data type.
    pub fn datatype(self) -> DataType {
        match self {
            Writable::Activate | Writable::Deactivate | Writable::Brake | Writable::FaultReset => {
                DataType::Boolean
            }
            Writable::Mode => DataType::String,
            Writable::SpeedRpm | Writable::PositionDeg | Writable::TorqueA => DataType::Double,
        }
    }
}

/// The metric saying what became of the last command: empty when it was
/// confirmed, else the refusal's or the failure's words.
pub const LAST_RESULT: &str = "command/last_result";

/// The node's rebirth request (NCMD) and its metric in the NBIRTH.
pub const REBIRTH: &str = "Node Control/Rebirth";

/// The birth/death sequence number's metric.
pub const BD_SEQ: &str = "bdSeq";

/// A metric with `name`, `datatype`, `value` (at `timestamp`, ms).
pub fn metric(name: &str, datatype: DataType, value: Value, timestamp: u64) -> Metric {
    let (value, is_null) = match value {
        Value::Int(v) if datatype == DataType::Int64 => {
            (Some(metric::Value::LongValue(v as u64)), None)
        }
        // Sparkplug carries signed 8-32 bit integers in the unsigned
        // field, as their two's complement.
        Value::Int(v) => (Some(metric::Value::IntValue(v as i32 as u32)), None),
        Value::UInt(v) => (Some(metric::Value::IntValue(v)), None),
        Value::Double(v) => (Some(metric::Value::DoubleValue(v)), None),
        Value::Bool(v) => (Some(metric::Value::BooleanValue(v)), None),
        Value::Text(v) => (Some(metric::Value::StringValue(v)), None),
        Value::Null => (None, Some(true)),
    };
    Metric {
        name: Some(name.to_string()),
        timestamp: Some(timestamp),
        datatype: Some(datatype as u32),
        is_null,
        value,
        ..Default::default()
    }
}

/// The birth's properties of a metric: its unit (`engUnit`, as SCADA
/// hosts read it) and whether a host may write it (`readOnly`).
fn properties(unit: Option<&str>, read_only: bool) -> PropertySet {
    let mut set = PropertySet::default();
    if let Some(unit) = unit {
        set.keys.push("engUnit".to_string());
        set.values.push(PropertyValue {
            r#type: Some(DataType::String as u32),
            is_null: None,
            value: Some(property_value::Value::StringValue(unit.to_string())),
        });
    }
    set.keys.push("readOnly".to_string());
    set.values.push(PropertyValue {
        r#type: Some(DataType::Boolean as u32),
        is_null: None,
        value: Some(property_value::Value::BooleanValue(read_only)),
    });
    set
}

/// The last values a host wrote, as the drive confirmed them, for the
/// births (`None`: never written since start).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Setpoints {
    /// The last speed setpoint, rpm.
    pub speed_rpm: Option<f64>,
    /// The last position setpoint, degrees.
    pub position_deg: Option<f64>,
    /// The last torque setpoint, amps.
    pub torque_a: Option<f64>,
}

/// Every metric of a drive's DBIRTH: its status (or nulls without one),
/// the writable metrics with the last confirmed setpoints, and
/// `command/last_result`.
pub fn birth_metrics(
    status: Option<&Status>,
    setpoints: &Setpoints,
    last_result: &str,
    timestamp: u64,
) -> Vec<Metric> {
    let mut out = Vec::with_capacity(StatusField::ALL.len() + Writable::ALL.len() + 1);
    for field in StatusField::ALL {
        let value = status.map_or(Value::Null, |s| status_value(field, s));
        let mut m = status_metric(field, value, timestamp);
        m.properties = Some(properties(field.unit(), true));
        out.push(m);
    }
    for w in Writable::ALL {
        let value = match w {
            Writable::Activate | Writable::Deactivate | Writable::Brake | Writable::FaultReset => {
                Value::Bool(false)
            }
            Writable::Mode => {
                status.map_or(Value::Null, |s| Value::Text(s.mode().name().to_string()))
            }
            Writable::SpeedRpm => setpoints.speed_rpm.map_or(Value::Null, Value::Double),
            Writable::PositionDeg => setpoints.position_deg.map_or(Value::Null, Value::Double),
            Writable::TorqueA => setpoints.torque_a.map_or(Value::Null, Value::Double),
        };
        let mut m = metric(w.name(), w.datatype(), value, timestamp);
        m.properties = Some(properties(w.unit(), false));
        out.push(m);
    }
    let mut m = metric(
        LAST_RESULT,
        DataType::String,
        Value::Text(last_result.to_string()),
        timestamp,
    );
    m.properties = Some(properties(None, true));
    out.push(m);
    out
}

/// A metric's value as a host sent it, whatever its declared type.
pub fn incoming_value(m: &Metric) -> Option<&metric::Value> {
    if m.is_null == Some(true) {
        return None;
    }
    m.value.as_ref()
}

/// A number from a host's metric: any numeric type, signed ones read
/// back from their two's complement by the declared data type.
pub fn as_f64(m: &Metric) -> Option<f64> {
    let datatype = m.datatype.and_then(|d| DataType::try_from(d as i32).ok());
    Some(match incoming_value(m)? {
        metric::Value::IntValue(v) => match datatype {
            Some(DataType::Int8) => f64::from(*v as u8 as i8),
            Some(DataType::Int16) => f64::from(*v as u16 as i16),
            Some(DataType::Int32) => f64::from(*v as i32),
            _ => f64::from(*v),
        },
        metric::Value::LongValue(v) => match datatype {
            Some(DataType::Int64) => *v as i64 as f64,
            _ => *v as f64,
        },
        metric::Value::FloatValue(v) => f64::from(*v),
        metric::Value::DoubleValue(v) => *v,
        _ => return None,
    })
}

/// The value as a boolean, if it is one.
pub fn as_bool(m: &Metric) -> Option<bool> {
    match incoming_value(m)? {
        metric::Value::BooleanValue(v) => Some(*v),
        _ => None,
    }
}

/// The value as a string, if it is one.
pub fn as_str(m: &Metric) -> Option<&str> {
    match incoming_value(m)? {
        metric::Value::StringValue(v) => Some(v),
        _ => None,
    }
}

/// Read a metric's value back (tests, hosts written in Rust).
pub fn value_of(m: &Metric) -> Value {
    let datatype = m.datatype.and_then(|d| DataType::try_from(d as i32).ok());
    match incoming_value(m) {
        None => Value::Null,
        Some(metric::Value::BooleanValue(v)) => Value::Bool(*v),
        Some(metric::Value::StringValue(v)) => Value::Text(v.clone()),
        Some(metric::Value::DoubleValue(v)) => Value::Double(*v),
        Some(metric::Value::FloatValue(v)) => Value::Double(f64::from(*v)),
        Some(metric::Value::IntValue(v)) => match datatype {
            Some(DataType::Int8 | DataType::Int16 | DataType::Int32) => {
                Value::Int(i64::from(*v as i32))
            }
            _ => Value::UInt(*v),
        },
        Some(metric::Value::LongValue(v)) => Value::Int(*v as i64),
        Some(_) => Value::Null,
    }
}

#[doc(hidden)]
pub use payload::Metric as ProtoMetric;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signed_values_round_trip_through_the_unsigned_field() {
        let m = metric("status/speed_rpm", DataType::Int32, Value::Int(-150), 1);
        assert_eq!(m.value, Some(metric::Value::IntValue((-150i32) as u32)));
        assert_eq!(as_f64(&m), Some(-150.0));
        assert_eq!(value_of(&m), Value::Int(-150));
        let m = metric(BD_SEQ, DataType::Int64, Value::Int(7), 1);
        assert_eq!(value_of(&m), Value::Int(7));
    }

    #[test]
    fn status_values_are_of_their_declared_types() {
        let s = Status {
            turns: 7,
            angle_centideg: -4500,
            speed_rpm: -120,
            current_counts: 256,
            voltage_v: 24,
            temperature_c: -5,
            flags: Status::flags_from(
                true,
                true,
                false,
                crate::drive::Mode::Speed,
                crate::drive::Fault::Encoder,
            ),
        };
        for field in StatusField::ALL {
            let value = status_value(field, &s);
            let m = status_metric(field, value.clone(), 1);
            assert_eq!(value_of(&m), value, "{field:?}");
        }
        assert_eq!(status_name(StatusField::FaultCode), "status/fault_code");
        assert_eq!(
            status_value(StatusField::Fault, &s),
            Value::Text("encoder".into())
        );
        assert_eq!(status_value(StatusField::FaultCode, &s), Value::UInt(2));
    }

    #[test]
    fn births_carry_units_and_nulls_before_a_status() {
        let ms = birth_metrics(None, &Setpoints::default(), "", 5);
        let speed = ms
            .iter()
            .find(|m| m.name.as_deref() == Some("status/speed_rpm"))
            .unwrap();
        assert_eq!(speed.is_null, Some(true));
        let props = speed.properties.as_ref().unwrap();
        assert_eq!(props.keys, ["engUnit", "readOnly"]);
        assert_eq!(
            props.values[0].value,
            Some(property_value::Value::StringValue("rpm".into()))
        );
        let names: Vec<&str> = ms.iter().filter_map(|m| m.name.as_deref()).collect();
        for w in Writable::ALL {
            assert!(names.contains(&w.name()), "{}", w.name());
        }
        assert!(names.contains(&LAST_RESULT));
        assert_eq!(
            Writable::from_name("setpoint/torque_a"),
            Some(Writable::TorqueA)
        );
        assert_eq!(Writable::from_name("status/speed_rpm"), None);
    }
}
