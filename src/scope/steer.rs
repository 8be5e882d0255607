//! Which drive's status to read next while a capture runs: the captured
//! drives get every poll, in turn, except that each other drive keeps a
//! floor rate (`[scope] floor_rate_hz`), so a capture never leaves a
//! drive's status stale for longer than the floor's period. Commands and
//! emergencies are not polls: the scheduler serves them first as always.
//!
//! Pure, with time passed in; the poll plan's own view (a drive's
//! configured interval, an offline drive's backoff) is asked through
//! closures, so an offline drive is never polled faster than its backoff.

use std::time::{Duration, Instant};

pub use crate::bus::observers::Steer;

/// How long to wait when every drive is waiting out a backoff.
const IDLE: Duration = Duration::from_millis(5);

/// The polling of one bus while a capture runs.
#[derive(Debug, Clone)]
pub struct PollSteer {
    captured: Vec<u8>,
    turn: usize,
    /// The other drives and when each is due next (`None`: at once).
    others: Vec<(u8, Option<Instant>)>,
    floor: Duration,
}

impl PollSteer {
    /// Steers `captured` drives to full rate, keeping the rest of `units`
    /// at one poll per `floor` at least.
    pub fn new(captured: &[u8], units: &[u8], floor: Duration) -> Self {
        Self {
            captured: captured.to_vec(),
            turn: 0,
            others: units
                .iter()
                .filter(|u| !captured.contains(u))
                .map(|&u| (u, None))
                .collect(),
            floor,
        }
    }

    /// True when `unit` is captured.
    pub fn is_captured(&self, unit: u8) -> bool {
        self.captured.contains(&unit)
    }

    /// The next poll at `now`. `plan_due(unit)` is the poll plan's view
    /// (its interval, its backoff for an offline drive); `offline(unit)`
    /// whether the drive stopped answering.
    pub fn next(
        &mut self,
        now: Instant,
        plan_due: impl Fn(u8) -> bool,
        offline: impl Fn(u8) -> bool,
    ) -> Steer {
        // The others first, when their floor period is over: the most
        // overdue of them.
        if let Some(&(unit, _)) = self
            .others
            .iter()
            .filter(|(u, due)| due.is_none_or(|t| now >= t) && plan_due(*u))
            .min_by_key(|(_, due)| *due)
        {
            return Steer::Poll(unit);
        }
        // Then the captured drives in turn; an offline one only when its
        // backoff allows, so a silent drive does not eat the bus.
        for i in 0..self.captured.len() {
            let index = (self.turn + i) % self.captured.len();
            let unit = self.captured[index];
            if !offline(unit) || plan_due(unit) {
                self.turn = index + 1;
                return Steer::Poll(unit);
            }
        }
        let next_floor = self
            .others
            .iter()
            .filter_map(|(_, due)| *due)
            .min()
            .unwrap_or(now + IDLE);
        Steer::Wait(next_floor.clamp(now, now + IDLE))
    }

    /// `unit` was polled at `now`: a drive not captured is due again one
    /// floor period after it was due (a steady rate, as the poll plan
    /// keeps), or at once if it fell further behind.
    pub fn polled(&mut self, unit: u8, now: Instant) {
        let floor = self.floor;
        if let Some(other) = self.others.iter_mut().find(|(u, _)| *u == unit) {
            let next = other.1.map_or(now, |due| due) + floor;
            // Fell more than a period behind: due at once, not in a burst.
            other.1 = Some(next.max(now));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const POLL: Duration = Duration::from_micros(5844);

    fn run(steer: &mut PollSteer, polls: usize, offline: &[u8]) -> Vec<u8> {
        let mut now = Instant::now();
        let mut order = vec![];
        for _ in 0..polls {
            match steer.next(now, |_| true, |u| offline.contains(&u)) {
                Steer::Poll(u) => {
                    order.push(u);
                    now += POLL;
                    steer.polled(u, now);
                }
                Steer::Wait(t) => now = t.max(now + Duration::from_micros(100)),
            }
        }
        order
    }

    #[test]
    fn captured_drives_get_the_polls_and_the_others_their_floor() {
        // 1 s of polls: drive 1 captured, drives 2-4 at 10 Hz.
        let mut steer = PollSteer::new(&[1], &[1, 2, 3, 4], Duration::from_millis(100));
        let order = run(&mut steer, 171, &[]);
        let count = |u| order.iter().filter(|&&x| x == u).count();
        for other in [2, 3, 4] {
            assert!(
                (10..=11).contains(&count(other)),
                "{other}: {}",
                count(other)
            );
        }
        assert!(count(1) >= 171 - 33, "{}", count(1));
    }

    #[test]
    fn several_captured_drives_take_turns() {
        let mut steer = PollSteer::new(&[2, 3], &[1, 2, 3], Duration::from_secs(10));
        let order = run(&mut steer, 7, &[]);
        assert_eq!(order, [1, 2, 3, 2, 3, 2, 3]);
        assert!(steer.is_captured(3) && !steer.is_captured(1));
    }

    #[test]
    fn an_offline_drive_keeps_its_backoff() {
        let mut steer = PollSteer::new(&[1, 2], &[1, 2], Duration::from_millis(100));
        let now = Instant::now();
        // Drive 2 is offline and its backoff is not over: only drive 1.
        for _ in 0..5 {
            assert_eq!(steer.next(now, |u| u != 2, |u| u == 2), Steer::Poll(1));
        }
        // Both offline, neither due: wait a little, never spin.
        match steer.next(now, |_| false, |_| true) {
            Steer::Wait(t) => assert!(t > now && t <= now + IDLE),
            other => panic!("{other:?}"),
        }
    }
}
