//! Which drive's status is due next.
//!
//! Each drive has a poll interval (0 = as often as the bus allows). The most
//! overdue drive goes first, which is round robin when all are due. A drive
//! that stopped answering is polled with exponential backoff instead, so it
//! costs little bus time and never holds up the others.

use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
struct Polled {
    unit: u8,
    interval: Duration,
    next_due: Instant,
    backoff: Option<Duration>,
}

/// The poll schedule of one bus.
#[derive(Debug, Clone)]
pub struct PollPlan {
    drives: Vec<Polled>,
    backoff_min: Duration,
    backoff_max: Duration,
}

impl PollPlan {
    /// A plan for `(unit, interval)` pairs; offline drives are retried after
    /// `backoff_min`, doubling up to `backoff_max`.
    pub fn new(
        drives: impl IntoIterator<Item = (u8, Duration)>,
        backoff_min: Duration,
        backoff_max: Duration,
    ) -> Self {
        let now = Instant::now();
        Self {
            drives: drives
                .into_iter()
                .map(|(unit, interval)| Polled {
                    unit,
                    interval,
                    next_due: now,
                    backoff: None,
                })
                .collect(),
            backoff_min,
            backoff_max: backoff_max.max(backoff_min),
        }
    }

    /// The most overdue drive, if any is due at `now`.
    pub fn due(&self, now: Instant) -> Option<u8> {
        self.drives
            .iter()
            .filter(|d| d.next_due <= now)
            .min_by_key(|d| d.next_due)
            .map(|d| d.unit)
    }

    /// True when `unit`'s poll is due at `now` (its interval, or an offline
    /// drive's backoff, is over); the scope asks this while it steers.
    pub fn is_due(&self, unit: u8, now: Instant) -> bool {
        self.drives
            .iter()
            .any(|d| d.unit == unit && d.next_due <= now)
    }

    /// When the next poll falls due, `None` with no drives.
    pub fn next_due(&self) -> Option<Instant> {
        self.drives.iter().map(|d| d.next_due).min()
    }

    /// Records a poll of `unit` finished at `now`; `offline` says whether the
    /// drive is (now) considered offline.
    pub fn polled(&mut self, unit: u8, now: Instant, offline: bool) {
        let (min, max) = (self.backoff_min, self.backoff_max);
        let Some(d) = self.drives.iter_mut().find(|d| d.unit == unit) else {
            return;
        };
        if offline {
            let backoff = d.backoff.map_or(min, |b| (b * 2).min(max));
            d.backoff = Some(backoff);
            d.next_due = now + backoff;
        } else {
            d.backoff = None;
            // Keep a steady rate; if we fell more than an interval behind,
            // start again from now rather than bursting to catch up.
            let next = d.next_due + d.interval;
            d.next_due = if next + d.interval < now { now } else { next };
        }
    }

    /// Makes `unit` due at once (e.g. after a command changed it, or when an
    /// offline drive should be tried again now).
    pub fn poll_soon(&mut self, unit: u8) {
        if let Some(d) = self.drives.iter_mut().find(|d| d.unit == unit) {
            d.next_due = Instant::now();
        }
    }

    /// Units in the plan.
    pub fn units(&self) -> impl Iterator<Item = u8> + '_ {
        self.drives.iter().map(|d| d.unit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_interval_is_round_robin() {
        let mut plan = PollPlan::new(
            [
                (1, Duration::ZERO),
                (2, Duration::ZERO),
                (3, Duration::ZERO),
            ],
            Duration::from_secs(1),
            Duration::from_secs(30),
        );
        let mut order = vec![];
        let mut now = Instant::now();
        for _ in 0..6 {
            let unit = plan.due(now).unwrap();
            order.push(unit);
            now += Duration::from_millis(6);
            plan.polled(unit, now, false);
        }
        assert_eq!(order, vec![1, 2, 3, 1, 2, 3]);
    }

    #[test]
    fn offline_drives_back_off_and_do_not_block_others() {
        let mut plan = PollPlan::new(
            [(1, Duration::ZERO), (2, Duration::ZERO)],
            Duration::from_secs(1),
            Duration::from_secs(4),
        );
        let start = Instant::now();
        let mut now = start;
        plan.polled(1, now, true);
        // Drive 2 keeps being polled while 1 waits out its backoff.
        for _ in 0..10 {
            assert_eq!(plan.due(now), Some(2));
            now += Duration::from_millis(6);
            plan.polled(2, now, false);
        }
        now = start + Duration::from_millis(1001);
        // Drive 2 was just polled: drive 1's backoff is over and it is next.
        plan.polled(2, now, false);
        assert_eq!(plan.due(now), Some(1));
        plan.polled(1, now, true);
        plan.polled(1, now, true); // 4 s
        plan.polled(1, now, true); // capped at 4 s
        assert_eq!(plan.drives[0].backoff, Some(Duration::from_secs(4)));
        // Answering again ends the backoff.
        plan.polled(1, now, false);
        assert_eq!(plan.drives[0].backoff, None);
    }

    #[test]
    fn intervals_are_kept() {
        let mut plan = PollPlan::new(
            [(1, Duration::from_millis(100))],
            Duration::from_secs(1),
            Duration::from_secs(1),
        );
        let t0 = Instant::now();
        assert_eq!(plan.due(t0), Some(1));
        plan.polled(1, t0 + Duration::from_millis(6), false);
        assert_eq!(plan.due(t0 + Duration::from_millis(50)), None);
        assert!(plan.next_due().unwrap() <= t0 + Duration::from_millis(101));
    }
}
