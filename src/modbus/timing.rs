//! RTU line timing: character time, the 1.5 and 3.5 character silences, wire time.
//!
//! Above 19200 baud the Modbus serial line specification fixes t1.5 at 750 us
//! and t3.5 at 1750 us instead of scaling them with the character time.

use std::time::Duration;

/// Timing of one serial line (baud and bits per character).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineTiming {
    baud: u32,
    bits_per_char: u32,
}

impl LineTiming {
    /// 8N1 (10 bits a character: start, 8 data, stop) at `baud`.
    pub fn new_8n1(baud: u32) -> Self {
        Self {
            baud: baud.max(1),
            bits_per_char: 10,
        }
    }

    /// The line's baud rate.
    pub fn baud(&self) -> u32 {
        self.baud
    }

    /// Time one character takes on the wire (86.8 us at 115200 8N1).
    pub fn char_time(&self) -> Duration {
        Duration::from_nanos(u64::from(self.bits_per_char) * 1_000_000_000 / u64::from(self.baud))
    }

    /// Time `bytes` characters take on the wire.
    pub fn wire_time(&self, bytes: usize) -> Duration {
        Duration::from_nanos(
            bytes as u64 * u64::from(self.bits_per_char) * 1_000_000_000 / u64::from(self.baud),
        )
    }

    /// Longest silence allowed inside a frame.
    pub fn t1_5(&self) -> Duration {
        if self.baud > 19_200 {
            Duration::from_micros(750)
        } else {
            self.char_time() * 3 / 2
        }
    }

    /// Silence that separates frames (1.75 ms above 19200 baud).
    pub fn t3_5(&self) -> Duration {
        if self.baud > 19_200 {
            Duration::from_micros(1750)
        } else {
            self.char_time() * 7 / 2
        }
    }

    /// Shortest possible duration of one request/reply transaction: both
    /// frames on the wire, the silence after each, and the drive's turnaround.
    pub fn transaction_time(
        &self,
        request_bytes: usize,
        reply_bytes: usize,
        turnaround: Duration,
    ) -> Duration {
        self.wire_time(request_bytes + reply_bytes) + self.t3_5() * 2 + turnaround
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_at_115200() {
        let line = LineTiming::new_8n1(115_200);
        assert_eq!(line.char_time(), Duration::from_nanos(86_805));
        assert_eq!(line.t3_5(), Duration::from_micros(1750));
        // status poll: 8-byte request + 19-byte reply + 2 x t3.5 = 5.844 ms -> 171 polls/s
        let t = line.transaction_time(8, 19, Duration::ZERO);
        assert_eq!(t.as_micros(), 5843);
        assert_eq!((1.0 / t.as_secs_f64()) as u32, 171);
    }

    #[test]
    fn slow_lines_scale_the_silences() {
        let line = LineTiming::new_8n1(9600);
        assert_eq!(line.t3_5(), line.char_time() * 7 / 2);
        assert!(line.t3_5() > Duration::from_millis(3));
    }
}
