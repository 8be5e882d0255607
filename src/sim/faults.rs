//! Fault injection on the simulated wire, reproducible from a seed.
//!
//! Every reply draws the same number of random values whatever the rates,
//! so the same seed and the same requests give the same faults, and raising
//! one rate does not reshuffle the others.

use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Deserialize;

use super::config_error::ConfigError;
use crate::drive::RangeError;

/// Per-reply fault injection rates (0.0 to 1.0), reproducible by seed.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct FaultRates {
    /// Fraction of requests that get no reply at all.
    pub drop_rate: f64,
    /// Fraction of replies sent with a corrupted CRC.
    pub crc_error_rate: f64,
    /// Fraction of replies sent `late_ms` late.
    pub late_rate: f64,
    /// How late a late reply is, in ms.
    pub late_ms: f64,
    /// Fraction of replies followed, about t3.5 after their end, by 1 to 4
    /// random bytes on the line.
    pub noise_rate: f64,
    /// Units that never answer.
    pub silent_units: Vec<u8>,
}

impl FaultRates {
    /// Checks every rate is a fraction and the delay a sane time.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, rate) in [
            ("drop rate", self.drop_rate),
            ("CRC error rate", self.crc_error_rate),
            ("late rate", self.late_rate),
            ("noise rate", self.noise_rate),
        ] {
            RangeError::check(name, rate, 0.0, 1.0, "")?;
        }
        RangeError::check("late reply delay", self.late_ms, 0.0, 60_000.0, "ms")?;
        Ok(())
    }

    /// True when `unit` never answers.
    pub fn is_silent(&self, unit: u8) -> bool {
        self.silent_units.contains(&unit)
    }
}

/// Random bytes written on the line between frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Noise {
    bytes: [u8; 4],
    len: usize,
}

impl Noise {
    /// The bytes (1 to 4).
    pub fn bytes(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

/// What happens to one reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct ReplyFate {
    /// The reply is not sent.
    pub drop: bool,
    /// Extra delay before the reply.
    pub late: Option<Duration>,
    /// XOR this mask into this CRC byte (0 = low, 1 = high); never zero.
    pub corrupt: Option<(usize, u8)>,
    /// Noise after the reply.
    pub noise: Option<Noise>,
}

/// The seeded source of faults.
#[derive(Debug, Clone)]
pub(crate) struct FaultInjector {
    rates: FaultRates,
    rng: ChaCha8Rng,
}

impl FaultInjector {
    /// Faults at `rates`, drawn from `seed`.
    pub(crate) fn new(rates: FaultRates, seed: u64) -> Self {
        FaultInjector {
            rates,
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// The rates in force.
    pub(crate) fn rates(&self) -> &FaultRates {
        &self.rates
    }

    /// Changes the rates; the random sequence goes on.
    pub(crate) fn set_rates(&mut self, rates: FaultRates) {
        self.rates = rates;
    }

    /// Makes `unit` silent or lets it answer again.
    pub(crate) fn set_silent(&mut self, unit: u8, silent: bool) {
        self.rates.silent_units.retain(|&u| u != unit);
        if silent {
            self.rates.silent_units.push(unit);
        }
    }

    /// Decides the fate of the next reply.
    pub(crate) fn decide(&mut self) -> ReplyFate {
        let drop: f64 = self.rng.random();
        let late: f64 = self.rng.random();
        let crc: f64 = self.rng.random();
        let noise: f64 = self.rng.random();
        let detail: u64 = self.rng.random();
        let r = &self.rates;
        if drop < r.drop_rate {
            return ReplyFate {
                drop: true,
                ..ReplyFate::default()
            };
        }
        let [n0, n1, n2, n3, mask, ..] = (detail >> 8).to_le_bytes();
        ReplyFate {
            drop: false,
            late: (late < r.late_rate)
                .then(|| Duration::from_secs_f64(r.late_ms.max(0.0) / 1000.0)),
            corrupt: (crc < r.crc_error_rate).then_some((
                ((detail >> 2) & 1) as usize,
                if mask == 0 { 0xFF } else { mask },
            )),
            noise: (noise < r.noise_rate).then_some(Noise {
                bytes: [n0, n1, n2, n3],
                len: 1 + (detail & 3) as usize,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rates() -> FaultRates {
        FaultRates {
            drop_rate: 0.1,
            crc_error_rate: 0.2,
            late_rate: 0.05,
            late_ms: 20.0,
            noise_rate: 0.3,
            silent_units: vec![3],
        }
    }

    #[test]
    fn same_seed_same_faults() {
        let mut a = FaultInjector::new(rates(), 7);
        let mut b = FaultInjector::new(rates(), 7);
        let mut c = FaultInjector::new(rates(), 8);
        let fa: Vec<_> = (0..200).map(|_| a.decide()).collect();
        let fb: Vec<_> = (0..200).map(|_| b.decide()).collect();
        let fc: Vec<_> = (0..200).map(|_| c.decide()).collect();
        assert_eq!(fa, fb);
        assert_ne!(fa, fc);
    }

    #[test]
    fn rates_are_roughly_met() {
        let mut f = FaultInjector::new(rates(), 1);
        let n = 20_000;
        let fates: Vec<_> = (0..n).map(|_| f.decide()).collect();
        let share = |p: &dyn Fn(&ReplyFate) -> bool| {
            fates.iter().filter(|x| p(x)).count() as f64 / n as f64
        };
        assert!((share(&|x| x.drop) - 0.1).abs() < 0.01);
        // The others apply to the replies that are not dropped.
        assert!((share(&|x| x.corrupt.is_some()) - 0.9 * 0.2).abs() < 0.01);
        assert!((share(&|x| x.late.is_some()) - 0.9 * 0.05).abs() < 0.01);
        assert!((share(&|x| x.noise.is_some()) - 0.9 * 0.3).abs() < 0.015);
        for x in &fates {
            if let Some((byte, mask)) = x.corrupt {
                assert!(byte < 2 && mask != 0);
            }
            if let Some(noise) = x.noise {
                assert!((1..=4).contains(&noise.bytes().len()));
            }
            if let Some(late) = x.late {
                assert_eq!(late, Duration::from_millis(20));
            }
        }
    }

    #[test]
    fn one_rate_does_not_reshuffle_the_others() {
        let mut a = FaultInjector::new(
            FaultRates {
                crc_error_rate: 0.3,
                ..FaultRates::default()
            },
            5,
        );
        let mut b = FaultInjector::new(
            FaultRates {
                crc_error_rate: 0.3,
                noise_rate: 0.5,
                ..FaultRates::default()
            },
            5,
        );
        for _ in 0..100 {
            assert_eq!(a.decide().corrupt, b.decide().corrupt);
        }
    }

    #[test]
    fn silent_units_and_validation() {
        let mut f = FaultInjector::new(rates(), 1);
        assert!(f.rates().is_silent(3));
        f.set_silent(3, false);
        f.set_silent(4, true);
        assert!(!f.rates().is_silent(3) && f.rates().is_silent(4));
        assert!(rates().validate().is_ok());
        let bad = FaultRates {
            late_rate: -0.1,
            ..rates()
        };
        assert!(bad.validate().is_err());
        let parsed: FaultRates = serde_json::from_str(r#"{"drop_rate": 0.5}"#).unwrap();
        assert_eq!(parsed.drop_rate, 0.5);
        assert!(serde_json::from_str::<FaultRates>(r#"{"drop": 0.5}"#).is_err());
    }
}
