//! Report by exception: of each new status of a drive, only the fields
//! that moved further than their deadband from the value last published
//! (booleans, names and counts: on any change). A value that settles
//! within the deadband of the last published one (a ramp to 120 rpm whose
//! last poll caught 119) is published once it has held for
//! [`SETTLE_POLLS`] polls, so the host's value ends equal to the drive's
//! after every change. Pure: no I/O.

use super::metric::{self, Value};
use crate::config::mqtt::Deadbands;
use crate::drive::{Status, StatusField};

/// Polls in a row a value within its deadband must be read unchanged
/// before it is published: long enough that noise is not reported, short
/// enough that a settled value reaches the host within a second at any
/// usual poll rate.
pub const SETTLE_POLLS: u32 = 3;

/// What was last published of one drive's status fields.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Reported {
    last: Vec<Option<Value>>,
    /// Per field, a value within the band of the last published one but
    /// not equal to it, and the polls in a row it has been read.
    settling: Vec<Option<(Value, u32)>>,
}

impl Reported {
    /// The values a birth published (every field of `status`).
    pub fn born(status: Option<&Status>) -> Self {
        Reported {
            last: StatusField::ALL
                .iter()
                .map(|f| status.map(|s| metric::status_value(*f, s)))
                .collect(),
            settling: vec![None; StatusField::ALL.len()],
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
    ) -> Vec<(StatusField, Value)> {
        if self.last.len() != StatusField::ALL.len() {
            self.last = vec![None; StatusField::ALL.len()];
        }
        if self.settling.len() != StatusField::ALL.len() {
            self.settling = vec![None; StatusField::ALL.len()];
        }
        let mut out = Vec::new();
        for (i, field) in StatusField::ALL.iter().enumerate() {
            let now = metric::status_value(*field, status);
            let publish = full
                || match (&self.last[i], metric::deadband(*field, deadbands)) {
                    (None, _) => true,
                    (Some(last), Some(band)) => {
                        moved(last, &now) > band || settled(&mut self.settling[i], last, &now)
                    }
                    (Some(last), None) => *last != now,
                };
            if publish {
                self.last[i] = Some(now.clone());
                self.settling[i] = None;
                out.push((*field, now));
            }
        }
        out
    }
}

/// True when `now`, within the band of `last` but not equal to it, has
/// now been read [`SETTLE_POLLS`] times in a row (`settling` counts them).
fn settled(settling: &mut Option<(Value, u32)>, last: &Value, now: &Value) -> bool {
    if now == last {
        *settling = None;
        return false;
    }
    let held = match settling.take() {
        Some((value, polls)) if value == *now => polls + 1,
        _ => 1,
    };
    if held >= SETTLE_POLLS {
        return true;
    }
    *settling = Some((now.clone(), held));
    false
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
        assert_eq!(c, vec![(StatusField::SpeedRpm, Value::Int(102))]);
        // The band is measured from the value last published (102), so a
        // slow drift is published once it adds up.
        assert!(r.changes(&status(103, 30, 5), &bands, false).is_empty());
        assert_eq!(r.changes(&status(104, 30, 5), &bands, false).len(), 1);
        // Counts have no band.
        let c = r.changes(&status(104, 30, 6), &bands, false);
        assert_eq!(c, vec![(StatusField::Turns, Value::UInt(6))]);
    }

    /// Speeds a poll catches of a ramp from 0 to `to` in steps of `step`.
    fn ramp(to: i16, step: i16) -> Vec<i16> {
        (0..=to / step).map(|k| k * step).collect()
    }

    #[test]
    fn a_ramp_that_ends_within_the_band_is_published_once_it_held() {
        let bands = Deadbands::default(); // speed 1 rpm
        let mut r = Reported::born(Some(&status(0, 30, 0)));
        let mut host = 0_i64;
        let mut publish = |r: &mut Reported, rpm: i16| {
            for (f, v) in r.changes(&status(rpm, 30, 0), &bands, false) {
                if let (StatusField::SpeedRpm, Value::Int(v)) = (f, v) {
                    host = v;
                }
            }
            host
        };
        // The polls caught the ramp up to 119 rpm in steps of 7: the last
        // published value is 119, the drive settles at 120, 1 rpm away.
        for rpm in ramp(119, 7) {
            publish(&mut r, rpm);
        }
        assert_eq!(publish(&mut r, 119), 119);
        // 120 is within the band: not at once, and not while it may be
        // noise, but once it held for SETTLE_POLLS polls.
        for _ in 1..SETTLE_POLLS {
            assert_eq!(publish(&mut r, 120), 119);
        }
        assert_eq!(publish(&mut r, 120), 120);
        // Published once: no more while it holds.
        for _ in 0..10 {
            assert!(r.changes(&status(120, 30, 0), &bands, false).is_empty());
        }
        // A value that wobbles within the band never holds: not published.
        for rpm in [121, 120, 121, 120, 121, 120] {
            assert_eq!(publish(&mut r, rpm), 120);
        }
        // Back down a ramp that ends 1 rpm above the last published value.
        let mut seen = 0;
        for rpm in [100, 80, 61] {
            seen = publish(&mut r, rpm);
        }
        assert_eq!(seen, 61);
        for _ in 0..SETTLE_POLLS {
            seen = publish(&mut r, 60);
        }
        assert_eq!(seen, 60);
    }

    #[test]
    fn a_full_publish_sends_every_field() {
        let mut r = Reported::born(None);
        // Nothing published yet: everything is new.
        let all = r.changes(&status(0, 20, 0), &Deadbands::default(), false);
        assert_eq!(all.len(), StatusField::ALL.len());
        let again = r.changes(&status(0, 20, 0), &Deadbands::default(), true);
        assert_eq!(again.len(), StatusField::ALL.len());
    }
}
