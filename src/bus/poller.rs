//! Which drive's status is due next. Pure: time is passed in.
//!
//! Each drive has a poll interval (0 = as often as the bus allows). The most
//! overdue drive goes first, which is round robin when all are due.
//!
//! Polls at an interval are spread evenly over it: of `n` drives polled
//! every `T`, the `i`-th is due at `i * T / n` past each multiple of `T`, and
//! keeps that phase for good (a late poll does not move the next one, a
//! missed period is skipped, not caught up). Background polling then never
//! comes in a burst that a client's request would queue behind: at 1 Hz
//! with 8 drives, one poll every 125 ms instead of eight back to back once
//! a second. Every drive is polled once at start, so its state is known at
//! once.
//!
//! A drive that stopped answering is polled with exponential backoff
//! instead, so it costs little bus time and never holds up the others; once
//! it answers again it goes back to its phase.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
struct Polled {
    unit: u8,
    interval: Duration,
    /// A moment the drive's polls fall due at, `interval` apart either side.
    phase_origin: Instant,
    next_due: Instant,
    backoff: Option<Duration>,
}

impl Polled {
    /// The first moment on this drive's phase strictly after `now`.
    fn next_in_phase(&self, now: Instant) -> Instant {
        if self.interval.is_zero() {
            return now;
        }
        if now < self.phase_origin {
            return self.phase_origin;
        }
        let periods = (now - self.phase_origin).as_nanos() / self.interval.as_nanos() + 1;
        // Saturates only for intervals and uptimes no bus has.
        let periods = u32::try_from(periods).unwrap_or(u32::MAX);
        self.phase_origin + self.interval.saturating_mul(periods)
    }
}

/// The poll schedule of one bus.
#[derive(Debug, Clone)]
pub struct PollPlan {
    drives: Vec<Polled>,
    backoff_min: Duration,
    backoff_max: Duration,
}

impl PollPlan {
    /// A plan for `(unit, interval)` pairs starting at `now`: every drive is
    /// due at once, then at its phase. Offline drives are retried after
    /// `backoff_min`, doubling up to `backoff_max`.
    pub fn new(
        drives: impl IntoIterator<Item = (u8, Duration)>,
        backoff_min: Duration,
        backoff_max: Duration,
        now: Instant,
    ) -> Self {
        let drives: Vec<(u8, Duration)> = drives.into_iter().collect();
        // Drives sharing an interval share it out between them, in the
        // order they are configured.
        let mut sharing: BTreeMap<Duration, u32> = BTreeMap::new();
        for (_, interval) in &drives {
            *sharing.entry(*interval).or_default() += 1;
        }
        let mut placed: BTreeMap<Duration, u32> = BTreeMap::new();
        let drives = drives
            .into_iter()
            .map(|(unit, interval)| {
                let index = placed.entry(interval).or_default();
                let share = sharing.get(&interval).copied().unwrap_or(1).max(1);
                let phase = interval * *index / share;
                *index += 1;
                Polled {
                    unit,
                    interval,
                    phase_origin: now + phase,
                    next_due: now,
                    backoff: None,
                }
            })
            .collect();
        Self {
            drives,
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

    /// When `unit`'s next poll falls (or fell) due.
    pub fn due_at(&self, unit: u8) -> Option<Instant> {
        self.drives
            .iter()
            .find(|d| d.unit == unit)
            .map(|d| d.next_due)
    }

    /// True when `unit`'s poll is due at `now` (its interval, or an offline
    /// drive's backoff, is over); the scope asks this while it steers.
    pub fn is_due(&self, unit: u8, now: Instant) -> bool {
        self.due_at(unit).is_some_and(|due| due <= now)
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
            d.next_due = d.next_in_phase(now);
        }
    }

    /// Makes `unit` due at `now` (e.g. after a command changed it); its
    /// polls after that keep their phase.
    pub fn poll_soon(&mut self, unit: u8, now: Instant) {
        if let Some(d) = self.drives.iter_mut().find(|d| d.unit == unit) {
            d.next_due = d.next_due.min(now);
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

    const MS: Duration = Duration::from_millis(1);
    const SECOND: Duration = Duration::from_secs(1);

    fn plan(drives: &[(u8, Duration)], t0: Instant) -> PollPlan {
        PollPlan::new(drives.iter().copied(), SECOND, 30 * SECOND, t0)
    }

    /// Runs the plan from `t0` to `until`, each poll taking `poll` on the
    /// wire, every drive answering; returns (unit, start) of each poll.
    fn run(plan: &mut PollPlan, t0: Instant, until: Instant, poll: Duration) -> Vec<(u8, Instant)> {
        let mut now = t0;
        let mut polls = vec![];
        while now < until {
            match plan.due(now) {
                Some(unit) => {
                    polls.push((unit, now));
                    now += poll;
                    plan.polled(unit, now, false);
                }
                None => now = plan.next_due().unwrap().max(now + Duration::from_micros(1)),
            }
        }
        polls
    }

    #[test]
    fn zero_interval_is_round_robin() {
        let t0 = Instant::now();
        let mut plan = plan(
            &[
                (1, Duration::ZERO),
                (2, Duration::ZERO),
                (3, Duration::ZERO),
            ],
            t0,
        );
        let polls = run(&mut plan, t0, t0 + 35 * MS, 6 * MS);
        let order: Vec<u8> = polls.iter().map(|p| p.0).collect();
        assert_eq!(order, vec![1, 2, 3, 1, 2, 3]);
    }

    #[test]
    fn polls_at_an_interval_are_spread_evenly_over_it() {
        let t0 = Instant::now();
        let drives: Vec<(u8, Duration)> = (1..=8).map(|u| (u, SECOND)).collect();
        let mut plan = plan(&drives, t0);
        let polls = run(&mut plan, t0, t0 + 10 * SECOND, 6 * MS);
        // At start every drive is polled once, back to back, so its state
        // is known at once...
        let first: Vec<u8> = polls[..8].iter().map(|p| p.0).collect();
        assert_eq!(first, (1..=8).collect::<Vec<u8>>());
        // ...then unit i is due at (i - 1) * 125 ms past each second, so
        // the polls come one at a time, 125 ms apart.
        let later: Vec<&(u8, Instant)> = polls.iter().filter(|p| p.1 >= t0 + SECOND).collect();
        assert_eq!(later.len(), 72, "9 s at 8 polls/s");
        for pair in later.windows(2) {
            assert_eq!(pair[1].1 - pair[0].1, 125 * MS, "{polls:?}");
        }
        for (unit, at) in later {
            let phase = (*at - t0).as_nanos() % SECOND.as_nanos();
            assert_eq!(phase, u128::from(unit - 1) * 125 * MS.as_nanos());
        }
    }

    #[test]
    fn a_late_poll_keeps_the_phase_and_missed_periods_are_skipped() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, 100 * MS), (2, 100 * MS)], t0);
        plan.polled(1, t0 + MS, false);
        plan.polled(2, t0 + 2 * MS, false);
        // Unit 2's phase is 50 ms.
        assert_eq!(plan.due_at(2), Some(t0 + 50 * MS));
        // Its poll ran 30 ms late: the next is still on the phase.
        plan.polled(2, t0 + 80 * MS, false);
        assert_eq!(plan.due_at(2), Some(t0 + 150 * MS));
        // Held up for 3.5 periods (a long outage of the port): the periods
        // missed are skipped, not caught up in a burst.
        plan.polled(2, t0 + 505 * MS, false);
        assert_eq!(plan.due_at(2), Some(t0 + 550 * MS));
        // A poll asked for now, off the phase, does not move the phase.
        plan.polled(1, t0 + 519 * MS, false);
        plan.poll_soon(2, t0 + 520 * MS);
        assert_eq!(plan.due(t0 + 520 * MS), Some(2));
        plan.polled(2, t0 + 526 * MS, false);
        assert_eq!(plan.due_at(2), Some(t0 + 550 * MS));
    }

    #[test]
    fn drives_with_other_intervals_spread_among_their_own() {
        let t0 = Instant::now();
        let mut plan = plan(
            &[(1, 100 * MS), (2, SECOND), (3, 100 * MS), (4, SECOND)],
            t0,
        );
        for unit in 1..=4 {
            plan.polled(unit, t0 + MS, false);
        }
        assert_eq!(plan.due_at(1), Some(t0 + 100 * MS));
        assert_eq!(plan.due_at(3), Some(t0 + 50 * MS));
        assert_eq!(plan.due_at(2), Some(t0 + SECOND));
        assert_eq!(plan.due_at(4), Some(t0 + 500 * MS));
    }

    #[test]
    fn offline_drives_back_off_and_do_not_block_others() {
        let start = Instant::now();
        let mut plan = PollPlan::new(
            [(1, Duration::ZERO), (2, Duration::ZERO)],
            SECOND,
            4 * SECOND,
            start,
        );
        let mut now = start;
        plan.polled(1, now, true);
        // Drive 2 keeps being polled while 1 waits out its backoff.
        for _ in 0..10 {
            assert_eq!(plan.due(now), Some(2));
            now += 6 * MS;
            plan.polled(2, now, false);
        }
        now = start + 1001 * MS;
        // Drive 2 was just polled: drive 1's backoff is over and it is next.
        plan.polled(2, now, false);
        assert_eq!(plan.due(now), Some(1));
        plan.polled(1, now, true);
        plan.polled(1, now, true); // 4 s
        plan.polled(1, now, true); // capped at 4 s
        assert_eq!(plan.drives[0].backoff, Some(4 * SECOND));
        // Answering again ends the backoff.
        plan.polled(1, now, false);
        assert_eq!(plan.drives[0].backoff, None);
    }

    #[test]
    fn a_drive_back_from_offline_returns_to_its_phase() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, SECOND), (2, SECOND)], t0);
        plan.polled(1, t0 + MS, false);
        plan.polled(2, t0 + 2 * MS, true);
        assert_eq!(plan.due_at(2), Some(t0 + 2 * MS + SECOND), "backoff");
        // It answers at 1.002 s: its next poll is at its phase, 1.5 s.
        plan.polled(2, t0 + SECOND + 8 * MS, false);
        assert_eq!(plan.due_at(2), Some(t0 + 1500 * MS));
    }

    #[test]
    fn intervals_are_kept() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, 100 * MS)], t0);
        assert_eq!(plan.due(t0), Some(1));
        plan.polled(1, t0 + 6 * MS, false);
        assert_eq!(plan.due(t0 + 50 * MS), None);
        assert_eq!(plan.next_due(), Some(t0 + 100 * MS));
        assert_eq!(plan.units().collect::<Vec<_>>(), vec![1]);
    }
}
