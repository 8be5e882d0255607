//! What a client asks a capture to be, and the check that it fits the
//! scope's limits, with what would fit when it does not.

use std::time::Duration;

use super::trigger::Trigger;
use crate::drive::{RangeError, StatusField};

/// A length: a number of samples per captured drive, or a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Amount {
    /// Samples of each captured drive.
    Samples(u32),
    /// Seconds.
    Seconds(f64),
}

/// What a client asks for, drives as unit addresses.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureSpec {
    /// The drives captured (polled at the bus's full rate meanwhile).
    pub units: Vec<u8>,
    /// The fields kept in the result.
    pub fields: Vec<StatusField>,
    /// What starts it.
    pub trigger: Trigger,
    /// What to keep from before the trigger.
    pub pre_trigger: Amount,
    /// What to keep from the trigger on.
    pub length: Amount,
    /// How long to wait for the trigger before giving up.
    pub wait: Duration,
}

/// The limits a capture must fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Samples one capture may hold (`[scope] max_samples`).
    pub max_samples: usize,
    /// The most status reads per second the wire carries (no turnaround).
    pub wire_rate: f64,
    /// Longest wait for a trigger.
    pub max_wait: Duration,
}

/// Longest capture or pre-trigger time, s.
pub const MAX_SECONDS: f64 = 3600.0;

impl Amount {
    /// Samples it takes at most for `drives` drives on a wire that carries
    /// `wire_rate` reads per second (a time is sized at the wire's rate,
    /// plus 5 % and one per drive for timing jitter).
    pub fn capacity(self, drives: usize, wire_rate: f64) -> usize {
        match self {
            Amount::Samples(n) => n as usize * drives,
            Amount::Seconds(s) => (s * wire_rate * 1.05).ceil() as usize + drives,
        }
    }

    fn describe(self) -> String {
        match self {
            Amount::Samples(n) => format!("{n} samples per drive"),
            Amount::Seconds(s) => format!("{s} s"),
        }
    }
}

/// Why a capture cannot be armed as asked.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    /// Contradictory or incomplete.
    #[error("{0}")]
    Invalid(String),
    /// A value out of its range (or a capture larger than allowed), with
    /// what would fit.
    #[error("{range}{hint}")]
    Range {
        /// The range.
        range: RangeError,
        /// What would fit, when the range alone does not say.
        hint: String,
    },
}

fn range(r: Result<f64, RangeError>) -> Result<f64, SpecError> {
    r.map_err(|range| SpecError::Range {
        range,
        hint: String::new(),
    })
}

impl CaptureSpec {
    /// Checks the capture against `limits`; returns the pre-trigger and
    /// post-trigger capacities in samples.
    pub fn check(&self, limits: &Limits) -> Result<(usize, usize), SpecError> {
        let invalid = |m: String| Err(SpecError::Invalid(m));
        if self.units.is_empty() {
            return invalid("capture at least one drive".into());
        }
        if let Some(unit) = self.trigger.watched_unit()
            && !self.units.contains(&unit)
        {
            return invalid(format!(
                "the trigger watches unit {unit}, which is not captured: capture it too"
            ));
        }
        if self.fields.is_empty() {
            return invalid("choose at least one field".into());
        }
        let drives = self.units.len();
        let per_drive = (limits.max_samples / drives) as f64;
        for (quantity, amount, min) in [
            ("pre-trigger", self.pre_trigger, 0.0),
            ("capture length", self.length, 1.0),
        ] {
            match amount {
                Amount::Samples(n) => {
                    range(RangeError::check(
                        quantity,
                        f64::from(n),
                        min,
                        per_drive,
                        "samples per drive",
                    ))?;
                }
                Amount::Seconds(s) => {
                    range(RangeError::check(
                        quantity,
                        s,
                        min * 0.001,
                        MAX_SECONDS,
                        "s",
                    ))?;
                }
            }
        }
        range(RangeError::check(
            "trigger wait",
            self.wait.as_secs_f64(),
            0.001,
            limits.max_wait.as_secs_f64(),
            "s",
        ))?;
        let pre = self.pre_trigger.capacity(drives, limits.wire_rate);
        let post = self.length.capacity(drives, limits.wire_rate);
        if pre + post > limits.max_samples {
            let seconds = limits.max_samples as f64 / (limits.wire_rate * 1.05);
            return Err(SpecError::Range {
                range: RangeError {
                    quantity: "capture size",
                    value: (pre + post) as f64,
                    min: 1.0,
                    max: limits.max_samples as f64,
                    unit: "samples",
                },
                hint: format!(
                    " ([scope] max_samples): a pre-trigger of {} and a length of {} need up to {} samples; at most {per_drive} samples per drive for {drives} drive(s) fit, or about {seconds:.1} s in all at the wire's rate",
                    self.pre_trigger.describe(),
                    self.length.describe(),
                    pre + post,
                ),
            });
        }
        Ok((pre, post))
    }
}

/// Limits and specs for the scope's unit tests (this module's and the
/// capture's).
#[cfg(test)]
pub(crate) mod fixtures {
    use super::*;

    /// A 10,000-sample, 171.1 polls/s, one-hour limit.
    pub(crate) fn limits() -> Limits {
        Limits {
            max_samples: 10_000,
            wire_rate: 171.1,
            max_wait: Duration::from_secs(3600),
        }
    }

    /// The speed of `units`, with `trigger`, `pre` and `length`.
    pub(crate) fn spec(units: &[u8], trigger: Trigger, pre: Amount, length: Amount) -> CaptureSpec {
        CaptureSpec {
            units: units.to_vec(),
            fields: vec![StatusField::SpeedRpm],
            trigger,
            pre_trigger: pre,
            length,
            wait: Duration::from_secs(10),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::fixtures::{limits, spec};
    use super::*;

    #[test]
    fn memory_is_bounded_and_the_refusal_says_what_fits() {
        let s = spec(
            &[1, 2],
            Trigger::Manual,
            Amount::Samples(1000),
            Amount::Seconds(60.0),
        );
        let e = s.check(&limits()).unwrap_err().to_string();
        assert!(
            e.contains("valid 1 to 10000 samples ([scope] max_samples)")
                && e.contains("5000 samples per drive"),
            "{e}"
        );
        let ok = spec(
            &[1, 2],
            Trigger::Manual,
            Amount::Samples(100),
            Amount::Seconds(10.0),
        );
        let (pre, post) = ok.check(&limits()).unwrap();
        assert_eq!((pre, post), (200, 1799));
        let mut bad = ok.clone();
        bad.trigger = Trigger::Stall { unit: 3 };
        assert!(
            bad.check(&limits())
                .unwrap_err()
                .to_string()
                .contains("not captured")
        );
        bad = ok.clone();
        bad.length = Amount::Samples(0);
        assert!(bad.check(&limits()).is_err());
        bad = ok.clone();
        bad.units.clear();
        assert!(bad.check(&limits()).is_err());
        bad = ok;
        bad.pre_trigger = Amount::Seconds(-1.0);
        let e = bad.check(&limits()).unwrap_err().to_string();
        assert_eq!(e, "pre-trigger -1 s is out of range: valid 0 to 3600 s");
    }
}
