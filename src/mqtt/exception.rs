//! Report by exception: of each new status of a drive, only the fields
//! that moved further than their deadband from the value last published
//! (booleans, names and counts: on any change). Pure: no I/O.

use super::metric::{Field, Value};
use crate::config::mqtt::Deadbands;
use crate::drive::Status;

/// What was last published of one drive's status fields.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Reported {
    last: Vec<Option<Value>>,
}

impl Reported {
    /// The values a birth published (every field of `status`).
    pub fn born(status: Option<&Status>) -> Self {
        Reported {
            last: Field::ALL
                .iter()
                .map(|f| status.map(|s| f.value(s)))
                .collect(),
        }
    }

    /// The fields of `status` to publish now, with their values; they
    /// become the last published. `full`: every field (a periodic full
    /// publish).
    pub fn changes(
        &mut self,
        status: &Status,
        deadbands: &Deadbands,
        full: bool,
    ) -> Vec<(Field, Value)> {
        if self.last.len() != Field::ALL.len() {
            self.last = vec![None; Field::ALL.len()];
        }
        let mut out = Vec::new();
        for (i, field) in Field::ALL.iter().enumerate() {
            let now = field.value(status);
            let publish = full
                || match (&self.last[i], field.deadband(deadbands)) {
                    (None, _) => true,
                    (Some(last), Some(band)) => moved(last, &now) > band,
                    (Some(last), None) => *last != now,
                };
            if publish {
                self.last[i] = Some(now.clone());
                out.push((*field, now));
            }
        }
        out
    }
}

/// How far `now` is from `last` (numbers; other kinds: 0 when equal, else
/// infinitely far).
fn moved(last: &Value, now: &Value) -> f64 {
    match (number(last), number(now)) {
        (Some(a), Some(b)) => (a - b).abs(),
        _ if last == now => 0.0,
        _ => f64::INFINITY,
    }
}

fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Int(v) => Some(*v as f64),
        Value::UInt(v) => Some(f64::from(*v)),
        Value::Double(v) => Some(*v),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(speed_rpm: i16, temperature_c: i16, turns: u16) -> Status {
        Status {
            speed_rpm,
            temperature_c,
            turns,
            voltage_v: 24,
            ..Status::default()
        }
    }

    #[test]
    fn only_what_moved_past_its_deadband_is_published() {
        let bands = Deadbands::default(); // speed 1 rpm, temperature 1 °C
        let mut r = Reported::born(Some(&status(100, 30, 5)));
        assert!(r.changes(&status(100, 30, 5), &bands, false).is_empty());
        // 1 rpm is within the band; 2 is beyond it.
        assert!(r.changes(&status(101, 30, 5), &bands, false).is_empty());
        let c = r.changes(&status(102, 30, 5), &bands, false);
        assert_eq!(c, vec![(Field::SpeedRpm, Value::Int(102))]);
        // The band is measured from the value last published (102), so a
        // slow drift is published once it adds up.
        assert!(r.changes(&status(103, 30, 5), &bands, false).is_empty());
        assert_eq!(r.changes(&status(104, 30, 5), &bands, false).len(), 1);
        // Counts have no band.
        let c = r.changes(&status(104, 30, 6), &bands, false);
        assert_eq!(c, vec![(Field::Turns, Value::UInt(6))]);
    }

    #[test]
    fn a_full_publish_sends_every_field() {
        let mut r = Reported::born(None);
        // Nothing published yet: everything is new.
        let all = r.changes(&status(0, 20, 0), &Deadbands::default(), false);
        assert_eq!(all.len(), Field::ALL.len());
        let again = r.changes(&status(0, 20, 0), &Deadbands::default(), true);
        assert_eq!(again.len(), Field::ALL.len());
    }
}
