//! How fast stored messages are replayed beside live ones: a pure rule,
//! time passed in.
//!
//! After an outage the store may hold minutes of data while the drives
//! keep producing new data. Replaying it all at once would queue the live
//! messages behind it (a host would see the present late, which is worse
//! than seeing the past late), so the replay is a token bucket of
//! `per_second` messages (at most `burst` at once) that also stands aside
//! whenever live messages are waiting to be sent.

use std::time::{Duration, Instant};

const NANO: u128 = 1_000_000_000;

/// The pace of a replay.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pacing {
    /// Stored messages sent per second at most.
    pub per_second: u32,
    /// Stored messages sent at once at most (the bucket's size).
    pub burst: u32,
    /// Live messages waiting above this many: no replay this round.
    pub live_backlog: usize,
}

impl Default for Pacing {
    /// 1000 messages a second in bursts of 50: a fleet daemon's live data
    /// (a DDATA per poll, some hundreds a second) keeps its pace, and a
    /// minute's outage is replayed in well under a minute.
    fn default() -> Self {
        Pacing {
            per_second: 1000,
            burst: 50,
            live_backlog: 8,
        }
    }
}

/// The replay's bucket.
#[derive(Debug, Clone)]
pub struct Pacer {
    pacing: Pacing,
    /// Tokens in billionths, so that refills add up exactly.
    credit: u128,
    last: Option<Instant>,
}

impl Pacer {
    /// A bucket that starts full.
    pub fn new(pacing: Pacing) -> Self {
        Pacer {
            pacing,
            credit: u128::from(pacing.burst) * NANO,
            last: None,
        }
    }

    /// How many stored messages may go now, with `live_waiting` live
    /// messages not yet sent. Call [`Pacer::spent`] with what was sent.
    pub fn allowance(&mut self, now: Instant, live_waiting: usize) -> usize {
        if let Some(last) = self.last {
            // A clock read out of order counts as no time passed.
            let dt = now.saturating_duration_since(last).as_nanos();
            self.credit = (self.credit + dt * u128::from(self.pacing.per_second))
                .min(u128::from(self.pacing.burst) * NANO);
        }
        self.last = Some(now);
        if live_waiting > self.pacing.live_backlog {
            return 0;
        }
        usize::try_from(self.credit / NANO).unwrap_or(usize::MAX)
    }

    /// `n` stored messages were sent.
    pub fn spent(&mut self, n: usize) {
        self.credit = self.credit.saturating_sub(n as u128 * NANO);
    }

    /// How long until one more message may go (zero: now), for the
    /// caller's timer.
    pub fn wait(&self) -> Duration {
        if self.credit >= NANO || self.pacing.per_second == 0 {
            return Duration::ZERO;
        }
        let nanos = (NANO - self.credit).div_ceil(u128::from(self.pacing.per_second));
        Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pacer() -> Pacer {
        Pacer::new(Pacing {
            per_second: 100,
            burst: 10,
            live_backlog: 2,
        })
    }

    #[test]
    fn a_full_bucket_allows_a_burst_then_nothing() {
        let t0 = Instant::now();
        let mut p = pacer();
        assert_eq!(p.allowance(t0, 0), 10);
        p.spent(10);
        assert_eq!(p.allowance(t0, 0), 0);
        assert_eq!(p.wait(), Duration::from_millis(10));
    }

    #[test]
    fn the_bucket_refills_at_the_rate_up_to_the_burst() {
        let t0 = Instant::now();
        let mut p = pacer();
        p.allowance(t0, 0);
        p.spent(10);
        assert_eq!(p.allowance(t0 + Duration::from_millis(50), 0), 5);
        p.spent(5);
        // A long pause fills it to the burst, not beyond.
        assert_eq!(p.allowance(t0 + Duration::from_secs(60), 0), 10);
    }

    #[test]
    fn over_a_second_the_replay_sends_its_rate() {
        let t0 = Instant::now();
        let mut p = pacer();
        let mut sent = 0;
        for ms in 0..=1000 {
            let n = p.allowance(t0 + Duration::from_millis(ms), 0);
            p.spent(n);
            sent += n;
        }
        // The first burst plus a second's refill.
        assert_eq!(sent, 110);
    }

    #[test]
    fn live_messages_waiting_stop_the_replay_without_losing_its_tokens() {
        let t0 = Instant::now();
        let mut p = pacer();
        assert_eq!(p.allowance(t0, 3), 0);
        assert_eq!(p.allowance(t0, 2), 10);
    }

    #[test]
    fn a_clock_read_out_of_order_gives_nothing_extra() {
        let t0 = Instant::now() + Duration::from_secs(1);
        let mut p = pacer();
        p.allowance(t0, 0);
        p.spent(10);
        assert_eq!(p.allowance(t0 - Duration::from_millis(500), 0), 0);
    }
}
