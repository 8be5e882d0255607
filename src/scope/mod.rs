//! The scope: captures chosen status fields of one or more drives at the
//! highest rate the bus allows, around a trigger.
//!
//! - [`spec`] is what a client asks for, checked against the limits;
//! - [`capture`] is one capture's pure state machine (time passed in):
//!   armed with a pre-trigger buffer, triggered, ended;
//! - [`trigger`] says what starts it and detects it in the samples;
//! - [`field`] says which status fields it records, and how a client
//!   names them;
//! - [`steer`] decides which drive is polled while a capture runs: the
//!   captured drives at full rate, the others at a floor rate;
//! - [`result`] renders a capture as JSON or CSV;
//! - [`tap`] is the scope's side of the bus: what it takes from the wire
//!   and how it steers the polling.
//!
//! [`Scope`] is the one capture slot of a bus, shared by the bus thread
//! (which feeds it samples and write events through the bus's wire tap,
//! and asks it which drive to poll) and the API (which arms, triggers, cancels
//! and reads it). With no capture running the bus thread only reads one
//! atomic flag.

pub mod capture;
pub mod field;
pub mod result;
pub mod spec;
pub mod steer;
pub mod tap;
pub mod trigger;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime};

use tokio::sync::Notify;

use crate::bus::Origin;
use crate::bus::observers::Steer;
use crate::drive::Status;
use crate::drive::registers::{STATUS_BLOCK_LEN, STATUS_BLOCK_START};
use crate::modbus::timing::LineTiming;
use capture::Capture;
use spec::{CaptureSpec, Limits, SpecError};
use steer::PollSteer;

/// `[scope]` settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScopeSettings {
    /// Samples one capture may hold (its memory: this times
    /// [`capture::Sample`]'s size).
    pub max_samples: usize,
    /// Status reads per second each drive not captured keeps while a
    /// capture runs.
    pub floor_rate_hz: f64,
    /// Longest wait for a trigger.
    pub max_wait: Duration,
}

impl Default for ScopeSettings {
    fn default() -> Self {
        Self {
            max_samples: 200_000,
            floor_rate_hz: 10.0,
            max_wait: Duration::from_secs(3600),
        }
    }
}

/// Why the scope refused a request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScopeError {
    /// A capture is running on this bus.
    #[error(
        "capture {id} is {state} on this bus: one capture per bus at a time; cancel it first (DELETE) or wait for it to end"
    )]
    Busy {
        /// The running capture.
        id: u64,
        /// Its state.
        state: &'static str,
    },
    /// The capture asked for does not fit.
    #[error("{0}")]
    Invalid(#[from] SpecError),
    /// No capture has been armed since start-up.
    #[error("no capture has been armed on this bus yet")]
    None,
    /// The operation does not apply in the capture's state.
    #[error("{0}")]
    State(&'static str),
}

#[derive(Default)]
struct Inner {
    capture: Option<Capture>,
    steer: Option<PollSteer>,
}

/// The capture slot of one bus.
pub struct Scope {
    settings: ScopeSettings,
    line: LineTiming,
    units: Mutex<Vec<u8>>,
    /// A capture is armed or triggered: the bus thread looks at nothing
    /// else while this is false.
    running: AtomicBool,
    inner: Mutex<Inner>,
    next_id: AtomicU64,
    changed: Notify,
}

/// A status read's request PDU (manual 1.7).
const STATUS_READ: [u8; 5] = [
    0x03,
    (STATUS_BLOCK_START >> 8) as u8,
    STATUS_BLOCK_START as u8,
    (STATUS_BLOCK_LEN >> 8) as u8,
    STATUS_BLOCK_LEN as u8,
];

impl Scope {
    /// The scope of a bus with `line` timing whose drives are `units`.
    pub fn new(settings: ScopeSettings, line: LineTiming, units: Vec<u8>) -> Self {
        Self {
            settings,
            line,
            units: Mutex::new(units),
            running: AtomicBool::new(false),
            inner: Mutex::new(Inner::default()),
            next_id: AtomicU64::new(1),
            changed: Notify::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic while the capture was held leaves, at worst, a capture
        // missing a sample: go on with it.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The settings.
    pub fn settings(&self) -> &ScopeSettings {
        &self.settings
    }

    /// One status read's time on the wire with no turnaround: the fastest
    /// a drive can be sampled.
    pub fn transaction_time(&self) -> Duration {
        self.line.transaction_time(8, 19, Duration::ZERO)
    }

    /// The limits every capture must fit.
    pub fn limits(&self) -> Limits {
        Limits {
            max_samples: self.settings.max_samples,
            wire_rate: 1.0 / self.transaction_time().as_secs_f64(),
            max_wait: self.settings.max_wait,
        }
    }

    /// The configured units of the bus.
    pub fn units(&self) -> Vec<u8> {
        self.units.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The bus's drives are now `units` (a reload added or removed drives
    /// on the running bus): from the next capture armed.
    pub fn set_units(&self, units: Vec<u8>) {
        *self.units.lock().unwrap_or_else(|p| p.into_inner()) = units;
    }

    /// True while a capture is armed or triggered.
    pub fn is_running(&self) -> bool {
        self.running.load(Ordering::Acquire)
    }

    /// Waits until a capture is armed (or another change worth telling).
    pub async fn changed(&self) {
        self.changed.notified().await;
    }

    /// Arms a capture of `spec` at `now`; refused while one runs.
    pub fn arm(&self, spec: CaptureSpec, now: Instant) -> Result<u64, ScopeError> {
        let units = self.units();
        if let Some(&unknown) = spec.units.iter().find(|u| !units.contains(u)) {
            return Err(ScopeError::Invalid(SpecError::Invalid(format!(
                "unit {unknown} is not a configured drive of this bus"
            ))));
        }
        let capacities = spec.check(&self.limits())?;
        let mut inner = self.lock();
        if let Some(c) = inner.capture.as_ref().filter(|c| c.is_running()) {
            return Err(ScopeError::Busy {
                id: c.id(),
                state: c.phase().name(),
            });
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let floor = Duration::from_secs_f64(1.0 / self.settings.floor_rate_hz.max(0.001));
        inner.steer = Some(PollSteer::new(&spec.units, &units, floor));
        // Drop the previous capture before allocating the next one.
        inner.capture = None;
        inner.capture = Some(Capture::arm(
            id,
            spec,
            capacities,
            self.transaction_time(),
            now,
            SystemTime::now(),
        ));
        self.running.store(true, Ordering::Release);
        drop(inner);
        self.changed.notify_waiters();
        Ok(id)
    }

    /// Cancels the running capture (it keeps what it holds).
    pub fn cancel(&self, now: Instant) -> Result<u64, ScopeError> {
        let mut inner = self.lock();
        let capture = inner.capture.as_mut().ok_or(ScopeError::None)?;
        if !capture.is_running() {
            return Err(ScopeError::State("the capture is over already"));
        }
        capture.cancel(now);
        let id = capture.id();
        self.settle(&mut inner);
        Ok(id)
    }

    /// Triggers the running capture by hand, for `by`.
    pub fn trigger(&self, now: Instant, by: Origin) -> Result<u64, ScopeError> {
        let mut inner = self.lock();
        let capture = inner.capture.as_mut().ok_or(ScopeError::None)?;
        capture.trigger_now(now, by).map_err(ScopeError::State)?;
        let id = capture.id();
        self.settle(&mut inner);
        Ok(id)
    }

    /// Lets time pass for the running capture (waits and lengths run out).
    pub fn tick(&self, now: Instant) {
        if !self.is_running() {
            return;
        }
        let mut inner = self.lock();
        if let Some(c) = inner.capture.as_mut() {
            c.tick(now, |_| false);
        }
        self.settle(&mut inner);
    }

    /// Reads the current (or last) capture, under the lock the bus thread
    /// takes for each sample while a capture runs: `f` must be quick (use
    /// [`snapshot`](Self::snapshot) for the samples).
    pub fn with_capture<T>(&self, f: impl FnOnce(&Capture) -> T) -> Result<T, ScopeError> {
        let inner = self.lock();
        inner.capture.as_ref().map(f).ok_or(ScopeError::None)
    }

    /// A copy of the current (or last) capture, samples included, to render
    /// outside the lock. While a capture runs, its samples after the
    /// trigger are copied a batch at a time, the lock released between
    /// batches, so a reader holds up the bus thread for one batch's copy
    /// at most (8192 samples, 256 kB), never for the rendering.
    pub fn snapshot(&self) -> Result<Capture, ScopeError> {
        const BATCH: usize = 8192;
        let (mut copy, id) = {
            let inner = self.lock();
            let capture = inner.capture.as_ref().ok_or(ScopeError::None)?;
            if !capture.is_running() {
                // The bus thread no longer touches it.
                return Ok(capture.clone());
            }
            (capture.copy_without_post(), capture.id())
        };
        loop {
            let inner = self.lock();
            let Some(post) = inner
                .capture
                .as_ref()
                .filter(|c| c.id() == id)
                .map(Capture::post)
            else {
                break;
            };
            let copied = copy.post().len();
            if copied >= post.len() {
                break;
            }
            let end = post.len().min(copied + BATCH);
            copy.extend_post(&post[copied..end]);
        }
        Ok(copy)
    }

    /// Clears the running flag once the capture ended.
    fn settle(&self, inner: &mut Inner) {
        if !inner.capture.as_ref().is_some_and(Capture::is_running) {
            inner.steer = None;
            self.running.store(false, Ordering::Release);
        }
    }

    // What the bus thread calls.

    /// A valid reply `frame` to the request whose first bytes were
    /// `request`, for `unit`; the request left the wire at `at`.
    pub fn on_reply(&self, unit: u8, request: &[u8], frame: &[u8], at: Instant) {
        if !self.is_running() || request.get(1..6) != Some(&STATUS_READ[..]) {
            return;
        }
        // unit, 0x03, byte count 14, the status block, CRC.
        let Some(status) = frame
            .get(3..3 + Status::BYTES)
            .filter(|_| frame.get(2) == Some(&(Status::BYTES as u8)))
            .and_then(Status::from_bytes)
        else {
            return;
        };
        let mut inner = self.lock();
        if let Some(c) = inner.capture.as_mut() {
            c.on_sample(unit, &status, at);
        }
        self.settle(&mut inner);
    }

    /// A write to `unit` (0: broadcast) by `origin` went out at `at`.
    pub fn on_write(&self, unit: u8, origin: &Origin, at: Instant) {
        if !self.is_running() {
            return;
        }
        let mut inner = self.lock();
        if let Some(c) = inner.capture.as_mut() {
            c.on_write(unit, origin, at);
        }
    }

    /// Which drive to poll at `now` while a capture runs (`None`: no
    /// capture, the poll plan decides). `plan_due` and `offline` are the
    /// poll plan's and the status cache's views of a unit.
    pub fn steer(
        &self,
        now: Instant,
        plan_due: impl Fn(u8) -> bool,
        offline: impl Fn(u8) -> bool,
    ) -> Option<Steer> {
        if !self.is_running() {
            return None;
        }
        let mut inner = self.lock();
        if let Some(c) = inner.capture.as_mut() {
            c.tick(now, &offline);
        }
        self.settle(&mut inner);
        inner.steer.as_mut().map(|s| s.next(now, plan_due, offline))
    }

    /// `unit`'s status was polled at `now`.
    pub fn polled(&self, unit: u8, now: Instant) {
        if !self.is_running() {
            return;
        }
        if let Some(s) = self.lock().steer.as_mut() {
            s.polled(unit, now);
        }
    }

    /// Who a poll of `unit` is for: the scope while it captures the drive,
    /// else the poller.
    pub fn poll_origin(&self, unit: u8) -> Origin {
        if self.is_running()
            && self
                .lock()
                .steer
                .as_ref()
                .is_some_and(|s| s.is_captured(unit))
        {
            Origin::Scope
        } else {
            Origin::Poller
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::rtu_frame::encode;
    use field::RECORDED;
    use spec::Amount;
    use trigger::Trigger;

    fn scope() -> Scope {
        Scope::new(
            ScopeSettings::default(),
            LineTiming::new_8n1(115_200),
            vec![1, 2, 3],
        )
    }

    fn spec(units: &[u8]) -> CaptureSpec {
        CaptureSpec {
            units: units.to_vec(),
            fields: RECORDED.to_vec(),
            trigger: Trigger::Manual,
            pre_trigger: Amount::Samples(10),
            length: Amount::Samples(3),
            wait: Duration::from_secs(60),
        }
    }

    fn status_reply(unit: u8, rpm: i16) -> Vec<u8> {
        let mut pdu = vec![0x03, 14];
        pdu.extend_from_slice(
            &Status {
                speed_rpm: rpm,
                ..Status::default()
            }
            .to_bytes(),
        );
        encode(unit, &pdu)
    }

    #[test]
    fn one_capture_at_a_time_fed_by_status_replies() {
        let scope = scope();
        assert!(!scope.is_running());
        assert_eq!(scope.steer(Instant::now(), |_| true, |_| false), None);
        let t0 = Instant::now();
        let id = scope.arm(spec(&[2]), t0).unwrap();
        assert!(scope.is_running());
        let busy = scope.arm(spec(&[1]), t0).unwrap_err();
        assert!(busy.to_string().contains("one capture per bus"), "{busy}");
        assert_eq!(scope.poll_origin(2), Origin::Scope);
        assert_eq!(scope.poll_origin(1), Origin::Poller);
        let request = encode(2, &STATUS_READ);
        scope.on_reply(2, &request, &status_reply(2, 10), t0);
        // A write's echo is not a sample.
        let write = encode(2, &[0x06, 0x00, 0x06, 0x00, 0x0A]);
        scope.on_reply(2, &write, &write, t0);
        assert_eq!(scope.with_capture(|c| c.counts()).unwrap(), (1, 0));
        scope.trigger(t0, Origin::Internal).unwrap();
        for i in 0..3 {
            scope.on_reply(
                2,
                &request,
                &status_reply(2, 20),
                t0 + Duration::from_millis(i + 1),
            );
        }
        assert!(!scope.is_running(), "three samples: complete");
        assert_eq!(
            scope.with_capture(|c| (c.id(), c.phase().name())).unwrap(),
            (id, "complete")
        );
        assert_eq!(scope.steer(t0, |_| true, |_| false), None);
        // The next one may be armed now.
        assert!(scope.arm(spec(&[1]), t0).is_ok());
        assert!(scope.cancel(t0).is_ok());
        assert!(matches!(scope.cancel(t0), Err(ScopeError::State(_))));
    }

    #[test]
    fn a_snapshot_of_a_running_capture_holds_every_sample_so_far() {
        let scope = scope();
        let t0 = Instant::now();
        let mut spec = spec(&[1]);
        spec.trigger = Trigger::Immediate;
        spec.length = Amount::Samples(20_000);
        scope.arm(spec, t0).unwrap();
        let request = encode(1, &STATUS_READ);
        for i in 0..10_000u64 {
            let rpm = (i % 1000) as i16;
            scope.on_reply(
                1,
                &request,
                &status_reply(1, rpm),
                t0 + Duration::from_micros(i),
            );
        }
        let copy = scope.snapshot().unwrap();
        assert!(copy.is_running());
        assert_eq!(copy.counts(), (0, 10_000));
        assert!(
            copy.samples()
                .enumerate()
                .all(|(i, s)| s.status.speed_rpm == (i % 1000) as i16)
        );
        scope.cancel(t0).unwrap();
        assert_eq!(scope.snapshot().unwrap().counts(), (0, 10_000));
    }

    #[test]
    fn refuses_drives_of_other_buses() {
        let e = scope().arm(spec(&[9]), Instant::now()).unwrap_err();
        assert!(e.to_string().contains("unit 9"), "{e}");
    }
}
