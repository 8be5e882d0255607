//! How the reply's bytes reach the master: the moment each byte is handed
//! over, given when its last bit left the drive. Pure code.
//!
//! A UART on the master's board hands every byte over as it arrives. A USB
//! adapter does not: it collects what the line carried and sends it to the
//! host in packets, a little after the bytes were on the wire, and the host's
//! USB stack adds its own jitter. A master that counts the 3.5-character
//! silence from the last byte it *received* then leaves the line idle longer
//! than it needs to, and the simulator can model that ("a foreign wire") so
//! the cost shows in the benchmarks.

use std::time::{Duration, Instant};

use rand::Rng;
use serde::Deserialize;

use super::config_error::ConfigError;
use crate::drive::RangeError;
use crate::modbus::timing::LineTiming;

/// How received bytes are handed to the master.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Delivery {
    /// Bytes handed over together (1: each byte as it arrives, like a UART).
    pub chunk_bytes: u16,
    /// Largest extra delay of each chunk after its last byte was on the
    /// wire, in microseconds; each chunk draws its delay uniformly from 0 to
    /// this (0: none).
    pub jitter_us: u32,
}

impl Default for Delivery {
    /// Byte by byte, on time: a UART.
    fn default() -> Self {
        Self {
            chunk_bytes: 1,
            jitter_us: 0,
        }
    }
}

impl Delivery {
    /// A USB adapter as the benchmarks model it: 8-byte chunks, each up to
    /// 0.5 ms late.
    pub const USB: Delivery = Delivery {
        chunk_bytes: 8,
        jitter_us: 500,
    };

    /// True for a UART's delivery (every byte on time).
    pub fn is_exact(&self) -> bool {
        self.chunk_bytes <= 1 && self.jitter_us == 0
    }

    /// Checks the values, naming what is wrong.
    pub fn validate(&self) -> Result<(), ConfigError> {
        RangeError::check(
            "chunk size",
            f64::from(self.chunk_bytes),
            1.0,
            256.0,
            "bytes",
        )?;
        RangeError::check(
            "delivery jitter",
            f64::from(self.jitter_us),
            0.0,
            100_000.0,
            "us",
        )?;
        Ok(())
    }

    /// When each of `len` bytes is handed over, for a frame whose first bit
    /// leaves the drive at `start`: `out[i]` is byte `i`'s moment. Never
    /// before the byte was on the wire, never out of order.
    pub fn schedule(
        &self,
        line: &LineTiming,
        start: Instant,
        len: usize,
        rng: &mut impl Rng,
        out: &mut Vec<Instant>,
    ) {
        out.clear();
        let chunk = usize::from(self.chunk_bytes.max(1));
        let mut previous = start;
        let mut first = 0;
        while first < len {
            let end = (first + chunk).min(len);
            let on_wire = start + line.wire_time(end);
            let delay = if self.jitter_us == 0 {
                Duration::ZERO
            } else {
                Duration::from_micros(rng.random_range(0..=u64::from(self.jitter_us)))
            };
            let at = (on_wire + delay).max(previous);
            out.extend(std::iter::repeat_n(at, end - first));
            previous = at;
            first = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_uart_hands_each_byte_over_as_its_last_bit_arrives() {
        let line = LineTiming::new_8n1(115_200);
        let start = Instant::now();
        let mut out = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        Delivery::default().schedule(&line, start, 3, &mut rng, &mut out);
        assert_eq!(
            out,
            [1, 2, 3].map(|i| start + line.wire_time(i)).to_vec(),
            "one character time apart"
        );
    }

    #[test]
    fn a_usb_adapter_hands_over_chunks_late_but_in_order() {
        let line = LineTiming::new_8n1(115_200);
        let start = Instant::now();
        let mut out = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let usb = Delivery {
            chunk_bytes: 8,
            jitter_us: 500,
        };
        for _ in 0..200 {
            usb.schedule(&line, start, 19, &mut rng, &mut out);
            assert_eq!(out.len(), 19);
            // Chunks of 8, 8 and 3 bytes: bytes of a chunk arrive together.
            assert!(out[..8].iter().all(|&t| t == out[0]));
            assert!(out[8..16].iter().all(|&t| t == out[8]));
            assert!(out[16..].iter().all(|&t| t == out[16]));
            for (i, &at) in out.iter().enumerate() {
                // Never before the chunk's last byte was on the wire, at most
                // the jitter after it (or after the previous chunk).
                let chunk_end = ((i / 8 + 1) * 8).min(19);
                let on_wire = start + line.wire_time(chunk_end);
                assert!(at >= on_wire);
                assert!(at <= on_wire.max(out[i.saturating_sub(8)]) + Duration::from_micros(500));
            }
            assert!(out.windows(2).all(|w| w[0] <= w[1]));
        }
    }

    #[test]
    fn silly_values_are_refused() {
        assert!(Delivery::default().validate().is_ok());
        assert!(Delivery::USB.validate().is_ok());
        let zero = Delivery {
            chunk_bytes: 0,
            jitter_us: 0,
        };
        assert!(
            zero.validate()
                .unwrap_err()
                .to_string()
                .starts_with("chunk size 0")
        );
    }
}
