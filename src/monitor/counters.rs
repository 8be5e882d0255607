//! Wire counters per attempt, per unit.
//!
//! The bus's transaction counters say how each transaction ended after its
//! retries, so a retry that succeeds hides the fault before it: with 5 % of
//! replies corrupted, almost every transaction still ends "ok". These count
//! every attempt: each corrupted reply, each timeout, each reply that does
//! not answer, and the stray bytes, per unit, so a noisy cable shows.
//!
//! Plain atomics in a fixed table (256 units): the bus thread adds without
//! locking or allocating; scrapes read.

use std::sync::atomic::{AtomicU64, Ordering};

use crate::listed::listed_enum;

listed_enum! {
    /// What the counters count.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum WireEvent {
        /// A request put on the wire (each attempt, broadcasts included).
        Attempt,
        /// A reply with a wrong CRC.
        CrcError,
        /// No reply within the response timeout.
        Timeout,
        /// A reply that does not answer the request.
        BadReply,
        /// A valid exception reply.
        Exception,
    }
}

impl WireEvent {
    /// Whether it is an error kind, as exported in
    /// `drivegate_bus_wire_errors_total` (an exception is the drive's
    /// answer, not a fault of the wire).
    pub const fn is_error(self) -> bool {
        match self {
            WireEvent::CrcError | WireEvent::Timeout | WireEvent::BadReply => true,
            WireEvent::Attempt | WireEvent::Exception => false,
        }
    }

    /// Stable name for metric labels.
    pub fn name(self) -> &'static str {
        match self {
            WireEvent::Attempt => "attempt",
            WireEvent::CrcError => "crc_error",
            WireEvent::Timeout => "timeout",
            WireEvent::BadReply => "bad_reply",
            WireEvent::Exception => "exception",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

const EVENTS: usize = WireEvent::ALL.len();

#[derive(Default)]
struct UnitCounters {
    events: [AtomicU64; EVENTS],
    stray_bytes: AtomicU64,
}

/// The counters of one bus.
pub struct WireCounters {
    units: Box<[UnitCounters]>,
}

/// A copy of one unit's counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UnitSnapshot {
    /// Requests sent to it (every attempt).
    pub attempts: u64,
    /// Replies with a wrong CRC.
    pub crc_errors: u64,
    /// Attempts without a reply.
    pub timeouts: u64,
    /// Replies that did not answer the request.
    pub bad_replies: u64,
    /// Exception replies.
    pub exceptions: u64,
    /// Stray bytes that followed a transaction with this unit.
    pub stray_bytes: u64,
}

impl UnitSnapshot {
    /// The count of `event`.
    pub fn get(&self, event: WireEvent) -> u64 {
        match event {
            WireEvent::Attempt => self.attempts,
            WireEvent::CrcError => self.crc_errors,
            WireEvent::Timeout => self.timeouts,
            WireEvent::BadReply => self.bad_replies,
            WireEvent::Exception => self.exceptions,
        }
    }

    /// True when nothing was counted.
    pub fn is_zero(&self) -> bool {
        *self == UnitSnapshot::default()
    }
}

impl Default for WireCounters {
    fn default() -> Self {
        Self::new()
    }
}

impl WireCounters {
    /// All at zero.
    pub fn new() -> Self {
        Self {
            units: (0..256).map(|_| UnitCounters::default()).collect(),
        }
    }

    /// Counts `event` for `unit`.
    pub fn add(&self, unit: u8, event: WireEvent) {
        self.units[usize::from(unit)].events[event.index()].fetch_add(1, Ordering::Relaxed);
    }

    /// Counts `n` stray bytes after a transaction with `unit`.
    pub fn add_stray(&self, unit: u8, n: usize) {
        self.units[usize::from(unit)]
            .stray_bytes
            .fetch_add(n as u64, Ordering::Relaxed);
    }

    /// A copy of `unit`'s counters.
    pub fn unit(&self, unit: u8) -> UnitSnapshot {
        let u = &self.units[usize::from(unit)];
        let e = |event: WireEvent| u.events[event.index()].load(Ordering::Relaxed);
        UnitSnapshot {
            attempts: e(WireEvent::Attempt),
            crc_errors: e(WireEvent::CrcError),
            timeouts: e(WireEvent::Timeout),
            bad_replies: e(WireEvent::BadReply),
            exceptions: e(WireEvent::Exception),
            stray_bytes: u.stray_bytes.load(Ordering::Relaxed),
        }
    }

    /// The units in `always` (at zero if nothing happened) and every other
    /// unit with something counted (a scan, a passthrough to an unconfigured
    /// unit), in unit order.
    pub fn snapshot(&self, always: &[u8]) -> Vec<(u8, UnitSnapshot)> {
        (0..=255u8)
            .filter_map(|unit| {
                let s = self.unit(unit);
                (always.contains(&unit) || !s.is_zero()).then_some((unit, s))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_per_unit_and_lists_the_configured_ones_at_zero() {
        let c = WireCounters::new();
        c.add(1, WireEvent::Attempt);
        c.add(1, WireEvent::Attempt);
        c.add(1, WireEvent::CrcError);
        c.add(9, WireEvent::Timeout);
        c.add_stray(1, 3);
        let s = c.snapshot(&[1, 2]);
        assert_eq!(
            s.iter().map(|(u, _)| *u).collect::<Vec<_>>(),
            [1, 2, 9],
            "configured units always, others once seen"
        );
        assert_eq!(s[0].1.attempts, 2);
        assert_eq!(s[0].1.get(WireEvent::CrcError), 1);
        assert_eq!(s[0].1.stray_bytes, 3);
        assert!(s[1].1.is_zero());
        assert_eq!(s[2].1.timeouts, 1);
    }
}
