//! The learner's rules, step by step, with time passed in.

use super::*;

const US: Duration = Duration::from_micros(1);

fn limits() -> Limits {
    Limits::for_line(LineTiming::new_8n1(115_200), SERIAL_ADAPTER_LATENCY)
}

/// Answers every poll of a drive that understands any silence of at
/// least `needs`, as long as trials go on; the polls made.
fn learn(gap: &mut DriveGap, needs: Duration, now: Instant) -> usize {
    let l = limits();
    let mut polls = 0;
    while gap.wants_trial(now) && polls < 200 {
        let s = gap.silence(Use::Poll, &l, now);
        if s.gap >= needs {
            gap.answered(s.gap, s.trial, &l, now);
        } else {
            gap.failed(s.trial, &l, now);
        }
        polls += 1;
    }
    polls
}

/// A drive that parts frames after 0.35 ms, its gap learned at `t0`.
fn fast_drive() -> (Limits, Instant, DriveGap) {
    let l = limits();
    let t0 = Instant::now();
    let mut gap = DriveGap::new(&l);
    learn(&mut gap, 350 * US, t0);
    (l, t0, gap)
}

#[test]
fn limits_at_115200() {
    let l = limits();
    assert_eq!(l.spec, 1750 * US);
    // 3.5 characters (303.8 us) and the adapter's 50 us.
    assert_eq!(l.floor.as_micros(), 353);
    assert_eq!(l.shortest_trial.as_micros(), 130);
    // At 9600 baud 3.5 characters are the spec's t3.5 already.
    let slow = Limits::for_line(LineTiming::new_8n1(9600), SERIAL_ADAPTER_LATENCY);
    assert_eq!(slow.floor, slow.spec);
}

#[test]
fn starts_at_the_spec_and_tries_shorter_only_on_polls() {
    let l = limits();
    let now = Instant::now();
    let gap = DriveGap::new(&l);
    assert_eq!(gap.confirmed(), l.spec);
    let poll = gap.silence(Use::Poll, &l, now);
    assert!(poll.trial && poll.gap < l.spec, "{poll:?}");
    for use_ in [Use::Command, Use::Emergency] {
        assert_eq!(
            gap.silence(use_, &l, now),
            Silence {
                gap: l.spec,
                trial: false
            }
        );
    }
}

#[test]
fn a_fast_drive_is_learned_with_a_margin_of_twice_what_worked() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    // A drive that parts frames after 0.35 ms (as the master measures).
    let polls = learn(&mut gap, 350 * US, now);
    assert!(polls < 40, "{polls} polls");
    // Trials from half the spec down by 7/8: ... 449, 393 answered, 344
    // not; then halfway back: 368 and 356 answered, close enough to 344
    // to stop. Twice 356.
    assert_eq!(gap.confirmed().as_micros(), 711, "{gap:?}");
    assert!(!gap.wants_trial(now));
    // Commands get it; polls too, now that the steps have ended.
    for use_ in [Use::Command, Use::Poll, Use::Emergency] {
        assert_eq!(gap.silence(use_, &l, now).gap, gap.confirmed());
    }
}

#[test]
fn a_drive_faster_than_any_trial_gets_the_floor() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    learn(&mut gap, Duration::ZERO, now);
    assert_eq!(gap.confirmed(), l.floor);
    assert!(!gap.wants_trial(now));
}

#[test]
fn a_strict_drive_stays_on_the_spec_and_is_tried_again_with_backoff() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    // Half the spec, twice (once may be a reply lost to noise).
    assert_eq!(learn(&mut gap, l.spec, now), FAILS_PER_STEP as usize);
    assert_eq!(gap.confirmed(), l.spec);
    assert_eq!(gap.fallbacks(), 0, "a failed trial is no fallback");
    assert!(!gap.wants_trial(now + RELEARN.0 - US));
    assert!(gap.wants_trial(now + RELEARN.0));
    let later = now + RELEARN.0;
    gap.tick(&l, later);
    assert_eq!(learn(&mut gap, l.spec, later), FAILS_PER_STEP as usize);
    assert!(!gap.wants_trial(later + RELEARN.0 * 2 - US));
    assert!(gap.wants_trial(later + RELEARN.0 * 2));
}

#[test]
fn one_lost_reply_does_not_end_the_steps() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    let first = gap.silence(Use::Poll, &l, now);
    gap.failed(true, &l, now);
    assert_eq!(gap.silence(Use::Poll, &l, now), first, "the level again");
    learn(&mut gap, 350 * US, now);
    assert_eq!(gap.confirmed().as_micros(), 711);
}

#[test]
fn a_trial_counts_only_at_the_silence_tried() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    let s = gap.silence(Use::Poll, &l, now);
    // A command's answer proves nothing about a trial.
    for _ in 0..10 {
        gap.answered(s.gap, false, &l, now);
    }
    assert_eq!(gap.silence(Use::Poll, &l, now), s);
    // The thread ran late: 1 ms more silence than tried, no shorter
    // than the spec. It counts for nothing, and is tried again.
    for _ in 0..MISSES_PER_STEP * 2 {
        gap.answered(s.gap + 1000 * US, true, &l, now);
    }
    assert_eq!(gap.silence(Use::Poll, &l, now), s, "still the same trial");
    assert_eq!(gap.confirmed(), l.spec);
    // Once a gap was learned, misses end the steps there.
    while gap.confirmed() == l.spec {
        let s = gap.silence(Use::Poll, &l, now);
        gap.answered(s.gap, s.trial, &l, now);
    }
    let learned = gap.confirmed();
    assert!(learned < l.spec);
    for _ in 0..MISSES_PER_STEP {
        gap.answered(l.spec, true, &l, now);
    }
    assert!(!gap.wants_trial(now));
    assert_eq!(gap.silence(Use::Poll, &l, now).gap, learned);
}

#[test]
fn any_fault_at_the_learned_gap_puts_the_drive_back_on_the_spec_and_it_relearns_with_backoff() {
    let (l, t0, mut gap) = fast_drive();
    let learned = gap.confirmed();
    // The drive was replaced by a strict one: its first miss.
    gap.failed(false, &l, t0);
    assert_eq!(gap.confirmed(), l.spec);
    assert_eq!(gap.fallbacks(), 1);
    for use_ in [Use::Command, Use::Poll, Use::Emergency] {
        assert_eq!(gap.silence(use_, &l, t0).gap, l.spec);
    }
    // Nothing shorter is tried before the backoff...
    let mut now = t0 + RELEARN.0 - US;
    gap.tick(&l, now);
    assert!(!gap.wants_trial(now));
    assert_eq!(gap.silence(Use::Poll, &l, now).gap, l.spec);
    // ...then a trial, which the strict drive fails: the spec stays,
    // and the next wait is twice as long.
    now = t0 + RELEARN.0;
    assert!(gap.wants_trial(now));
    gap.tick(&l, now);
    assert_eq!(learn(&mut gap, l.spec, now), FAILS_PER_STEP as usize);
    assert_eq!(gap.confirmed(), l.spec);
    assert!(!gap.wants_trial(now + RELEARN.0 * 2 - US));
    assert!(gap.wants_trial(now + RELEARN.0 * 2));
    // A fault at the spec is no fallback (and waits longer still).
    gap.failed(false, &l, now);
    assert_eq!(gap.fallbacks(), 1, "only a learned gap falls back");
    // A drive that is fast again is learned again.
    let later = now + RELEARN.0 * 4;
    gap.tick(&l, later);
    learn(&mut gap, 350 * US, later);
    assert_eq!(gap.confirmed(), learned);
}

#[test]
fn a_drive_that_fell_back_is_tried_first_at_its_old_level() {
    let (l, t0, mut gap) = fast_drive();
    let learned = gap.confirmed();
    // A reply the machine made late: a fault like any other.
    gap.failed(false, &l, t0);
    let now = t0 + RELEARN.0;
    gap.tick(&l, now);
    assert_eq!(gap.silence(Use::Poll, &l, now).gap, learned / 2);
    assert_eq!(learn(&mut gap, 350 * US, now), ANSWERS_PER_STEP as usize);
    assert_eq!(gap.confirmed(), learned);
}

/// The drive keeps its learned gap for `n` commands.
fn hold(gap: &mut DriveGap, n: u32, now: Instant) {
    let l = limits();
    let confirmed = gap.confirmed();
    for _ in 0..n {
        gap.answered(confirmed, false, &l, now);
    }
}

#[test]
fn a_lone_miss_after_a_long_hold_is_checked_again_on_a_poll_a_moment_later() {
    let (l, t0, mut gap) = fast_drive();
    let learned = gap.confirmed();
    hold(&mut gap, RECHECK_AFTER, t0);
    gap.failed(false, &l, t0);
    assert_eq!(gap.fallbacks(), 1);
    // The retry, and everything until the recheck, after the spec.
    let soon = t0 + RECHECK - US;
    assert!(!gap.wants_trial(soon));
    for use_ in [Use::Command, Use::Poll, Use::Emergency] {
        assert_eq!(gap.silence(use_, &l, t0).gap, l.spec);
        assert_eq!(gap.silence(use_, &l, soon).gap, l.spec);
    }
    // Then one poll after the gap that held; commands keep the spec.
    let now = t0 + RECHECK;
    assert!(gap.wants_trial(now));
    let poll = gap.silence(Use::Poll, &l, now);
    assert_eq!(
        poll,
        Silence {
            gap: learned,
            trial: true
        }
    );
    assert_eq!(gap.silence(Use::Command, &l, now).gap, l.spec);
    // A command's answer proves nothing; nor does a poll that the
    // machine sent after a longer silence.
    gap.answered(l.spec, false, &l, now);
    gap.answered(learned + 2 * TOLERANCE, true, &l, now);
    assert_eq!(gap.confirmed(), l.spec);
    // Answered after the gap itself: it holds again.
    gap.answered(poll.gap, poll.trial, &l, now);
    assert_eq!(gap.confirmed(), learned);
    assert!(!gap.wants_trial(now));
    assert_eq!(gap.silence(Use::Command, &l, now).gap, learned);
    // A second miss before the drive held the gap long again waits
    // the backoff.
    gap.failed(false, &l, now);
    assert!(!gap.wants_trial(now + RELEARN.0 - US));
    assert!(gap.wants_trial(now + RELEARN.0));
}

#[test]
fn a_recheck_the_drive_does_not_answer_waits_the_backoff() {
    let (l, t0, mut gap) = fast_drive();
    hold(&mut gap, RECHECK_AFTER, t0);
    // The drive was replaced by a strict one.
    gap.failed(false, &l, t0);
    let now = t0 + RECHECK;
    let poll = gap.silence(Use::Poll, &l, now);
    assert!(poll.trial);
    gap.failed(poll.trial, &l, now);
    assert_eq!(gap.confirmed(), l.spec);
    assert_eq!(gap.fallbacks(), 1, "the recheck is no second fallback");
    assert_eq!(gap.silence(Use::Poll, &l, now).gap, l.spec);
    assert!(!gap.wants_trial(now + RELEARN.0 - US));
    assert!(gap.wants_trial(now + RELEARN.0));
}

#[test]
fn a_late_answer_to_the_request_that_fell_back_restores_the_gap() {
    let (l, t0, mut gap) = fast_drive();
    let learned = gap.confirmed();
    gap.failed(false, &l, t0);
    assert_eq!(gap.confirmed(), l.spec);
    gap.answered_late(t0);
    assert_eq!(gap.confirmed(), learned);
    assert_eq!(gap.silence(Use::Emergency, &l, t0).gap, learned);
    assert!(!gap.wants_trial(t0 + RELEARN.0));
    // Only the very next outcome may say so.
    gap.failed(false, &l, t0);
    gap.answered(l.spec, false, &l, t0);
    gap.answered_late(t0);
    assert_eq!(gap.confirmed(), l.spec);
}

#[test]
fn a_level_counts_at_the_longest_silence_measured_before_its_answers() {
    let l = limits();
    let now = Instant::now();
    let mut gap = DriveGap::new(&l);
    // Half the spec (875 us), answered after 875, 975 and 925 us (the
    // thread ran late twice): the level is 975 us.
    for extra in [0, 100, 50] {
        let s = gap.silence(Use::Poll, &l, now);
        gap.answered(s.gap + extra * US, s.trial, &l, now);
    }
    assert_eq!(gap.confirmed(), l.spec, "twice 975 us is above the spec");
    // The steps go on from the level tried.
    assert_eq!(gap.silence(Use::Poll, &l, now).gap, 875 * US * 7 / 8);
    // The next level answered after 800 us each time (it tried 766):
    // the gap is twice that.
    for _ in 0..ANSWERS_PER_STEP {
        let s = gap.silence(Use::Poll, &l, now);
        gap.answered(800 * US, s.trial, &l, now);
    }
    assert_eq!(gap.confirmed(), 1600 * US);
}

#[test]
fn the_backoff_is_bounded() {
    let l = limits();
    let mut now = Instant::now();
    let mut gap = DriveGap::new(&l);
    for _ in 0..20 {
        gap.failed(false, &l, now);
        now += RELEARN.1 * 2;
        gap.tick(&l, now);
    }
    gap.failed(false, &l, now);
    assert!(!gap.wants_trial(now + RELEARN.1 - US));
    assert!(gap.wants_trial(now + RELEARN.1));
}

#[test]
fn an_emergency_uses_the_gap_only_when_it_was_answered_lately() {
    let (l, t0, mut gap) = fast_drive();
    let learned = gap.confirmed();
    assert_eq!(gap.silence(Use::Emergency, &l, t0 + RECENT).gap, learned);
    let stale = t0 + RECENT + US;
    assert_eq!(gap.silence(Use::Emergency, &l, stale).gap, l.spec);
    // A command answered at the gap vouches for it again.
    gap.answered(learned, false, &l, stale);
    assert_eq!(gap.silence(Use::Emergency, &l, stale).gap, learned);
}
