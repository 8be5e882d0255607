//! Counters of what the simulated wire saw and did.

use std::fmt;

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
    /// Replies dropped by fault injection.
    pub dropped: u64,
    /// Replies sent with a corrupted CRC.
    pub corrupted: u64,
    /// Replies sent late.
    pub late: u64,
    /// Bursts of noise written between frames.
    pub noise_bursts: u64,
    /// Exception replies.
    pub exceptions: u64,
    /// Requests answered by more than one drive at once (same address).
    pub collisions: u64,
}

impl fmt::Display for SimStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "requests={} replies={} broadcasts={} gap_violations={} bad_crc_requests={} \
             truncated_frames={} unanswered={} dropped={} corrupted={} late={} noise_bursts={} \
             exceptions={} collisions={}",
            self.requests,
            self.replies,
            self.broadcasts,
            self.gap_violations,
            self.bad_crc_requests,
            self.truncated_frames,
            self.unanswered,
            self.dropped,
            self.corrupted,
            self.late,
            self.noise_bursts,
            self.exceptions,
            self.collisions
        )
    }
}
