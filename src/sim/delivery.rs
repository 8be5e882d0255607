//! How the reply's bytes reach the master: the moment each byte is handed
//! over, given when its last bit left the drive. Pure code.
//!
//! A UART on the master's board hands bytes over as they arrive, through
//! its receive FIFO and the kernel, a few at a time. What a master needs of
//! that timing is when a reply starts (the drive's turnaround) and when it
//! ends (the silence before the next request is counted from there); so the
//! simulated UART hands the first byte over as it arrives and the last as
//! it arrives, and the bytes between with the last, or, for a frame a
//! master can only end by silence, in pieces no further apart than t3.5
//! less t1.5 (never a silence that would end it). Each piece is a wake-up
//! of both the simulator and the master: a byte at a time would cost 19 of
//! each for a status reply.
//!
//! A USB adapter does not: it collects what the line carried and sends it to the
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
    /// Bytes handed over together (1: a UART, see the module's doc).
    pub chunk_bytes: u16,
    /// Largest extra delay of each chunk after its last byte was on the
    /// wire, in microseconds; each chunk draws its delay uniformly from 0 to
    /// this (0: none).
    pub jitter_us: u32,
}

impl Default for Delivery {
    /// A UART: on time, the first and last bytes as they arrive.
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

    /// True for a UART's delivery (on time).
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
    /// before the byte was on the wire, never out of order. `by_length`
    /// says a master can tell the frame's length from its first bytes (a
    /// reply to a function it knows); else it ends the frame by silence.
    pub fn schedule(
        &self,
        line: &LineTiming,
        start: Instant,
        len: usize,
        by_length: bool,
        rng: &mut impl Rng,
        out: &mut Vec<Instant>,
    ) {
        out.clear();
        if self.is_exact() {
            return uart(line, start, len, by_length, out);
        }
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

/// A UART's schedule (see the module's doc): byte 0 as it arrives; the
/// others with the last, or, for a frame ended by silence, with the piece
/// they end, pieces being cut back from the last byte at most t3.5 - t1.5
/// apart.
fn uart(line: &LineTiming, start: Instant, len: usize, by_length: bool, out: &mut Vec<Instant>) {
    if len == 0 {
        return;
    }
    let piece = if by_length {
        len
    } else {
        // The most characters whose wire time is shorter than t3.5 - t1.5
        // (11 at 115200 baud, 1 at 19200 baud and below).
        let apart = line.t3_5().saturating_sub(line.t1_5());
        (1..len)
            .take_while(|&k| line.wire_time(k + 1) < apart)
            .last()
            .map_or(1, |k| k + 1)
    };
    out.push(start + line.wire_time(1));
    // The pieces after the first byte, cut back from the last: byte i goes
    // with the piece that ends at the first cut at or after it.
    for i in 1..len {
        let from_end = (len - 1 - i) / piece * piece;
        out.push(start + line.wire_time(len - from_end));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_uart_hands_the_first_and_the_last_byte_over_as_they_arrive() {
        let line = LineTiming::new_8n1(115_200);
        let start = Instant::now();
        let mut out = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // A status reply (19 bytes), framed by its length: the first byte
        // alone, the other 18 with the last.
        Delivery::default().schedule(&line, start, 19, true, &mut rng, &mut out);
        assert_eq!(out.len(), 19);
        assert_eq!(out[0], start + line.wire_time(1));
        assert!(out[1..].iter().all(|&t| t == start + line.wire_time(19)));
        // One byte: as it arrives.
        Delivery::default().schedule(&line, start, 1, true, &mut rng, &mut out);
        assert_eq!(out, [start + line.wire_time(1)]);
    }

    #[test]
    fn a_frame_ended_by_silence_comes_in_pieces_closer_than_t3_5_less_t1_5() {
        for baud in [9600, 19_200, 115_200] {
            let line = LineTiming::new_8n1(baud);
            let start = Instant::now();
            let mut out = Vec::new();
            let mut rng = ChaCha8Rng::seed_from_u64(1);
            Delivery::default().schedule(&line, start, 40, false, &mut rng, &mut out);
            assert_eq!(out.len(), 40);
            assert_eq!(out[0], start + line.wire_time(1), "{baud}");
            assert_eq!(out[39], start + line.wire_time(40), "{baud}");
            for (i, &at) in out.iter().enumerate() {
                // Never before the byte was on the wire, in order.
                assert!(at >= start + line.wire_time(i + 1), "{baud}: byte {i}");
                assert!(i == 0 || at >= out[i - 1]);
            }
            // No pause a master would end the frame at.
            let most = line.t3_5() - line.t1_5();
            assert!(out.windows(2).all(|w| w[1] - w[0] < most), "{baud}");
            // As few pieces as that allows: the first byte, then pieces of
            // as many characters as fit in it.
            let per_piece = (1..40)
                .take_while(|&k| line.wire_time(k) < most)
                .count()
                .max(1);
            let mut pieces = out.clone();
            pieces.dedup();
            assert_eq!(pieces.len(), 1 + 39usize.div_ceil(per_piece), "{baud}");
        }
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
            usb.schedule(&line, start, 19, true, &mut rng, &mut out);
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
