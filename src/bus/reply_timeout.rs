//! The reply timeout learned per drive, as TCP learns its retransmission
//! timeout (RFC 6298). Pure: every turnaround is passed in.
//!
//! A drive's turnaround is measured from the end of the request on the wire
//! to the first byte of its reply. From each good reply the estimator keeps
//! a smoothed turnaround (`srtt`, gain 1/8) and its mean deviation
//! (`rttvar`, gain 1/4), and waits `srtt + 4 x rttvar + margin` for the next
//! reply's first byte, never less than the floor and never more than the
//! ceiling (`response_timeout_ms`). Before a drive has answered, the ceiling
//! is used (a probe of a silent drive uses the floor: it is not expected to
//! answer).
//!
//! A timeout doubles the wait of the next attempts (Karn's back-off) until
//! a reply that answers a single attempt gives a new sample: a drive that
//! slowed down is waited for longer at once, and learned again from its
//! first clean reply. A reply that arrives after the learned timeout (but
//! before the ceiling) is a sample too: it can only raise the estimate.

use std::time::Duration;

/// Longest back-off: the ceiling is reached long before 2^6 times the
/// learned timeout on any sane bus.
const MAX_BACKOFF: u32 = 6;

/// The limits of a learned timeout on one line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bounds {
    /// Never wait less: a drive waits t3.5 before it answers, so no reply
    /// comes sooner, and a busy host (or an adapter's packets) delivers the
    /// first byte later than the drive sent it (`reply_timeout_floor_ms`).
    pub floor: Duration,
    /// Never wait more, and wait this long before a drive has answered
    /// (`response_timeout_ms`).
    pub ceiling: Duration,
    /// Added to the estimate for the adapter's and the system's latency
    /// that the drive's own variation does not show.
    pub margin: Duration,
}

/// The least floor above t3.5: a reply cannot start sooner than t3.5 after
/// the request, and its first byte needs a moment to reach us.
const FLOOR_ABOVE_T35: Duration = Duration::from_millis(1);

/// The margin for the adapter's and the host's latency on a serial port:
/// a busy host runs the kernel's tty worker and our thread a millisecond
/// late now and then.
pub const SERIAL_MARGIN: Duration = Duration::from_millis(1);

impl Bounds {
    /// Bounds for a line whose t3.5 is `t3_5`, with `ceiling` the configured
    /// response timeout and `floor` the configured least wait: the floor is
    /// at least t3.5 + 1 ms and at most the ceiling; the margin
    /// [`SERIAL_MARGIN`].
    pub fn for_line(t3_5: Duration, ceiling: Duration, floor: Duration) -> Self {
        Self {
            floor: floor.max(t3_5 + FLOOR_ABOVE_T35).min(ceiling),
            ceiling,
            margin: SERIAL_MARGIN,
        }
    }
}

/// The learned reply timeout of one drive.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplyTimeout {
    /// Smoothed turnaround; `None` until the drive has answered.
    srtt: Option<Duration>,
    /// Mean deviation of the turnaround.
    rttvar: Duration,
    /// Timeouts since the last sample: each doubles the wait.
    backoff: u32,
}

impl ReplyTimeout {
    /// The wait for a reply's first byte: the ceiling until the drive has
    /// answered, then the learned timeout (doubled per timeout since the last
    /// sample), within the bounds.
    pub fn timeout(&self, bounds: &Bounds) -> Duration {
        match self.srtt {
            None => bounds.ceiling,
            Some(_) => self.backed_off(self.learned_base(bounds), bounds),
        }
    }

    /// The wait for a probe of a drive not known to answer: the learned
    /// timeout, or the floor for a drive never heard, doubled per silent
    /// probe (or timeout) since the last sample, up to the ceiling. A drive
    /// that is off costs little per probe at first; a slow drive that comes
    /// (back) on is heard within a few probes and learned from there.
    pub fn probe_timeout(&self, bounds: &Bounds) -> Duration {
        let base = match self.srtt {
            None => bounds.floor,
            Some(_) => self.learned_base(bounds),
        };
        self.backed_off(base, bounds)
    }

    /// The smoothed turnaround, once the drive has answered.
    pub fn smoothed(&self) -> Option<Duration> {
        self.srtt
    }

    /// A reply answered a single attempt, `turnaround` after the request's
    /// end: it updates the estimate and ends any back-off.
    pub fn sample(&mut self, turnaround: Duration) {
        match self.srtt {
            None => {
                self.srtt = Some(turnaround);
                self.rttvar = turnaround / 2;
            }
            Some(srtt) => {
                let deviation = srtt.abs_diff(turnaround);
                self.rttvar = self.rttvar * 3 / 4 + deviation / 4;
                self.srtt = Some(srtt * 7 / 8 + turnaround / 8);
            }
        }
        self.backoff = 0;
    }

    /// A reply came after the timeout, `turnaround` after its request's
    /// end (at least: it may answer an earlier attempt of the same
    /// request): a drive that slowed down. It is learned as a sample, which
    /// raises the estimate.
    pub fn late(&mut self, turnaround: Duration) {
        self.sample(turnaround);
    }

    /// An attempt got no reply in time: the next ones wait twice as long,
    /// up to the ceiling, until the next sample.
    pub fn timed_out(&mut self) {
        self.backoff = (self.backoff + 1).min(MAX_BACKOFF);
    }

    fn learned_base(&self, bounds: &Bounds) -> Duration {
        let srtt = self.srtt.unwrap_or(bounds.ceiling);
        (srtt + self.rttvar * 4 + bounds.margin)
            .clamp(bounds.floor, bounds.ceiling.max(bounds.floor))
    }

    fn backed_off(&self, base: Duration, bounds: &Bounds) -> Duration {
        base.saturating_mul(1 << self.backoff)
            .min(bounds.ceiling.max(bounds.floor))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);
    const US: Duration = Duration::from_micros(1);

    /// 115200 baud: t3.5 is 1.75 ms; a 50 ms response timeout.
    fn bounds() -> Bounds {
        Bounds::for_line(1750 * US, 50 * MS, 3 * MS)
    }

    fn learned(turnarounds: impl IntoIterator<Item = Duration>) -> ReplyTimeout {
        let mut t = ReplyTimeout::default();
        for r in turnarounds {
            t.sample(r);
        }
        t
    }

    #[test]
    fn the_ceiling_until_the_drive_has_answered_and_the_floor_for_its_probes() {
        let t = ReplyTimeout::default();
        assert_eq!(t.timeout(&bounds()), 50 * MS);
        assert_eq!(t.probe_timeout(&bounds()), 3 * MS);
    }

    #[test]
    fn a_silent_drives_probes_wait_longer_each_time_so_a_slow_drive_is_found() {
        let mut t = ReplyTimeout::default();
        let waits: Vec<_> = (0..6)
            .map(|_| {
                let wait = t.probe_timeout(&bounds());
                t.timed_out();
                wait
            })
            .collect();
        assert_eq!(waits, [3 * MS, 6 * MS, 12 * MS, 24 * MS, 48 * MS, 50 * MS]);
        // An 8 ms drive (9.75 ms after t3.5) is heard by the third probe and
        // learned: its timeout is then its own, not the ceiling.
        t.sample(9750 * US);
        assert!(t.timeout(&bounds()) < 50 * MS);
    }

    #[test]
    fn learns_a_fast_drive_down_towards_its_turnaround() {
        // 2.25 ms (t3.5 + 0.5 ms) with a few microseconds of jitter.
        let t = learned((0..40).map(|i| 2250 * US + (i % 3) * 20 * US));
        let timeout = t.timeout(&bounds());
        // Far below the ceiling, just above the turnaround and margin.
        assert!(timeout < 3600 * US, "{timeout:?}");
        assert!(timeout >= 2250 * US + SERIAL_MARGIN, "{timeout:?}");
        // The first sample alone leaves room for the unknown variation.
        let first = learned([2250 * US]).timeout(&bounds());
        assert_eq!(first, 2250 * US + 4 * 1125 * US + SERIAL_MARGIN);
    }

    #[test]
    fn a_slow_drive_is_waited_for() {
        let t = learned((0..40).map(|_| 8 * MS + 1750 * US));
        let timeout = t.timeout(&bounds());
        assert!(
            (9750 * US + SERIAL_MARGIN..11500 * US).contains(&timeout),
            "{timeout:?}"
        );
    }

    #[test]
    fn the_floor_holds_for_a_drive_faster_than_possible() {
        let t = learned((0..40).map(|_| 100 * US));
        assert_eq!(t.timeout(&bounds()), bounds().floor);
    }

    #[test]
    fn the_configured_floor_holds_and_never_falls_below_t3_5() {
        let busy_host = Bounds::for_line(1750 * US, 50 * MS, 10 * MS);
        let t = learned((0..40).map(|_| 2250 * US));
        assert_eq!(t.timeout(&busy_host), 10 * MS);
        // Configured below what a reply needs: t3.5 + 1 ms.
        let too_low = Bounds::for_line(1750 * US, 50 * MS, Duration::ZERO);
        assert_eq!(too_low.floor, 2750 * US);
        // Never above the ceiling.
        assert_eq!(Bounds::for_line(1750 * US, 50 * MS, 80 * MS).floor, 50 * MS);
    }

    #[test]
    fn the_ceiling_holds_for_a_drive_slower_than_it() {
        let t = learned((0..40).map(|_| 70 * MS));
        assert_eq!(t.timeout(&bounds()), 50 * MS);
        assert_eq!(t.probe_timeout(&bounds()), 50 * MS);
    }

    #[test]
    fn a_timeout_doubles_the_wait_until_the_next_sample() {
        let mut t = learned((0..40).map(|_| 2250 * US));
        let base = t.timeout(&bounds());
        t.timed_out();
        assert_eq!(t.timeout(&bounds()), base * 2);
        t.timed_out();
        assert_eq!(t.timeout(&bounds()), base * 4);
        for _ in 0..10 {
            t.timed_out();
        }
        assert_eq!(t.timeout(&bounds()), 50 * MS, "never past the ceiling");
        assert_eq!(t.probe_timeout(&bounds()), 50 * MS);
        t.sample(2250 * US);
        assert!(t.timeout(&bounds()) <= base, "{:?}", t.timeout(&bounds()));
    }

    #[test]
    fn a_sudden_slowdown_is_followed_within_a_few_replies() {
        // 0.5 ms, then 20 ms (plus t3.5 each time).
        let mut t = learned((0..40).map(|_| 2250 * US));
        let slow = 21750 * US;
        assert!(t.timeout(&bounds()) < slow);
        // The first slow reply misses the learned timeout: the attempt times
        // out, the retries wait twice as long each time.
        t.timed_out();
        t.timed_out();
        t.timed_out();
        assert!(t.timeout(&bounds()) > slow, "{:?}", t.timeout(&bounds()));
        // It comes (late, or on a backed-off attempt) and is learned: from
        // then on every reply of the slowed drive is waited for.
        t.late(slow);
        assert!(t.timeout(&bounds()) > slow, "{:?}", t.timeout(&bounds()));
        for _ in 0..40 {
            t.sample(slow);
            assert!(t.timeout(&bounds()) > slow, "{:?}", t.timeout(&bounds()));
        }
        // Settled close above the new turnaround.
        assert!(
            t.timeout(&bounds()) < slow + 2 * MS,
            "{:?}",
            t.timeout(&bounds())
        );
    }

    #[test]
    fn a_late_reply_raises_the_estimate() {
        let mut t = learned((0..40).map(|_| 2250 * US));
        let before = t.timeout(&bounds());
        t.late(before + 3 * MS);
        let after = t.timeout(&bounds());
        assert!(after > before + 3 * MS, "{before:?} -> {after:?}");
        assert!(t.smoothed() > Some(2250 * US));
    }

    #[test]
    fn a_drive_that_speeds_up_again_is_learned_down() {
        let mut t = learned((0..40).map(|_| 21750 * US));
        for _ in 0..60 {
            t.sample(2250 * US);
        }
        assert!(t.timeout(&bounds()) < 4 * MS, "{:?}", t.timeout(&bounds()));
    }
}
