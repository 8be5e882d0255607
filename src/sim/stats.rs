//! Counters of what the simulated wire saw and did.

use std::fmt;
use std::time::Duration;

/// Counters of the simulated wire since it started.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SimStats {
    /// Requests framed with a good CRC (any unit, broadcasts included).
    pub requests: u64,
    /// Replies put on the wire (corrupted and late ones included).
    pub replies: u64,
    /// Requests to unit 0.
    pub broadcasts: u64,
    /// Requests whose first byte arrived less than t3.5 after the end of
    /// the previous wire activity.
    pub gap_violations: u64,
    /// Frames ignored for a bad CRC.
    pub bad_crc_requests: u64,
    /// Partial frames dropped after a silence.
    pub truncated_frames: u64,
    /// Requests nobody answered: no such unit, a silent unit, a drive off.
    pub unanswered: u64,
    /// Requests the addressed drive did not understand: they followed the
    /// last frame sooner than it parts frames (its frame gap), so it heard
    /// one garbled frame. Counted in `unanswered` too.
    pub merged_frames: u64,
    /// Replies dropped by fault injection.
    pub dropped: u64,
    /// Replies sent with a corrupted CRC.
    pub corrupted: u64,
    /// Replies sent late.
    pub late: u64,
    /// Replies not sent because the simulator fell behind their time by
    /// more than its `max_lag` (the machine kept its thread from running):
    /// a drive answers on time, and a reply that late would cross the
    /// master's next request. The master sees a lost reply.
    pub stalled: u64,
    /// Bursts of noise written between frames.
    pub noise_bursts: u64,
    /// Exception replies.
    pub exceptions: u64,
    /// Requests answered by more than one drive at once (same address).
    pub collisions: u64,
    /// Masters that connected, for a simulator served on TCP.
    pub connections: u64,
}

impl fmt::Display for SimStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "requests={} replies={} broadcasts={} gap_violations={} bad_crc_requests={} \
             truncated_frames={} unanswered={} merged_frames={} dropped={} corrupted={} late={} \
             stalled={} noise_bursts={} exceptions={} collisions={} connections={}",
            self.requests,
            self.replies,
            self.broadcasts,
            self.gap_violations,
            self.bad_crc_requests,
            self.truncated_frames,
            self.unanswered,
            self.merged_frames,
            self.dropped,
            self.corrupted,
            self.late,
            self.stalled,
            self.noise_bursts,
            self.exceptions,
            self.collisions,
            self.connections
        )
    }
}

/// The silences the simulated wire saw before each request: from the end
/// of the previous activity (the last reply byte on the wire, or the
/// previous request when it had no reply) to the request's first byte.
/// t3.5 is the least a correct master leaves; what it leaves beyond is its
/// overhead. Buckets of 10 us up to 20 ms, then one overflow bucket.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GapHistogram {
    buckets: Vec<u64>,
}

impl Default for GapHistogram {
    fn default() -> Self {
        Self {
            buckets: vec![0; Self::BUCKETS + 1],
        }
    }
}

impl GapHistogram {
    /// Resolution.
    pub const STEP: Duration = Duration::from_micros(10);
    const BUCKETS: usize = 2000;

    /// Counts one silence.
    pub fn record(&mut self, gap: Duration) {
        let i = (gap.as_nanos() / Self::STEP.as_nanos()) as usize;
        self.buckets[i.min(Self::BUCKETS)] += 1;
    }

    /// Silences counted.
    pub fn count(&self) -> u64 {
        self.buckets.iter().sum()
    }

    /// What was counted since `earlier` (a copy taken before).
    pub fn since(&self, earlier: &GapHistogram) -> GapHistogram {
        GapHistogram {
            buckets: self
                .buckets
                .iter()
                .zip(&earlier.buckets)
                .map(|(a, b)| a.saturating_sub(*b))
                .collect(),
        }
    }

    /// The `p` quantile (0 to 1), to the upper edge of its bucket; `None`
    /// when nothing was counted, 20 ms and more reads as 20 ms.
    pub fn quantile(&self, p: f64) -> Option<Duration> {
        let total = self.count();
        if total == 0 {
            return None;
        }
        let rank = ((total as f64) * p.clamp(0.0, 1.0)).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (i, n) in self.buckets.iter().enumerate() {
            seen += n;
            if seen >= rank {
                return Some(Self::STEP * (i as u32 + 1).min(Self::BUCKETS as u32));
            }
        }
        Some(Self::STEP * Self::BUCKETS as u32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gap_quantiles_are_bucket_upper_edges() {
        let mut h = GapHistogram::default();
        assert_eq!(h.quantile(0.5), None);
        for us in [1750, 1755, 1760, 1800, 5000] {
            h.record(Duration::from_micros(us));
        }
        let earlier = h.clone();
        h.record(Duration::from_secs(1));
        assert_eq!(h.count(), 6);
        assert_eq!(h.quantile(0.5), Some(Duration::from_micros(1770)));
        assert_eq!(h.quantile(0.0), Some(Duration::from_micros(1760)));
        assert_eq!(h.quantile(1.0), Some(Duration::from_millis(20)));
        let late = h.since(&earlier);
        assert_eq!(late.count(), 1);
    }
}
