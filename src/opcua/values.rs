//! A drive's values as OPC UA data values: each with its poll's source
//! timestamp and a status code from the freshness the bus decided
//! (`crate::bus::freshness`), the same answer every face gives. Pure.
//!
//! | freshness | status code |
//! |---|---|
//! | live | `Good` |
//! | stale | `UncertainLastUsableValue`, the last value polled |
//! | offline, bus down, never answered | `BadNoCommunication`, no value |
//! | not polled yet | `BadWaitingForInitialData`, no value |
//!
//! `Online` is always `Good`: it is the answer to whether the drive is on
//! line (true while its data is live or stale).

use std::time::{SystemTime, UNIX_EPOCH};

use opcua::types::{DataValue, DateTime, StatusCode, Variant};

use super::spec::{Kind, Setpoint, Source, Variable};
use crate::bus::freshness::{Cause, Freshness, Verdict};
use crate::drive::Status;
use crate::drive::StatusField;
use crate::drive::settings::DriveSettings;
use crate::drive::units::COUNTS_PER_AMP;
use crate::drive::wanted::Setting;

/// Ticks (100 ns) from OPC UA's epoch (1601-01-01) to the Unix epoch.
const UNIX_EPOCH_TICKS: i64 = 116_444_736_000_000_000;

/// `t` as an OPC UA time.
pub fn date_time(t: SystemTime) -> DateTime {
    let ticks = match t.duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_nanos() / 100).unwrap_or(i64::MAX - UNIX_EPOCH_TICKS),
        Err(e) => -i64::try_from(e.duration().as_nanos() / 100).unwrap_or(0),
    };
    DateTime::from(UNIX_EPOCH_TICKS.saturating_add(ticks))
}

/// An OPC UA time as Unix milliseconds.
pub fn unix_ms(t: &DateTime) -> i64 {
    (t.ticks() - UNIX_EPOCH_TICKS).div_euclid(10_000)
}

/// The status code of data as fresh as `verdict` says.
pub fn quality(verdict: &Verdict) -> StatusCode {
    match verdict.freshness {
        Freshness::Live => StatusCode::Good,
        Freshness::Stale => StatusCode::UncertainLastUsableValue,
        Freshness::Never if verdict.cause == Cause::NotPolledYet => {
            StatusCode::BadWaitingForInitialData
        }
        Freshness::Offline | Freshness::Never | Freshness::BusDown => {
            StatusCode::BadNoCommunication
        }
    }
}

/// True when the drive is on line: its data live, or late but not given up.
pub fn online(verdict: &Verdict) -> bool {
    matches!(verdict.freshness, Freshness::Live | Freshness::Stale)
}

/// A number as a variable of `kind` holds it.
pub fn number(kind: Kind, value: f64) -> Variant {
    match kind {
        Kind::Double => Variant::Double(value),
        Kind::Int32 | Kind::Mode => Variant::Int32(value as i32),
        Kind::UInt16 => Variant::UInt16(value as u16),
        Kind::UInt32 => Variant::UInt32(value as u32),
        Kind::Boolean => Variant::Boolean(value != 0.0),
        Kind::String => Variant::from(value.to_string()),
    }
}

/// The value of status field `field` in `status`.
pub fn status_value(field: StatusField, status: &Status) -> Variant {
    match field {
        StatusField::SpeedRpm => Variant::Double(f64::from(status.speed_rpm)),
        StatusField::AngleDeg => Variant::Double(status.angle_deg()),
        StatusField::Turns => Variant::Int32(i32::from(status.turns)),
        StatusField::CurrentA => Variant::Double(status.current_a()),
        StatusField::VoltageV => Variant::Double(f64::from(status.voltage_v)),
        StatusField::TemperatureC => Variant::Double(f64::from(status.temperature_c)),
        StatusField::Active => Variant::Boolean(status.active()),
        StatusField::Stalled => Variant::Boolean(status.stalled()),
        StatusField::Calibrated => Variant::Boolean(status.calibrated()),
        // The STATUS bits are DriveMode's values (spec::MODES).
        StatusField::Mode => Variant::Int32(i32::from(status.mode().bits())),
        StatusField::Fault => Variant::from(status.fault().name()),
        StatusField::FaultCode => Variant::UInt16(status.fault().code()),
    }
}

/// The value of a setpoint or setting variable in what a drive holds.
pub fn held_value(variable: &Variable, held: &DriveSettings) -> Option<Variant> {
    let value = match variable.source {
        Source::Setpoint(Setpoint::Speed) => f64::from(held.speed_rpm),
        Source::Setpoint(Setpoint::Position) => f64::from(held.position_centideg) / 100.0,
        Source::Setpoint(Setpoint::Torque) => f64::from(held.torque_counts) / COUNTS_PER_AMP,
        Source::Setting(Setting::Rs485Control) => {
            return Some(Variant::Boolean(held.rs485_control));
        }
        Source::Setting(Setting::CurrentLimit) => f64::from(held.limit_counts) / COUNTS_PER_AMP,
        Source::Setting(setting) => f64::from(setting.held(held)),
        Source::Status(_) | Source::Online => return None,
    };
    Some(number(variable.kind, value))
}

/// A data value with `status`, stamped `source` and now; a Bad one holds
/// no value (Part 4, 7.11).
pub fn data_value(value: Variant, status: StatusCode, source: SystemTime) -> DataValue {
    let now = DateTime::now();
    DataValue {
        value: (!status.is_bad()).then_some(value),
        status: Some(status),
        source_timestamp: Some(date_time(source)),
        source_picoseconds: None,
        server_timestamp: Some(now),
        server_picoseconds: None,
    }
}

/// A value with no data and why: a Bad status, stamped now.
pub fn missing(status: StatusCode) -> DataValue {
    let now = DateTime::now();
    DataValue {
        value: None,
        status: Some(status),
        source_timestamp: Some(now),
        source_picoseconds: None,
        server_timestamp: Some(now),
        server_picoseconds: None,
    }
}

/// The value of a drive's status variable (or `Online`) from its last
/// status `last` (with when it was read) and its freshness `verdict`.
pub fn drive_value(
    variable: &Variable,
    last: Option<(&Status, SystemTime)>,
    verdict: &Verdict,
    now: SystemTime,
) -> Option<DataValue> {
    match variable.source {
        Source::Online => Some(data_value(
            Variant::Boolean(online(verdict)),
            StatusCode::Good,
            verdict.since.unwrap_or(now),
        )),
        Source::Status(field) => Some(match last {
            Some((status, at)) => data_value(status_value(field, status), quality(verdict), at),
            None => missing(quality(verdict)),
        }),
        Source::Setpoint(_) | Source::Setting(_) => None,
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::opcua::spec::VARIABLES;

    fn verdict(freshness: Freshness, cause: Cause) -> Verdict {
        Verdict {
            freshness,
            since: None,
            age: None,
            cause,
            stale_at: None,
        }
    }

    fn variable(name: &str) -> &'static Variable {
        VARIABLES.iter().find(|v| v.name == name).unwrap()
    }

    #[test]
    fn freshness_is_the_status_code() {
        let down = Cause::PortDown {
            reason: "unplugged".into(),
        };
        let cases = [
            (Freshness::Live, Cause::Polled, StatusCode::Good),
            (
                Freshness::Stale,
                Cause::Late {
                    period: Duration::from_millis(100),
                },
                StatusCode::UncertainLastUsableValue,
            ),
            (
                Freshness::Offline,
                Cause::NoAnswer {
                    failures: 3,
                    last_failure: None,
                },
                StatusCode::BadNoCommunication,
            ),
            (Freshness::BusDown, down, StatusCode::BadNoCommunication),
            (
                Freshness::Never,
                Cause::NotPolledYet,
                StatusCode::BadWaitingForInitialData,
            ),
            (
                Freshness::Never,
                Cause::NeverAnswered {
                    failures: 1,
                    last_failure: None,
                },
                StatusCode::BadNoCommunication,
            ),
        ];
        for (freshness, cause, code) in cases {
            assert_eq!(quality(&verdict(freshness, cause)), code, "{freshness:?}");
        }
    }

    #[test]
    fn a_stale_value_keeps_its_value_and_a_bad_one_has_none() {
        let status = Status {
            speed_rpm: 1200,
            ..Status::default()
        };
        let at = UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let speed = variable("Speed");
        let late = verdict(
            Freshness::Stale,
            Cause::Late {
                period: Duration::ZERO,
            },
        );
        let dv = drive_value(speed, Some((&status, at)), &late, at).unwrap();
        assert_eq!(dv.value, Some(Variant::Double(1200.0)));
        assert_eq!(dv.status, Some(StatusCode::UncertainLastUsableValue));
        assert_eq!(
            dv.source_timestamp.map(|t| unix_ms(&t)),
            Some(1_700_000_000_000)
        );
        let gone = verdict(
            Freshness::BusDown,
            Cause::PortDown {
                reason: String::new(),
            },
        );
        let dv = drive_value(speed, Some((&status, at)), &gone, at).unwrap();
        assert_eq!(dv.value, None);
        assert_eq!(dv.status, Some(StatusCode::BadNoCommunication));
        // Online is the answer, always Good.
        let dv = drive_value(variable("Online"), None, &gone, at).unwrap();
        assert_eq!(dv.value, Some(Variant::Boolean(false)));
        assert_eq!(dv.status, Some(StatusCode::Good));
    }

    #[test]
    fn status_fields_in_their_units() {
        let status = Status {
            turns: 7,
            angle_centideg: -4500,
            speed_rpm: -300,
            current_counts: 256,
            voltage_v: 48,
            temperature_c: 41,
            flags: Status::flags_from(
                true,
                true,
                false,
                crate::drive::Mode::Speed,
                crate::drive::Fault::OverTemperature,
            ),
        };
        let value = |name| match variable(name).source {
            Source::Status(f) => status_value(f, &status),
            _ => unreachable!(),
        };
        assert_eq!(value("Speed"), Variant::Double(-300.0));
        assert_eq!(value("Angle"), Variant::Double(-45.0));
        assert_eq!(value("Turns"), Variant::Int32(7));
        assert_eq!(value("Current"), Variant::Double(2.0));
        assert_eq!(value("Voltage"), Variant::Double(48.0));
        assert_eq!(value("Temperature"), Variant::Double(41.0));
        assert_eq!(value("Active"), Variant::Boolean(true));
        assert_eq!(value("Mode"), Variant::Int32(1));
        assert_eq!(value("Fault"), Variant::from("over_temperature"));
        assert_eq!(value("FaultCode"), Variant::UInt16(4));
    }

    #[test]
    fn held_values_in_their_units() {
        let held = DriveSettings {
            speed_rpm: 600,
            position_centideg: 9000,
            torque_counts: -128,
            limit_counts: 1536,
            stall_ms: 500,
            speed_alpha: 250_000,
            position_alpha: 0,
            inertia_ratio: 3,
            rs485_control: true,
        };
        let value = |name| held_value(variable(name), &held).unwrap();
        assert_eq!(value("SpeedSetpoint"), Variant::Double(600.0));
        assert_eq!(value("PositionSetpoint"), Variant::Double(90.0));
        assert_eq!(value("TorqueSetpoint"), Variant::Double(-1.0));
        assert_eq!(value("CurrentLimit"), Variant::Double(12.0));
        assert_eq!(value("StallTime"), Variant::UInt32(500));
        assert_eq!(value("SpeedRampAlpha"), Variant::UInt32(250_000));
        assert_eq!(value("InertiaRatio"), Variant::UInt32(3));
        assert_eq!(value("Rs485Control"), Variant::Boolean(true));
        assert_eq!(held_value(variable("Speed"), &held), None);
    }

    #[test]
    fn times_round_trip() {
        let t = UNIX_EPOCH + Duration::from_millis(1_764_000_123_456);
        assert_eq!(unix_ms(&date_time(t)), 1_764_000_123_456);
    }
}
