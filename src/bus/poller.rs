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
//! A poll is skipped when a client has just read the same status: a status
//! read on request that falls at most half an interval before the poll is
//! due (or while it is due) counts as that poll, and the next one falls a
//! period on, at the same phase. While clients read a drive's status at
//! least every half interval its polls cost the bus nothing, and a status
//! is never older than one and a half intervals (one interval when no
//! client reads it), plus the time the poll waits for the bus.
//!
//! A drive that stopped answering, or has not answered since start, is
//! probed with exponential backoff instead, each probe at the first moment
//! on its phase after the backoff, so it costs little bus time, never comes
//! beside another drive's poll and never holds up the others. A drive that
//! comes back is noticed by the first probe after it did: within the
//! longest backoff plus one interval, or at once if a client's request
//! reaches it. Once it answers it goes back to its phase.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// The share of a drive's interval before its poll is due in which a
/// client's read of its status counts as the poll.
const FRESH_ENOUGH_DIVISOR: u32 = 2;

#[derive(Debug, Clone)]
struct Drive {
    unit: u8,
    interval: Duration,
    /// A moment the drive's polls fall due at, `interval` apart either side.
    phase_origin: Instant,
    next_due: Instant,
    backoff: Option<Duration>,
    /// When its last failed probe ended, while it is backed off.
    probed_at: Option<Instant>,
    /// It has answered since start: a drive never heard is backed off from
    /// its first failed probe, one that answered only once it is offline.
    heard: bool,
}

impl Drive {
    /// The first moment on this drive's phase strictly after `now`.
    fn next_in_phase(&self, now: Instant) -> Instant {
        self.phase_from(now, true)
    }

    /// The first moment on this drive's phase at or after `at`.
    fn in_phase_from(&self, at: Instant) -> Instant {
        self.phase_from(at, false)
    }

    /// The first phase point after `t` (`strictly`) or at or after it; `t`
    /// itself for a drive polled as often as possible.
    fn phase_from(&self, t: Instant, strictly: bool) -> Instant {
        if self.interval.is_zero() {
            return t;
        }
        if t < self.phase_origin {
            return self.phase_origin;
        }
        let since = (t - self.phase_origin).as_nanos();
        let period = self.interval.as_nanos();
        let periods = if strictly {
            since / period + 1
        } else {
            since.div_ceil(period)
        };
        // Saturates only for intervals and uptimes no bus has.
        let periods = u32::try_from(periods).unwrap_or(u32::MAX);
        self.phase_origin + self.interval.saturating_mul(periods)
    }
}

/// How a poll ended, for [`PollPlan::polled`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PollResult {
    /// The drive sent its status.
    Answered,
    /// It did not; `offline` says whether it is (now) reported offline.
    Failed {
        /// Reported offline (after its failures in a row).
        offline: bool,
    },
}

/// The poll schedule of one bus.
#[derive(Debug, Clone)]
pub struct PollPlan {
    drives: Vec<Drive>,
    backoff_min: Duration,
    backoff_max: Duration,
}

impl PollPlan {
    /// A plan for `(unit, interval)` pairs starting at `now`: every drive is
    /// due at once, then at its phase. Drives that do not answer are
    /// probed after `backoff_min`, doubling up to `backoff_max`.
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
                Drive {
                    unit,
                    interval,
                    phase_origin: now + phase,
                    next_due: now,
                    backoff: None,
                    probed_at: None,
                    heard: false,
                }
            })
            .collect();
        Self {
            drives,
            backoff_min,
            backoff_max: backoff_max.max(backoff_min),
        }
    }

    fn drive(&mut self, unit: u8) -> Option<&mut Drive> {
        self.drives.iter_mut().find(|d| d.unit == unit)
    }

    /// The most overdue drive, if any is due at `now`.
    pub fn due(&self, now: Instant) -> Option<u8> {
        self.drives
            .iter()
            .filter(|d| d.next_due <= now)
            .min_by_key(|d| d.next_due)
            .map(|d| d.unit)
    }

    /// The most overdue drive among those `may_go`, if any is due at `now`.
    pub fn due_among(&self, now: Instant, may_go: impl Fn(u8) -> bool) -> Option<u8> {
        self.drives
            .iter()
            .filter(|d| d.next_due <= now && may_go(d.unit))
            .min_by_key(|d| d.next_due)
            .map(|d| d.unit)
    }

    /// True when `unit`'s probe may wait for the clients: it is probed with
    /// backoff, the backoff has not reached the longest, and its last probe
    /// was less than the longest backoff ago. A silent drive then costs the
    /// waiting clients one probe per longest backoff at most, and is probed
    /// on its phase whenever the bus has time.
    pub fn probe_may_wait(&self, unit: u8, now: Instant) -> bool {
        let max = self.backoff_max;
        self.drives.iter().any(|d| {
            d.unit == unit
                && d.backoff.is_some_and(|b| b < max)
                && d.probed_at.is_some_and(|t| now < t + max)
        })
    }

    /// When the first probe that waits for the clients at `now` stops
    /// waiting (its last probe is the longest backoff ago), if one waits.
    pub fn waiting_probe_goes_at(&self, now: Instant) -> Option<Instant> {
        self.drives
            .iter()
            .filter(|d| d.next_due <= now && self.probe_may_wait(d.unit, now))
            .filter_map(|d| d.probed_at.map(|t| t + self.backoff_max))
            .min()
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

    /// True while `unit` is probed with backoff (offline, or never heard
    /// and failed).
    pub fn backing_off(&self, unit: u8) -> bool {
        self.drives
            .iter()
            .any(|d| d.unit == unit && d.backoff.is_some())
    }

    /// When the next poll falls due, `None` with no drives.
    pub fn next_due(&self) -> Option<Instant> {
        self.drives.iter().map(|d| d.next_due).min()
    }

    /// When the next poll falls due after `now`, `None` if none does.
    pub fn next_due_after(&self, now: Instant) -> Option<Instant> {
        self.drives
            .iter()
            .map(|d| d.next_due)
            .filter(|&due| due > now)
            .min()
    }

    /// Records a poll of `unit` finished at `now`.
    pub fn polled(&mut self, unit: u8, now: Instant, result: PollResult) {
        let (min, max) = (self.backoff_min, self.backoff_max);
        let Some(d) = self.drive(unit) else {
            return;
        };
        match result {
            PollResult::Answered => {
                d.heard = true;
                d.backoff = None;
                d.probed_at = None;
                d.next_due = d.next_in_phase(now);
            }
            // Offline, or never heard: a drive that is off (or absent)
            // would cost a timeout at every period.
            PollResult::Failed { offline } if offline || !d.heard => {
                let backoff = d.backoff.map_or(min, |b| (b * 2).min(max));
                d.backoff = Some(backoff);
                d.probed_at = Some(now);
                // From when the probe fell due, so a backoff of whole
                // periods keeps the phase exactly; but never sooner than
                // the backoff from now (a probe longer than the backoff).
                let from = d.next_due.min(now) + backoff;
                d.next_due = d.in_phase_from(if from > now { from } else { now + backoff });
            }
            // A drive that answered before keeps its period until it is
            // reported offline: one missed reply is not an outage.
            PollResult::Failed { .. } => d.next_due = d.next_in_phase(now),
        }
    }

    /// Records a good status of `unit` that a client's request read at
    /// `now`. If the drive's poll is due, or due within half an interval,
    /// this read counts as it: the poll is skipped and the next falls a
    /// period on, at the drive's phase. A drive being probed with backoff
    /// is back: its polls return to its phase.
    pub fn refreshed(&mut self, unit: u8, now: Instant) {
        let Some(d) = self.drive(unit) else {
            return;
        };
        d.heard = true;
        d.probed_at = None;
        if d.backoff.take().is_some() {
            d.next_due = d.next_in_phase(now);
        } else if d.interval.is_zero() {
            // As often as possible: it goes behind the drives not read.
            d.next_due = d.next_due.max(now);
        } else if d.next_due <= now + d.interval / FRESH_ENOUGH_DIVISOR {
            d.next_due = d.next_in_phase(d.next_due.max(now));
        }
    }

    /// Records that `unit` answered a client's request at `now` (anything
    /// but its status: that is [`refreshed`](Self::refreshed)). A drive
    /// being probed with backoff is back: it is polled at once for its
    /// status, then on its phase. A drive that answers says nothing about
    /// its status, so its polls stay as they are.
    pub fn answered(&mut self, unit: u8, now: Instant) {
        let Some(d) = self.drive(unit) else {
            return;
        };
        d.heard = true;
        d.probed_at = None;
        if d.backoff.take().is_some() {
            d.next_due = d.next_due.min(now);
        }
    }

    /// Makes `unit` due at `now` (e.g. after a command changed it); its
    /// polls after that keep their phase.
    pub fn poll_soon(&mut self, unit: u8, now: Instant) {
        if let Some(d) = self.drive(unit) {
            d.next_due = d.next_due.min(now);
        }
    }

    /// The plan for new `(unit, interval)` pairs and backoffs, from `now`
    /// (a reload, applied in place): a drive kept at its interval keeps its
    /// phase, its next poll and its backoff; one whose interval changed
    /// takes its place among the drives of its new interval, due no later
    /// than it was (a faster rate applies at once), backed off as it was;
    /// one added is due at once, as at start; one removed is dropped.
    pub fn retune(
        &mut self,
        drives: impl IntoIterator<Item = (u8, Duration)>,
        backoff_min: Duration,
        backoff_max: Duration,
        now: Instant,
    ) {
        let mut new = PollPlan::new(drives, backoff_min, backoff_max, now);
        for d in &mut new.drives {
            let Some(old) = self.drives.iter().find(|o| o.unit == d.unit) else {
                continue;
            };
            if old.interval == d.interval {
                *d = old.clone();
            } else {
                d.next_due = old.next_due.min(d.in_phase_from(now));
                d.backoff = old
                    .backoff
                    .map(|b| b.clamp(new.backoff_min, new.backoff_max));
                d.probed_at = old.probed_at;
                d.heard = old.heard;
            }
        }
        *self = new;
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
    const OFFLINE: PollResult = PollResult::Failed { offline: true };

    fn plan(drives: &[(u8, Duration)], t0: Instant) -> PollPlan {
        PollPlan::new(drives.iter().copied(), SECOND, 30 * SECOND, t0)
    }

    #[test]
    fn a_silent_drives_probe_waits_for_clients_until_the_longest_backoff() {
        let t0 = Instant::now();
        let mut p = plan(&[(1, SECOND), (2, SECOND)], t0);
        // Unit 2 is never heard: backed off from its first failed probe.
        p.polled(2, t0 + 10 * MS, PollResult::Failed { offline: false });
        assert!(p.backing_off(2));
        // Its next probe falls due a second later, but may wait for the
        // clients until 30 s (the longest backoff) after the last probe...
        let due = p.due_at(2).unwrap();
        assert!(p.probe_may_wait(2, due));
        assert!(p.probe_may_wait(2, t0 + 10 * MS + 30 * SECOND - MS));
        assert!(!p.probe_may_wait(2, t0 + 10 * MS + 30 * SECOND));
        assert_eq!(
            p.waiting_probe_goes_at(due),
            Some(t0 + 10 * MS + 30 * SECOND)
        );
        // ...and a drive that answers is never held back.
        assert!(!p.probe_may_wait(1, due));
        // The other drives' polls are found past the waiting probe.
        assert_eq!(p.due_among(due + SECOND, |u| u != 2), Some(1));
        // Once its backoff has reached the longest, it waits no more.
        let mut now = due;
        for _ in 0..6 {
            p.polled(2, now, PollResult::Failed { offline: true });
            now = p.due_at(2).unwrap();
        }
        assert!(!p.probe_may_wait(2, now));
        // A drive that answers again is polled on its phase, not held.
        p.polled(2, now, PollResult::Answered);
        assert!(!p.probe_may_wait(2, now));
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
                    plan.polled(unit, now, PollResult::Answered);
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
        plan.polled(1, t0 + MS, PollResult::Answered);
        plan.polled(2, t0 + 2 * MS, PollResult::Answered);
        // Unit 2's phase is 50 ms.
        assert_eq!(plan.due_at(2), Some(t0 + 50 * MS));
        // Its poll ran 30 ms late: the next is still on the phase.
        plan.polled(2, t0 + 80 * MS, PollResult::Answered);
        assert_eq!(plan.due_at(2), Some(t0 + 150 * MS));
        // Held up for 3.5 periods (a long outage of the port): the periods
        // missed are skipped, not caught up in a burst.
        plan.polled(2, t0 + 505 * MS, PollResult::Answered);
        assert_eq!(plan.due_at(2), Some(t0 + 550 * MS));
        // A poll asked for now, off the phase, does not move the phase.
        plan.polled(1, t0 + 519 * MS, PollResult::Answered);
        plan.poll_soon(2, t0 + 520 * MS);
        assert_eq!(plan.due(t0 + 520 * MS), Some(2));
        plan.polled(2, t0 + 526 * MS, PollResult::Answered);
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
            plan.polled(unit, t0 + MS, PollResult::Answered);
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
        plan.polled(1, now, OFFLINE);
        // Drive 2 keeps being polled while 1 waits out its backoff.
        for _ in 0..10 {
            assert_eq!(plan.due(now), Some(2));
            now += 6 * MS;
            plan.polled(2, now, PollResult::Answered);
        }
        now = start + 1001 * MS;
        // Drive 2 was just polled: drive 1's backoff is over and it is next.
        plan.polled(2, now, PollResult::Answered);
        assert_eq!(plan.due(now), Some(1));
        plan.polled(1, now, OFFLINE);
        plan.polled(1, now, OFFLINE); // 4 s
        plan.polled(1, now, OFFLINE); // capped at 4 s
        assert_eq!(plan.drives[0].backoff, Some(4 * SECOND));
        // Answering again ends the backoff.
        plan.polled(1, now, PollResult::Answered);
        assert_eq!(plan.drives[0].backoff, None);
    }

    #[test]
    fn a_drive_back_from_offline_returns_to_its_phase() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, SECOND), (2, SECOND)], t0);
        plan.polled(1, t0 + MS, PollResult::Answered);
        plan.polled(2, t0 + 2 * MS, OFFLINE);
        // Backoff: its first phase point a second on.
        assert_eq!(plan.due_at(2), Some(t0 + 1500 * MS), "backoff");
        // It answers at 1.508 s: its next poll is at its phase, 2.5 s.
        plan.polled(2, t0 + 1508 * MS, PollResult::Answered);
        assert_eq!(plan.due_at(2), Some(t0 + 2500 * MS));
    }

    #[test]
    fn intervals_are_kept() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, 100 * MS)], t0);
        assert_eq!(plan.due(t0), Some(1));
        plan.polled(1, t0 + 6 * MS, PollResult::Answered);
        assert_eq!(plan.due(t0 + 50 * MS), None);
        assert_eq!(plan.next_due(), Some(t0 + 100 * MS));
        assert_eq!(plan.units().collect::<Vec<_>>(), vec![1]);
    }

    /// Runs 8 drives at 1 Hz for `secs` with a client reading the status of
    /// unit `(k % 8) + 1` every `every` (each read taking `poll` on the
    /// wire, like a poll); returns the polls made after start and the
    /// oldest status seen, over all drives.
    fn clients_reading(every: Duration, secs: u32) -> (Vec<(u8, Instant)>, Duration) {
        let t0 = Instant::now();
        let poll = 6 * MS;
        let drives: Vec<(u8, Duration)> = (1..=8).map(|u| (u, SECOND)).collect();
        let mut plan = plan(&drives, t0);
        let mut fresh = [t0; 9];
        let mut oldest = Duration::ZERO;
        let mut polls = vec![];
        let mut next_read = t0;
        let mut k = 0u32;
        let mut now = t0;
        while now < t0 + secs * SECOND {
            // The client's read goes first when both are ready, as a
            // command goes before a poll.
            if now >= next_read {
                let unit = (k % 8) as u8 + 1;
                k += 1;
                now += poll;
                oldest = oldest.max(now - fresh[usize::from(unit)]);
                fresh[usize::from(unit)] = now;
                plan.refreshed(unit, now);
                next_read += every;
            } else if let Some(unit) = plan.due(now) {
                polls.push((unit, now));
                now += poll;
                oldest = oldest.max(now - fresh[usize::from(unit)]);
                fresh[usize::from(unit)] = now;
                plan.polled(unit, now, PollResult::Answered);
            } else {
                now = next_read.min(plan.next_due().unwrap());
            }
        }
        let after_start = polls.into_iter().filter(|p| p.1 > t0 + 100 * MS).collect();
        (after_start, oldest)
    }

    #[test]
    fn a_status_a_client_reads_counts_as_the_poll() {
        // Each drive read every 400 ms, less than half its interval: after
        // the polls at start, the clients' reads make every poll.
        let (polls, oldest) = clients_reading(50 * MS, 20);
        assert_eq!(polls, vec![], "no poll was needed");
        assert!(oldest <= 400 * MS + 6 * MS, "{oldest:?}");
    }

    #[test]
    fn reads_too_rare_to_keep_a_status_fresh_leave_the_polls_on_their_phase() {
        // Each drive read every 1.6 s: some reads fall within half a second
        // of a poll and skip it, the others do not; the polls made are all
        // on their drive's phase, never two within 125 ms of each other,
        // and no status is older than 1.5 s.
        let (polls, oldest) = clients_reading(200 * MS, 30);
        assert!(!polls.is_empty());
        assert!(polls.len() < 8 * 30 - 30, "{} polls", polls.len());
        for pair in polls.windows(2) {
            assert!(pair[1].1 - pair[0].1 >= 125 * MS - 6 * MS, "{pair:?}");
        }
        assert!(oldest <= 1500 * MS + 12 * MS, "{oldest:?}");
    }

    #[test]
    fn a_read_long_before_the_poll_does_not_count() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, SECOND), (2, SECOND)], t0);
        plan.polled(1, t0 + MS, PollResult::Answered);
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
        // 600 ms before the poll: the poll stays.
        plan.refreshed(1, t0 + 400 * MS);
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
        // 500 ms before: it counts, the next is a period on.
        plan.refreshed(1, t0 + 500 * MS);
        assert_eq!(plan.due_at(1), Some(t0 + 2 * SECOND));
        // A read while the poll is overdue (waiting behind commands) is
        // that poll: the next is on the phase after it.
        plan.polled(2, t0 + 2 * MS, PollResult::Answered);
        assert_eq!(plan.due(t0 + 1510 * MS), Some(2));
        plan.refreshed(2, t0 + 1510 * MS);
        assert_eq!(plan.due(t0 + 1510 * MS), None);
        assert_eq!(plan.due_at(2), Some(t0 + 2500 * MS));
    }

    #[test]
    fn reads_of_a_drive_polled_as_often_as_possible_put_it_behind_the_others() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, Duration::ZERO), (2, Duration::ZERO)], t0);
        plan.polled(1, t0 + 6 * MS, PollResult::Answered);
        plan.polled(2, t0 + 12 * MS, PollResult::Answered);
        assert_eq!(plan.due(t0 + 12 * MS), Some(1));
        plan.refreshed(1, t0 + 18 * MS);
        assert_eq!(plan.due(t0 + 18 * MS), Some(2));
    }

    #[test]
    fn a_drive_never_heard_is_backed_off_from_its_first_probe_on_its_phase() {
        let t0 = Instant::now();
        let drives: Vec<(u8, Duration)> = (1..=9).map(|u| (u, SECOND)).collect();
        let mut plan = plan(&drives, t0);
        // Unit 9's phase is 8/9 s. It never answers: backoff 1, 2, 4, 8 s,
        // each probe at the first phase point after it.
        let failed = PollResult::Failed { offline: false };
        let mut probes = vec![];
        let mut now = t0 + 60 * MS;
        for _ in 0..5 {
            probes.push(now);
            plan.polled(9, now + 54 * MS, failed);
            now = plan.due_at(9).unwrap();
        }
        let phase = SECOND * 8 / 9;
        let at: Vec<Duration> = probes.iter().map(|p| *p - t0).collect();
        assert_eq!(
            at,
            [
                60 * MS,
                SECOND + phase,
                3 * SECOND + phase,
                7 * SECOND + phase,
                15 * SECOND + phase
            ]
        );
        // Three probes in the first ten seconds, instead of three at the
        // interval and then the backoff.
        assert!(plan.backing_off(9));
    }

    #[test]
    fn a_drive_that_answered_keeps_its_period_until_it_is_offline() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, SECOND)], t0);
        plan.polled(1, t0 + 6 * MS, PollResult::Answered);
        plan.polled(
            1,
            t0 + SECOND + 6 * MS,
            PollResult::Failed { offline: false },
        );
        assert_eq!(plan.due_at(1), Some(t0 + 2 * SECOND));
        assert!(!plan.backing_off(1));
        // Reported offline: probed a backoff after the poll fell due.
        plan.polled(1, t0 + 2 * SECOND + 60 * MS, OFFLINE);
        assert_eq!(plan.due_at(1), Some(t0 + 3 * SECOND));
        assert!(plan.backing_off(1));
    }

    #[test]
    fn a_drive_in_backoff_that_answers_a_client_is_back() {
        let t0 = Instant::now();
        let mut plan = PollPlan::new([(1, SECOND), (2, SECOND)], SECOND, 30 * SECOND, t0);
        let mut now = t0;
        for _ in 0..6 {
            plan.polled(2, now, OFFLINE);
            now = plan.due_at(2).unwrap();
        }
        // Its backoff is 30 s by now.
        let later = now - 20 * SECOND;
        assert!(plan.due_at(2).unwrap() - later > 15 * SECOND);
        // A client's write is echoed: it is polled at once for its status.
        plan.answered(2, later);
        assert_eq!(plan.due_at(2), Some(later));
        assert!(!plan.backing_off(2));
        // A client's status read brings another back onto its phase.
        plan.polled(1, t0, OFFLINE);
        plan.refreshed(1, t0 + 10 * MS);
        assert!(!plan.backing_off(1));
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
        // Answering anything else leaves the polls of a drive that
        // answers as they were.
        plan.answered(1, t0 + 20 * MS);
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
    }

    #[test]
    fn a_probe_longer_than_the_backoff_is_not_followed_by_another_at_once() {
        let t0 = Instant::now();
        let mut plan = PollPlan::new([(1, 200 * MS)], 200 * MS, 400 * MS, t0);
        // A 300 ms timeout: the probe due at t0 ends at 300 ms.
        plan.polled(1, t0 + 300 * MS, OFFLINE);
        assert_eq!(plan.due_at(1), Some(t0 + 600 * MS));
        plan.polled(1, t0 + 900 * MS, OFFLINE);
        assert_eq!(plan.due_at(1), Some(t0 + 1000 * MS));
    }

    #[test]
    fn a_retune_keeps_the_phase_of_what_stayed_and_polls_the_new_at_once() {
        let t0 = Instant::now();
        let mut plan = plan(&[(1, SECOND), (2, SECOND), (3, Duration::ZERO)], t0);
        plan.polled(1, t0 + 10 * MS, PollResult::Answered);
        plan.polled(2, t0 + 20 * MS, PollResult::Answered);
        plan.polled(3, t0 + 30 * MS, OFFLINE);
        assert_eq!(plan.due_at(2), Some(t0 + 500 * MS));
        let backed_off = plan.due_at(3);
        // Unit 2 faster, unit 3 kept, unit 4 added, the backoff longer.
        let now = t0 + 100 * MS;
        plan.retune(
            [(1, SECOND), (2, 200 * MS), (3, Duration::ZERO), (4, SECOND)],
            SECOND,
            60 * SECOND,
            now,
        );
        // Unit 1 keeps its next poll, unit 3 its backoff.
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
        assert_eq!(plan.due_at(3), backed_off);
        assert!(plan.backing_off(3));
        // Unit 2's faster rate applies at once; unit 4 is due now.
        assert_eq!(plan.due_at(2), Some(now));
        assert_eq!(plan.due_at(4), Some(now));
        plan.polled(2, now + MS, PollResult::Answered);
        assert_eq!(plan.due_at(2), Some(now + 200 * MS));
        // Removed: no longer polled.
        plan.retune([(1, SECOND)], SECOND, 60 * SECOND, now);
        assert_eq!(plan.units().collect::<Vec<_>>(), vec![1]);
        assert_eq!(plan.due_at(1), Some(t0 + SECOND));
    }
}
