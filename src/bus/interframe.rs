//! The silence before a request, per drive (`[bus] interframe`). Pure: the
//! time and every outcome are passed in.
//!
//! The Modbus specification asks for t3.5 of silence between frames (1.75
//! ms above 19200 baud), but many drives part frames after 3.5 character
//! times (0.3 ms at 115200 baud). With [`Interframe::Auto`] the master
//! learns, per drive, the shortest silence before a request that the drive
//! still understands, and keeps a margin above it:
//!
//! - every drive starts at the spec; shorter silences are tried only on
//!   status polls (and polls made in idle time for the purpose), never on a
//!   client's command or an emergency: a trial that fails costs a retried
//!   poll, nobody's command;
//! - the trials start at half the spec (a longer one could not shorten the
//!   gap) and step down (by [`STEP`]) while each level is answered
//!   [`ANSWERS_PER_STEP`] times; the gap every other request gets is then
//!   twice the shortest level answered, never below the floor (3.5
//!   character times and the adapter's latency) nor above the spec. After
//!   a trial that is not answered, the next tries halfway back, until the
//!   levels answered and not are within 1/16 of each other;
//! - any fault of a request sent after the confirmed gap (a timeout, a CRC
//!   error, a reply that does not answer) puts the drive back on the spec
//!   at once (its retry goes after the spec's silence) and it learns again
//!   only after a backoff that doubles each time ([`RELEARN`]), trying the
//!   level it had answered first. A lone miss after [`RECHECK_AFTER`]
//!   answers at the confirmed gap is checked once sooner: a poll
//!   [`RECHECK`] later goes after that gap again, and if it is answered
//!   the gap holds again (one reply lost to noise, or a host that ran late,
//!   does not make a drive strict); if not, the backoff as above;
//! - a timeout is no fault of the gap when the reply comes after all: if
//!   the retry's reply begins sooner than any drive could answer the retry
//!   (3.5 character times after it), it is the late answer to the request
//!   that fell back, and what the drive had learned holds again (the host
//!   or the adapter ran late, the drive understood the gap);
//! - an emergency uses the drive's gap only if a request sent after it was
//!   answered within [`RECENT`]; otherwise, and for broadcasts, the spec.
//!
//! The silences counted are the master's: from the last byte it received
//! to the first it sends. The wire's silence is longer by the adapter's and
//! the system's latency, never shorter. A level counts at the longest
//! silence measured before its answers (the thread may run late), and a
//! trial counts only if that was shorter than any answered before.

use std::time::{Duration, Instant};

use crate::modbus::timing::LineTiming;

/// The silence before requests a bus is set to keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interframe {
    /// The specification's t3.5 before every request.
    #[default]
    Spec,
    /// Each drive's own, learned (see the module).
    Auto,
    /// This silence before every request: the plant's promise that every
    /// drive on the bus parts frames after it.
    Fixed(Duration),
}

impl Interframe {
    /// The shortest silence a status poll may get before its request on
    /// `line`: the spec's t3.5, the plant's fixed gap, or the shortest
    /// trial of `auto` (1.5 character times).
    pub fn shortest(&self, line: LineTiming) -> Duration {
        match self {
            Interframe::Spec => line.t3_5(),
            Interframe::Fixed(gap) => *gap,
            Interframe::Auto => line.char_time() * 3 / 2,
        }
    }

    /// The setting as the configuration and the API write it: `spec`,
    /// `auto`, or microseconds.
    pub fn describe(&self) -> String {
        match self {
            Interframe::Spec => "spec".into(),
            Interframe::Auto => "auto".into(),
            Interframe::Fixed(d) => d.as_micros().to_string(),
        }
    }
}

/// Each trial is this much shorter than the last (7/8): the shortest
/// silence answered is at most 8/7 of the least the drive needs.
pub const STEP: (u32, u32) = (7, 8);
/// Answers a trial level needs before the next, shorter one is tried.
pub const ANSWERS_PER_STEP: u8 = 3;
/// How long an answered request vouches for the drive's gap for an
/// emergency.
pub const RECENT: Duration = Duration::from_secs(5);
/// First and longest wait before a drive that fell back to the spec is
/// tried shorter again.
pub const RELEARN: (Duration, Duration) = (Duration::from_secs(10), Duration::from_secs(600));
/// An answered request vouches for the confirmed gap when the silence
/// before it was at most this much longer (the thread may have run late).
pub const TOLERANCE: Duration = Duration::from_micros(50);
/// Trials of one level not answered before the level counts as too short
/// (one may be a reply lost to noise).
pub const FAILS_PER_STEP: u8 = 2;
/// Trials of one level that could not be kept that short (the master's
/// own overhead is longer, or the machine kept it from running) before the
/// steps end there.
pub const MISSES_PER_STEP: u8 = 30;
/// Answers at the confirmed gap after which a lone miss is checked again
/// ([`RECHECK`] later, on a poll) rather than waited out: a drive that kept
/// a gap this long did not turn strict for one lost reply.
pub const RECHECK_AFTER: u32 = 20;
/// How long after such a miss its poll tries the gap again: never the
/// retry of the same transaction.
pub const RECHECK: Duration = Duration::from_secs(1);
/// The latency a serial adapter adds to the wire's timing, kept in the
/// floor: a request can reach the wire sooner after the last frame than the
/// master's own clock says by as much as this.
pub const SERIAL_ADAPTER_LATENCY: Duration = Duration::from_micros(50);

/// The limits of one line's gaps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// The spec's t3.5.
    pub spec: Duration,
    /// The least gap a request other than a trial gets: 3.5 character
    /// times and the adapter's latency (never above the spec).
    pub floor: Duration,
    /// The least silence tried: 1.5 character times, under which no drive
    /// can tell two frames apart.
    pub shortest_trial: Duration,
}

impl Limits {
    /// The limits of `line` behind an adapter that adds up to `latency`.
    pub fn for_line(line: LineTiming, latency: Duration) -> Self {
        let spec = line.t3_5();
        Self {
            spec,
            floor: (line.char_time() * 7 / 2 + latency).min(spec),
            shortest_trial: line.char_time() * 3 / 2,
        }
    }
}

/// What a request is, as far as its silence goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Use {
    /// A status poll: it may try a shorter silence.
    Poll,
    /// A client's command or read: the confirmed gap only.
    Command,
    /// An emergency: the confirmed gap if it was answered lately, else
    /// the spec.
    Emergency,
}

/// The silence to keep before one request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Silence {
    /// How long.
    pub gap: Duration,
    /// True when it is a trial, shorter than the drive's confirmed gap.
    pub trial: bool,
}

/// Where a drive's learning is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Trying `trial`: answered `answers` times so far after silences of
    /// at most `worst`, not answered `fails` times, `misses` times sent
    /// after a silence no shorter than `ok`. `ok` is the shortest level
    /// answered (the spec at first), `failed` the longest not answered.
    Stepping {
        trial: Duration,
        answers: u8,
        worst: Duration,
        fails: u8,
        misses: u8,
        ok: Duration,
        failed: Option<Duration>,
    },
    /// Learned: the confirmed gap holds until a fault.
    Settled,
    /// Back on the spec after a lone miss at `level`, a gap the drive had
    /// answered [`RECHECK_AFTER`] times: from `at`, the next poll goes
    /// after `level` again. An answer restores it (the miss was the line's
    /// or the host's, not the gap's); a miss is the drive's, and it waits
    /// its backoff.
    Recheck { level: Duration, at: Instant },
    /// Back on the spec after a fault; learning again from `until`.
    Waiting { until: Instant },
}

impl Phase {
    /// The first trial from the spec: half of it (a longer one could not
    /// shorten the gap, twice it).
    fn start(limits: &Limits) -> Self {
        Phase::Stepping {
            trial: (limits.spec / 2).max(limits.shortest_trial),
            answers: 0,
            worst: Duration::ZERO,
            fails: 0,
            misses: 0,
            ok: limits.spec,
            failed: None,
        }
    }

    /// The next trial between `ok` (answered) and `failed`, or `Settled`
    /// once they are within [`RESOLUTION`] of each other.
    fn between(ok: Duration, failed: Option<Duration>, limits: &Limits) -> Self {
        let next = match failed {
            Some(f) => (ok + f) / 2,
            None => (ok * STEP.0 / STEP.1).max(limits.shortest_trial),
        };
        let close = |f: Duration| ok.saturating_sub(f) <= ok / RESOLUTION;
        // A trial helps only if twice it makes a shorter gap than twice
        // `ok` (within the floor and the spec).
        let gap = |t: Duration| (t * 2).clamp(limits.floor, limits.spec);
        if failed.is_some_and(close) || next >= ok || gap(next) >= gap(ok) {
            return Phase::Settled;
        }
        Phase::Stepping {
            trial: next,
            answers: 0,
            worst: Duration::ZERO,
            fails: 0,
            misses: 0,
            ok,
            failed,
        }
    }
}

/// The steps end once the shortest silence answered and the longest not
/// answered are within 1/16 of each other.
const RESOLUTION: u32 = 16;

/// One drive's gap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DriveGap {
    /// The gap every request but a trial gets.
    confirmed: Duration,
    /// When a request sent after `confirmed` (or less) was last answered.
    confirmed_at: Option<Instant>,
    phase: Phase,
    /// The wait before the next relearning.
    backoff: Duration,
    /// Times the drive fell back to the spec.
    fallbacks: u64,
    /// The level that was answered before the last fallback: relearning
    /// tries it first.
    previous: Option<Duration>,
    /// What the last fallback replaced, until the next outcome: a late
    /// reply to the request that fell back restores it.
    undo: Option<Learned>,
    /// Requests answered after the confirmed gap since it was set.
    held: u32,
}

/// What a drive had learned before a fallback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Learned {
    confirmed: Duration,
    phase: Phase,
    backoff: Duration,
    previous: Option<Duration>,
    held: u32,
}

impl DriveGap {
    /// A drive not heard yet: the spec, trials from the first poll.
    pub fn new(limits: &Limits) -> Self {
        Self {
            confirmed: limits.spec,
            confirmed_at: None,
            phase: Phase::start(limits),
            backoff: RELEARN.0,
            fallbacks: 0,
            previous: None,
            undo: None,
            held: 0,
        }
    }

    /// The gap before the next request of kind `use_` at `now`.
    pub fn silence(&self, use_: Use, limits: &Limits, now: Instant) -> Silence {
        let confirmed = Silence {
            gap: self.confirmed,
            trial: false,
        };
        match use_ {
            Use::Poll => match self.phase {
                Phase::Stepping { trial, .. } if trial < self.confirmed => Silence {
                    gap: trial,
                    trial: true,
                },
                Phase::Recheck { level, at } if now >= at => Silence {
                    gap: level,
                    trial: true,
                },
                _ => confirmed,
            },
            Use::Command => confirmed,
            Use::Emergency => {
                if self
                    .confirmed_at
                    .is_some_and(|at| now.saturating_duration_since(at) <= RECENT)
                {
                    confirmed
                } else {
                    Silence {
                        gap: limits.spec,
                        trial: false,
                    }
                }
            }
        }
    }

    /// The gap requests get now (the spec until one was learned).
    pub fn confirmed(&self) -> Duration {
        self.confirmed
    }

    /// True while trials are wanted (and so a poll in idle time helps).
    pub fn wants_trial(&self, now: Instant) -> bool {
        match self.phase {
            Phase::Stepping { trial, .. } => trial < self.confirmed,
            Phase::Waiting { until } => now >= until,
            Phase::Recheck { at, .. } => now >= at,
            Phase::Settled => false,
        }
    }

    /// Times the drive fell back to the spec.
    pub fn fallbacks(&self) -> u64 {
        self.fallbacks
    }

    /// Moves a drive whose wait is over into its trials again.
    pub fn tick(&mut self, limits: &Limits, now: Instant) {
        if let Phase::Waiting { until } = self.phase
            && now >= until
        {
            // The level answered before the fallback first: if it is
            // answered again, the gap is back at once.
            self.phase = match self.previous.take() {
                Some(level) => Phase::Stepping {
                    trial: level,
                    answers: 0,
                    worst: Duration::ZERO,
                    fails: 0,
                    misses: 0,
                    ok: limits.spec,
                    failed: Some(level - level / RESOLUTION),
                },
                None => Phase::start(limits),
            };
        }
    }

    /// A request sent after `silence` (as measured) was answered at `now`;
    /// `trial` as [`silence`](Self::silence) said.
    pub fn answered(&mut self, silence: Duration, trial: bool, limits: &Limits, now: Instant) {
        self.undo = None;
        if silence <= self.confirmed + TOLERANCE {
            self.confirmed_at = Some(now);
            if !trial {
                self.held = self.held.saturating_add(1);
            }
        }
        if let Phase::Recheck { level, .. } = self.phase {
            // Only an answer after the level itself restores it.
            if trial && silence <= level + TOLERANCE {
                self.confirmed = level;
                self.confirmed_at = Some(now);
                self.phase = Phase::Settled;
                self.held = 0;
            }
            return;
        }
        let Phase::Stepping {
            trial: tried,
            answers,
            worst,
            fails,
            misses,
            ok,
            failed,
        } = self.phase
        else {
            return;
        };
        if !trial {
            return;
        }
        if silence >= ok {
            // The master could not keep it shorter than what was already
            // answered (its own overhead, or the machine kept it from
            // running): once something was learned, after a few, the steps
            // end there; before, the trial is simply made again.
            if misses + 1 >= MISSES_PER_STEP && ok < limits.spec {
                self.phase = Phase::Settled;
            } else {
                self.phase = Phase::Stepping {
                    trial: tried,
                    answers,
                    worst,
                    fails,
                    misses: misses + 1,
                    ok,
                    failed,
                };
            }
            return;
        }
        // A silence longer than the one tried, but shorter than any
        // answered before, still says something: the level counts at the
        // longest silence it was answered after.
        let worst = worst.max(silence).max(tried);
        if answers + 1 < ANSWERS_PER_STEP {
            self.phase = Phase::Stepping {
                trial: tried,
                answers: answers + 1,
                worst,
                fails,
                misses: 0,
                ok,
                failed,
            };
            return;
        }
        // The level holds: the drive's gap is twice the longest silence it
        // was answered after (never longer than a level before proved),
        // within the limits; the steps go on from the level tried.
        let confirmed = self
            .confirmed
            .min((worst * 2).clamp(limits.floor, limits.spec));
        if confirmed != self.confirmed {
            self.held = 0;
        }
        self.confirmed = confirmed;
        self.confirmed_at = Some(now);
        self.backoff = RELEARN.0;
        self.phase = Phase::between(tried, failed, limits);
    }

    /// Ends the steps: settled on the gap learned, or, with none learned,
    /// tried again after the backoff.
    fn settle_or_wait(&mut self, limits: &Limits, now: Instant) {
        if self.confirmed >= limits.spec {
            self.phase = Phase::Waiting {
                until: now + self.backoff,
            };
            self.backoff = (self.backoff * 2).min(RELEARN.1);
        } else {
            self.phase = Phase::Settled;
        }
    }

    /// A request sent after `silence` got no valid answer at `now` (a
    /// timeout, a CRC error, a reply that does not answer it).
    pub fn failed(&mut self, trial: bool, limits: &Limits, now: Instant) {
        self.undo = None;
        if trial && let Phase::Recheck { .. } = self.phase {
            // The gap that held is too short now: the drive's own doing.
            self.phase = Phase::Waiting {
                until: now + self.backoff,
            };
            self.backoff = (self.backoff * 2).min(RELEARN.1);
            return;
        }
        if trial {
            if let Phase::Stepping { fails, .. } = &mut self.phase
                && *fails + 1 < FAILS_PER_STEP
            {
                // Perhaps a reply lost to noise: the level is tried again.
                *fails += 1;
                return;
            }
            // Too short: the gap the answered levels confirmed stays, and
            // the next trial is halfway back to them. A drive that answered
            // no level (a strict one) is tried again after the backoff.
            if let Phase::Stepping { trial, ok, .. } = self.phase {
                self.phase = Phase::between(ok, Some(trial), limits);
            }
            if self.phase == Phase::Settled {
                self.settle_or_wait(limits, now);
            }
            return;
        }
        if self.confirmed < limits.spec {
            self.undo = Some(Learned {
                confirmed: self.confirmed,
                phase: self.phase,
                backoff: self.backoff,
                previous: self.previous,
                held: self.held,
            });
            self.fallbacks += 1;
            self.previous = Some(self.confirmed / 2);
            if self.held >= RECHECK_AFTER {
                // A lone miss after a long hold: checked again soon.
                self.phase = Phase::Recheck {
                    level: self.confirmed,
                    at: now + RECHECK,
                };
                self.confirmed = limits.spec;
                self.confirmed_at = None;
                self.held = 0;
                return;
            }
        }
        self.confirmed = limits.spec;
        self.confirmed_at = None;
        self.held = 0;
        self.phase = Phase::Waiting {
            until: now + self.backoff,
        };
        self.backoff = (self.backoff * 2).min(RELEARN.1);
    }
}

impl DriveGap {
    /// The request that failed last (and fell back) was answered after
    /// all, late, at `now`: the drive understood it after its gap, and
    /// what it had learned holds again. Nothing happens after any other
    /// outcome.
    pub fn answered_late(&mut self, now: Instant) {
        if let Some(learned) = self.undo.take() {
            self.confirmed = learned.confirmed;
            self.phase = learned.phase;
            self.backoff = learned.backoff;
            self.previous = learned.previous;
            self.held = learned.held;
            self.confirmed_at = Some(now);
        }
    }
}

/// Every unit's gap on one bus, as its master keeps them.
#[derive(Debug, Clone)]
pub struct Gaps {
    setting: Interframe,
    limits: Limits,
    drives: Box<[DriveGap; 256]>,
}

impl Gaps {
    /// Gaps for `setting` within `limits`, every drive at its start.
    pub fn new(setting: Interframe, limits: Limits) -> Self {
        Self {
            setting,
            limits,
            drives: Box::new([DriveGap::new(&limits); 256]),
        }
    }

    /// The limits in force.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// The silence before the next request of kind `use_` to `unit` (0:
    /// a broadcast, which every drive must understand: the spec).
    pub fn silence(&mut self, unit: u8, use_: Use, now: Instant) -> Silence {
        let fixed = |gap| Silence { gap, trial: false };
        match self.setting {
            Interframe::Spec => fixed(self.limits.spec),
            Interframe::Fixed(gap) => fixed(gap),
            Interframe::Auto if unit == 0 => fixed(self.limits.spec),
            Interframe::Auto => {
                let drive = &mut self.drives[usize::from(unit)];
                drive.tick(&self.limits, now);
                drive.silence(use_, &self.limits, now)
            }
        }
    }

    /// The least silence any request may get now: the line may be free
    /// for some request this soon after the last frame.
    pub fn least(&self) -> Duration {
        match self.setting {
            Interframe::Spec => self.limits.spec,
            Interframe::Fixed(gap) => gap,
            Interframe::Auto => self
                .drives
                .iter()
                .map(|d| match d.phase {
                    Phase::Stepping { trial, .. } => trial.min(d.confirmed),
                    Phase::Recheck { level, .. } => level.min(d.confirmed),
                    _ => d.confirmed,
                })
                .min()
                .unwrap_or(self.limits.spec),
        }
    }

    /// The gap `unit`'s requests get now.
    pub fn confirmed(&self, unit: u8) -> Duration {
        match self.setting {
            Interframe::Spec => self.limits.spec,
            Interframe::Fixed(gap) => gap,
            Interframe::Auto => self.drives[usize::from(unit)].confirmed,
        }
    }

    /// Times `unit` fell back to the spec.
    pub fn fallbacks(&self, unit: u8) -> u64 {
        self.drives[usize::from(unit)].fallbacks
    }

    /// True when a poll of `unit` would try a shorter silence now.
    pub fn wants_trial(&self, unit: u8, now: Instant) -> bool {
        self.setting == Interframe::Auto
            && unit != 0
            && self.drives[usize::from(unit)].wants_trial(now)
    }

    /// A request to `unit` sent after `silence` (measured) was answered.
    pub fn answered(&mut self, unit: u8, silence: Duration, trial: bool, now: Instant) {
        if self.setting == Interframe::Auto && unit != 0 {
            self.drives[usize::from(unit)].answered(silence, trial, &self.limits, now);
        }
    }

    /// A request to `unit` got no valid answer.
    pub fn failed(&mut self, unit: u8, trial: bool, now: Instant) {
        if self.setting == Interframe::Auto && unit != 0 {
            self.drives[usize::from(unit)].failed(trial, &self.limits, now);
        }
    }

    /// The request to `unit` that failed last was answered late (its
    /// retry's reply began before the drive could have answered the retry):
    /// a fallback it caused is undone.
    pub fn answered_late(&mut self, unit: u8, now: Instant) {
        if self.setting == Interframe::Auto && unit != 0 {
            self.drives[usize::from(unit)].answered_late(now);
        }
    }
}

#[cfg(test)]
mod tests;
