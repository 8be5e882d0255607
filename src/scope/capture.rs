//! One capture: the pure state machine that fills it, with time passed in
//! (what was asked for is [`super::spec`]).
//!
//! Armed, it keeps the last samples in a pre-trigger buffer; when the
//! trigger fires it keeps the samples after it until the length is reached;
//! then it ends. Its memory is allocated when it is armed, bounded by
//! `[scope] max_samples`, and never grows while it runs: the bus thread
//! feeds it without allocating.

use std::collections::VecDeque;
use std::time::{Duration, Instant, SystemTime};

use super::spec::{Amount, CaptureSpec};
use super::trigger::{Detector, Trigger};
use crate::bus::Origin;
use crate::drive::Status;

/// One status read of a captured drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    /// When the drive took it: the end of the status request on the wire.
    pub at: Instant,
    /// The drive.
    pub unit: u8,
    /// What it read.
    pub status: Status,
}

/// How a capture ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum End {
    /// It holds all it was asked for.
    Complete,
    /// A drive stopped answering (or the bus failed) before the length was
    /// reached: it holds what came.
    Incomplete,
    /// The trigger did not come within the wait: it holds the pre-trigger
    /// buffer.
    TimedOut,
    /// A client cancelled it.
    Cancelled,
}

/// Where a capture is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Waiting for the trigger, keeping the pre-trigger buffer.
    Armed,
    /// Triggered, filling.
    Triggered,
    /// Over.
    Ended(End),
}

impl Phase {
    /// Stable name: `armed`, `triggered`, `complete`, `incomplete`,
    /// `timed-out`, `cancelled`.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Armed => "armed",
            Phase::Triggered => "triggered",
            Phase::Ended(End::Complete) => "complete",
            Phase::Ended(End::Incomplete) => "incomplete",
            Phase::Ended(End::TimedOut) => "timed-out",
            Phase::Ended(End::Cancelled) => "cancelled",
        }
    }
}

/// The moment a capture triggered.
#[derive(Debug, Clone, PartialEq)]
pub struct Fired {
    /// When (t = 0 of the result).
    pub at: Instant,
    /// What happened, in words.
    pub what: String,
    /// Who caused it (a write's origin, or who asked for a manual trigger).
    pub by: Option<Origin>,
}

/// A capture in progress or over.
#[derive(Debug, Clone)]
pub struct Capture {
    id: u64,
    spec: CaptureSpec,
    phase: Phase,
    armed_at: Instant,
    /// Wall-clock time of `armed_at`.
    armed_wall: SystemTime,
    ended_at: Option<Instant>,
    pre: VecDeque<Sample>,
    pre_capacity: usize,
    post: Vec<Sample>,
    post_capacity: usize,
    /// Post-trigger samples per captured drive (in `spec.units` order).
    per_unit: Vec<u32>,
    /// When each captured drive last gave a sample after the trigger (the
    /// trigger's time before its first).
    last_at: Vec<Option<Instant>>,
    detector: Detector,
    fired: Option<Fired>,
    /// After this, a capture ends as incomplete once a drive it still
    /// needs has given no sample for [`SILENT`].
    post_deadline: Option<Instant>,
    /// One status read's time on the wire.
    transaction: Duration,
}

/// Added to a triggered capture's expected duration before it may end
/// incomplete.
const GRACE: Duration = Duration::from_millis(500);

/// Longest a drive that the bus still counts as online may go without a
/// sample before a capture that has outlasted its expected duration gives
/// up on it (the bus itself stopped: its port failed). A capture that is
/// only slower than expected (a busy host, a retry) goes on; a drive that
/// stopped answering, which the bus takes offline, ends it at once.
const SILENT: Duration = Duration::from_secs(5);

impl Capture {
    /// Arms a capture of `spec`, checked to need `pre` and `post` samples at
    /// most, at `now`; `transaction` is one status read's time on the wire.
    pub fn arm(
        id: u64,
        spec: CaptureSpec,
        (pre, post): (usize, usize),
        transaction: Duration,
        now: Instant,
        wall: SystemTime,
    ) -> Self {
        let detector = Detector::new(spec.trigger.clone());
        let mut capture = Self {
            id,
            per_unit: vec![0; spec.units.len()],
            last_at: vec![None; spec.units.len()],
            phase: Phase::Armed,
            armed_at: now,
            armed_wall: wall,
            ended_at: None,
            pre: VecDeque::with_capacity(pre),
            pre_capacity: pre,
            post: Vec::with_capacity(post),
            post_capacity: post,
            detector,
            fired: None,
            post_deadline: None,
            transaction,
            spec,
        };
        if capture.spec.trigger == Trigger::Immediate {
            capture.fire(now, "armed with an immediate trigger".into(), None);
        }
        capture
    }

    /// Its number.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// What was asked for.
    pub fn spec(&self) -> &CaptureSpec {
        &self.spec
    }

    /// Where it is.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// True while armed or filling.
    pub fn is_running(&self) -> bool {
        matches!(self.phase, Phase::Armed | Phase::Triggered)
    }

    /// When it triggered, if it did.
    pub fn fired(&self) -> Option<&Fired> {
        self.fired.as_ref()
    }

    /// When it was armed, and its wall-clock time.
    pub fn armed_at(&self) -> (Instant, SystemTime) {
        (self.armed_at, self.armed_wall)
    }

    /// When it ended.
    pub fn ended_at(&self) -> Option<Instant> {
        self.ended_at
    }

    /// Samples held before and after the trigger.
    pub fn counts(&self) -> (usize, usize) {
        (self.pre.len(), self.post.len())
    }

    /// Samples held in all, in time order (pre-trigger first).
    pub fn samples(&self) -> impl Iterator<Item = &Sample> {
        self.pre.iter().chain(self.post.iter())
    }

    /// The times of the first and the last sample held.
    pub fn first_last(&self) -> (Option<Instant>, Option<Instant>) {
        let first = self.pre.front().or(self.post.first()).map(|s| s.at);
        let last = self.post.last().or(self.pre.back()).map(|s| s.at);
        (first, last)
    }

    /// The samples from the trigger on.
    pub fn post(&self) -> &[Sample] {
        &self.post
    }

    /// A copy of everything but the samples from the trigger on (which a
    /// reader copies in steps, see [`extend_post`](Self::extend_post)).
    pub fn copy_without_post(&self) -> Capture {
        Capture {
            spec: self.spec.clone(),
            per_unit: self.per_unit.clone(),
            last_at: self.last_at.clone(),
            pre: self.pre.clone(),
            post: Vec::new(),
            detector: self.detector.clone(),
            fired: self.fired.clone(),
            ..*self
        }
    }

    /// Appends samples to a copy made by [`copy_without_post`](Self::copy_without_post).
    pub fn extend_post(&mut self, samples: &[Sample]) {
        self.post.extend_from_slice(samples);
    }

    /// Samples it may hold at most.
    pub fn capacity(&self) -> usize {
        self.pre_capacity + self.post_capacity
    }

    /// Post-trigger samples it waits for, for a length in samples.
    pub fn target(&self) -> Option<usize> {
        match self.spec.length {
            Amount::Samples(n) => Some(n as usize * self.spec.units.len()),
            Amount::Seconds(_) => None,
        }
    }

    /// A status read of `unit` taken at `at`.
    pub fn on_sample(&mut self, unit: u8, status: &Status, at: Instant) {
        let Some(index) = self.spec.units.iter().position(|&u| u == unit) else {
            return;
        };
        let sample = Sample {
            at,
            unit,
            status: *status,
        };
        match self.phase {
            Phase::Armed => {
                if let Some(what) = self.detector.sample(unit, status) {
                    self.fire(at, what, None);
                    self.keep_after_trigger(index, sample);
                } else {
                    self.keep_before_trigger(sample);
                }
            }
            Phase::Triggered => self.keep_after_trigger(index, sample),
            Phase::Ended(_) => {}
        }
    }

    /// A write to `unit` (0: a broadcast) by `origin` went on the wire at `at`.
    pub fn on_write(&mut self, unit: u8, origin: &Origin, at: Instant) {
        if self.phase != Phase::Armed || origin.is_background() {
            return;
        }
        if let Trigger::Write { unit: watched } = self.spec.trigger
            && (unit == watched || unit == 0)
        {
            let what = if unit == 0 {
                "a broadcast write".to_string()
            } else {
                format!("a write to unit {unit}")
            };
            self.fire(at, format!("{what} by {origin}"), Some(origin.clone()));
        }
    }

    /// A client asks for the trigger now.
    pub fn trigger_now(&mut self, at: Instant, by: Origin) -> Result<(), &'static str> {
        match self.phase {
            Phase::Armed => {
                self.fire(at, format!("triggered by hand by {by}"), Some(by));
                Ok(())
            }
            Phase::Triggered => Err("the capture has triggered already"),
            Phase::Ended(_) => Err("the capture is over"),
        }
    }

    /// Time passes: a wait or a length may run out. `offline(unit)` is
    /// the bus's view of a captured drive (no view: `|_| false`).
    pub fn tick(&mut self, now: Instant, offline: impl Fn(u8) -> bool) {
        match self.phase {
            Phase::Armed if now >= self.armed_at + self.spec.wait => {
                self.end(End::TimedOut, now);
            }
            Phase::Triggered => {
                let late = self.post_deadline.is_some_and(|d| now >= d);
                if self.a_needed_drive_stopped(now, late, offline) {
                    self.end(End::Incomplete, now);
                }
            }
            _ => {}
        }
    }

    /// Whether a drive the capture still needs samples of is offline, or,
    /// `late` past the expected duration, has given none for [`SILENT`]
    /// (since the trigger, before its first).
    fn a_needed_drive_stopped(
        &self,
        now: Instant,
        late: bool,
        offline: impl Fn(u8) -> bool,
    ) -> bool {
        let since_trigger = self.fired.as_ref().map(|f| f.at);
        self.spec
            .units
            .iter()
            .zip(self.per_unit.iter().zip(&self.last_at))
            .filter(|(_, (count, _))| match self.spec.length {
                Amount::Samples(n) => **count < n,
                Amount::Seconds(_) => true,
            })
            .any(|(&unit, (_, last))| {
                offline(unit)
                    || late
                        && last
                            .or(since_trigger)
                            .is_none_or(|t| now.saturating_duration_since(t) >= SILENT)
            })
    }

    /// A client cancels it.
    pub fn cancel(&mut self, now: Instant) {
        if self.is_running() {
            self.end(End::Cancelled, now);
        }
    }

    fn fire(&mut self, at: Instant, what: String, by: Option<Origin>) {
        self.phase = Phase::Triggered;
        // The pre-trigger buffer keeps only what it was asked for.
        match self.spec.pre_trigger {
            Amount::Samples(n) => {
                let mut total = [0u32; 256];
                for s in &self.pre {
                    total[usize::from(s.unit)] += 1;
                }
                let mut skip = total.map(|t| t.saturating_sub(n));
                self.pre.retain(|s| {
                    let left = &mut skip[usize::from(s.unit)];
                    if *left > 0 {
                        *left -= 1;
                        false
                    } else {
                        true
                    }
                });
            }
            Amount::Seconds(s) => {
                let since = at.checked_sub(Duration::from_secs_f64(s));
                self.pre.retain(|x| since.is_none_or(|t| x.at >= t));
            }
        }
        self.post_deadline = Some(match self.spec.length {
            // Each drive gets a read every `drives` transactions at full
            // rate; three times that, and the grace, before giving up.
            Amount::Samples(n) => {
                at + self.transaction * (3 * n * self.spec.units.len() as u32) + GRACE
            }
            Amount::Seconds(s) => at + Duration::from_secs_f64(s) + GRACE,
        });
        self.fired = Some(Fired { at, what, by });
    }

    fn keep_before_trigger(&mut self, sample: Sample) {
        if self.pre_capacity == 0 {
            return;
        }
        if let Amount::Seconds(s) = self.spec.pre_trigger
            && let Some(since) = sample.at.checked_sub(Duration::from_secs_f64(s))
        {
            while self.pre.front().is_some_and(|x| x.at < since) {
                self.pre.pop_front();
            }
        }
        // A count is per drive: a drive polled more often than another (a
        // client's read between polls) must not push the other's samples
        // out of the buffer.
        if let Amount::Samples(n) = self.spec.pre_trigger
            && self.pre.iter().filter(|s| s.unit == sample.unit).count() >= n as usize
            && let Some(oldest) = self.pre.iter().position(|s| s.unit == sample.unit)
        {
            self.pre.remove(oldest);
        }
        if self.pre.len() == self.pre_capacity {
            self.pre.pop_front();
        }
        self.pre.push_back(sample);
    }

    fn keep_after_trigger(&mut self, index: usize, sample: Sample) {
        let Some(fired) = &self.fired else {
            return;
        };
        if sample.at < fired.at {
            // Read before a trigger that came from outside (by hand) while
            // its reply was on the wire: it belongs before the trigger.
            self.keep_late_before_trigger(sample);
            return;
        }
        if let Some(last) = self.last_at.get_mut(index) {
            *last = Some(sample.at);
        }
        match self.spec.length {
            Amount::Samples(n) => {
                if self.per_unit[index] < n && self.post.len() < self.post_capacity {
                    self.post.push(sample);
                    self.per_unit[index] += 1;
                }
                if self.per_unit.iter().all(|&c| c >= n) || self.post.len() >= self.post_capacity {
                    self.end(End::Complete, sample.at);
                }
            }
            Amount::Seconds(s) => {
                if sample.at >= fired.at + Duration::from_secs_f64(s) {
                    self.end(End::Complete, sample.at);
                } else if self.post.len() < self.post_capacity {
                    self.post.push(sample);
                } else {
                    // Sized for the wire's fastest rate: cannot happen on
                    // a real line; end rather than grow.
                    self.end(End::Complete, sample.at);
                }
            }
        }
    }

    /// A sample taken before the trigger that arrived after it: added to
    /// the pre-trigger buffer within its bounds.
    fn keep_late_before_trigger(&mut self, sample: Sample) {
        if self.pre_capacity == 0 {
            return;
        }
        if let Amount::Samples(n) = self.spec.pre_trigger {
            let held = self.pre.iter().filter(|s| s.unit == sample.unit).count();
            if held >= n as usize
                && let Some(oldest) = self.pre.iter().position(|s| s.unit == sample.unit)
            {
                self.pre.remove(oldest);
            }
        }
        if self.pre.len() < self.pre_capacity {
            self.pre.push_back(sample);
        }
    }

    fn end(&mut self, end: End, now: Instant) {
        self.phase = Phase::Ended(end);
        self.ended_at = Some(now);
        self.post_deadline = None;
    }

    /// Time of `at` relative to the trigger (or, untriggered, to the arming).
    pub fn relative(&self, at: Instant) -> f64 {
        let zero = self.fired.as_ref().map_or(self.armed_at, |f| f.at);
        if at >= zero {
            (at - zero).as_secs_f64()
        } else {
            -(zero - at).as_secs_f64()
        }
    }

    /// Wall-clock time of `at`.
    pub fn wall(&self, at: Instant) -> SystemTime {
        if at >= self.armed_at {
            self.armed_wall + (at - self.armed_at)
        } else {
            self.armed_wall - (self.armed_at - at)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::StatusField;
    use crate::drive::status::FLAG_STALLED;
    use crate::scope::spec::fixtures::{limits, spec};
    use crate::scope::trigger::Edge;

    const MS: Duration = Duration::from_millis(1);
    const POLL: Duration = Duration::from_micros(5844);

    fn arm(spec: CaptureSpec, now: Instant) -> Capture {
        let caps = spec.check(&limits()).unwrap();
        Capture::arm(1, spec, caps, POLL, now, SystemTime::now())
    }

    fn speed(rpm: i16) -> Status {
        Status {
            speed_rpm: rpm,
            ..Status::default()
        }
    }

    #[test]
    fn a_speed_step_triggers_at_the_first_sample_above_the_level() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1],
                Trigger::Level {
                    unit: 1,
                    field: StatusField::SpeedRpm,
                    level: 50.0,
                    edge: Edge::Rising,
                },
                Amount::Samples(5),
                Amount::Samples(10),
            ),
            t0,
        );
        let mut t = t0;
        // 20 samples at 0 rpm, then the step to 100 rpm.
        for i in 0..40 {
            t += POLL;
            let rpm = if i < 20 { 0 } else { 100 };
            c.on_sample(1, &speed(rpm), t);
        }
        assert_eq!(c.phase(), Phase::Ended(End::Complete));
        let fired = c.fired().unwrap();
        assert_eq!(
            fired.at,
            t0 + POLL * 21,
            "the 21st sample is the first at 100 rpm"
        );
        let samples: Vec<_> = c.samples().collect();
        assert_eq!(c.counts(), (5, 10), "the pre-trigger holds the 5 before");
        assert!(samples[..5].iter().all(|s| s.status.speed_rpm == 0));
        assert!(samples[5..].iter().all(|s| s.status.speed_rpm == 100));
        assert_eq!(c.relative(samples[5].at), 0.0);
        assert!((c.relative(samples[4].at) + POLL.as_secs_f64()).abs() < 1e-9);
    }

    #[test]
    fn a_stall_of_one_of_two_drives_and_samples_per_drive() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1, 2],
                Trigger::Stall { unit: 2 },
                Amount::Samples(3),
                Amount::Samples(4),
            ),
            t0,
        );
        let stalled = Status {
            flags: FLAG_STALLED,
            ..Status::default()
        };
        let mut t = t0;
        for i in 0..30 {
            for unit in [1, 2] {
                t += POLL;
                let s = if unit == 2 && i >= 10 {
                    stalled
                } else {
                    speed(7)
                };
                c.on_sample(unit, &s, t);
            }
        }
        assert_eq!(c.phase(), Phase::Ended(End::Complete));
        let (pre, post) = c.counts();
        assert_eq!((pre, post), (6, 8), "3 and 4 samples of each drive");
        let first_post = c.samples().nth(pre).unwrap();
        assert_eq!((first_post.unit, first_post.status.stalled()), (2, true));
        assert_eq!(c.fired().unwrap().what, "the drive stalled");
    }

    #[test]
    fn a_pre_trigger_count_is_kept_per_drive_when_one_drive_is_sampled_more() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1, 2],
                Trigger::Manual,
                Amount::Samples(5),
                Amount::Samples(2),
            ),
            t0,
        );
        let mut t = t0;
        // Drive 2 first, then drive 1 three times as often.
        for _ in 0..5 {
            t += POLL;
            c.on_sample(2, &speed(2), t);
        }
        for _ in 0..15 {
            t += POLL;
            c.on_sample(1, &speed(1), t);
        }
        c.trigger_now(t, Origin::Internal).unwrap();
        let held = |unit| c.samples().filter(|s| s.unit == unit).count();
        assert_eq!(
            (held(1), held(2)),
            (5, 5),
            "5 before the trigger of each drive"
        );
    }

    #[test]
    fn a_write_from_a_client_triggers_and_polls_do_not() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1],
                Trigger::Write { unit: 1 },
                Amount::Seconds(0.05),
                Amount::Seconds(0.1),
            ),
            t0,
        );
        let mut t = t0;
        for _ in 0..20 {
            t += POLL;
            c.on_sample(1, &speed(0), t);
        }
        c.on_write(1, &Origin::Poller, t);
        c.on_write(2, &Origin::Internal, t);
        assert_eq!(c.phase(), Phase::Armed);
        let tcp = Origin::modbus_tcp("127.0.0.1:4000".parse().unwrap(), 9);
        let write_at = t + MS;
        c.on_write(1, &tcp, write_at);
        assert_eq!(c.phase(), Phase::Triggered);
        assert_eq!(c.fired().unwrap().by, Some(tcp));
        for _ in 0..40 {
            t += POLL;
            c.on_sample(1, &speed(10), t);
        }
        assert_eq!(c.phase(), Phase::Ended(End::Complete));
        let (pre, post) = c.counts();
        // 50 ms before the write, 100 ms after, at 5.844 ms a sample.
        assert_eq!(pre, 9);
        assert!((17..=18).contains(&post), "{post}");
        assert!(c.samples().take(pre).all(|s| s.at <= write_at));
        assert!(
            c.samples()
                .skip(pre)
                .all(|s| s.at > write_at && s.status.speed_rpm == 10)
        );
    }

    #[test]
    fn waits_run_out_and_drives_that_go_silent_end_it() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1],
                Trigger::Manual,
                Amount::Samples(2),
                Amount::Samples(100),
            ),
            t0,
        );
        c.on_sample(1, &speed(1), t0 + MS);
        c.tick(t0 + Duration::from_secs(9), |_| false);
        assert!(c.is_running());
        c.tick(t0 + Duration::from_secs(10), |_| false);
        assert_eq!(c.phase(), Phase::Ended(End::TimedOut));
        assert_eq!(c.counts(), (1, 0));

        let mut c = arm(
            spec(
                &[1],
                Trigger::Manual,
                Amount::Samples(2),
                Amount::Samples(100),
            ),
            t0,
        );
        c.on_sample(1, &speed(1), t0);
        c.trigger_now(t0 + 2 * MS, Origin::Http { who: "op".into() })
            .unwrap();
        assert!(c.trigger_now(t0 + MS, Origin::Internal).is_err());
        // Read before the trigger, its reply after it: before the trigger.
        c.on_sample(1, &speed(1), t0 + MS);
        assert_eq!(c.counts(), (2, 0));
        c.on_sample(1, &speed(1), t0 + 3 * MS);
        c.tick(t0 + Duration::from_secs(1), |_| false);
        assert!(c.is_running(), "100 samples take 0.6 s at full rate");
        // Past 3 times that: still online, silent for 3 s, it goes on...
        let mut copy = c.clone();
        copy.tick(t0 + Duration::from_secs(3), |_| false);
        assert!(copy.is_running());
        // ...silent for 5 s, it ends;
        copy.tick(t0 + Duration::from_secs(6), |_| false);
        assert_eq!(copy.phase(), Phase::Ended(End::Incomplete));
        // the bus took it offline: it ends at once.
        c.tick(t0 + Duration::from_millis(1500), |unit| unit == 1);
        assert_eq!(c.phase(), Phase::Ended(End::Incomplete));
        assert_eq!(c.counts(), (2, 1));
    }

    #[test]
    fn a_capture_slower_than_expected_goes_on_while_its_drive_is_online() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1],
                Trigger::Manual,
                Amount::Samples(0),
                Amount::Samples(100),
            ),
            t0,
        );
        c.trigger_now(t0, Origin::Internal).unwrap();
        // A sample every 100 ms: ten times slower than the wire allows (a
        // starved host), far past the expected duration.
        for i in 1..100 {
            let at = t0 + 100 * MS * i;
            c.tick(at, |_| false);
            assert!(c.is_running(), "sample {i}");
            c.on_sample(1, &speed(1), at);
        }
        c.tick(t0 + 100 * MS * 100, |_| false);
        c.on_sample(1, &speed(1), t0 + 100 * MS * 100);
        assert_eq!(c.phase(), Phase::Ended(End::Complete));
        assert_eq!(c.counts(), (0, 100));
    }

    #[test]
    fn immediate_and_cancel() {
        let t0 = Instant::now();
        let mut c = arm(
            spec(
                &[1],
                Trigger::Immediate,
                Amount::Samples(0),
                Amount::Seconds(1.0),
            ),
            t0,
        );
        assert_eq!(c.phase(), Phase::Triggered);
        c.on_sample(1, &speed(1), t0 + MS);
        c.cancel(t0 + 2 * MS);
        assert_eq!(c.phase().name(), "cancelled");
        assert_eq!(c.counts(), (0, 1));
    }
}
