//! What the RTU master calls as frames go out and come in, on the bus
//! thread: it records each frame in the monitor's ring, counts faults per
//! attempt, and hands the scope its samples and write events.
//!
//! The master owns its tap and calls it at four places: a request sent, a
//! reply received (or its absence), stray bytes. The scheduler tells it,
//! before each transaction, who caused it ([`WireTap::cause`]). Nothing here
//! waits or allocates.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::BusMonitor;
use super::counters::WireEvent;
use super::record::{Direction, FrameOutcome, REQUEST_HEAD};
use crate::bus::Origin;
use crate::bus::master::Fault;
use crate::modbus::function::EXCEPTION_BIT;
use crate::modbus::timing::LineTiming;
use crate::scope::Scope;

/// The tap of one master.
pub struct WireTap {
    monitor: Option<Arc<BusMonitor>>,
    scope: Option<Arc<Scope>>,
    line: LineTiming,
    origin: Origin,
    /// The transaction in progress.
    unit: u8,
    attempt: u8,
    request: [u8; REQUEST_HEAD],
    request_len: u8,
    request_whole: bool,
    request_end: Instant,
    /// The unit of the last transaction: stray bytes are put down to it.
    last_unit: u8,
}

impl WireTap {
    /// A tap that records nothing (a master without a monitor).
    pub fn detached(line: LineTiming) -> Self {
        Self {
            monitor: None,
            scope: None,
            line,
            origin: Origin::Internal,
            unit: 0,
            attempt: 0,
            request: [0; REQUEST_HEAD],
            request_len: 0,
            request_whole: false,
            request_end: Instant::now(),
            last_unit: 0,
        }
    }

    /// Records into `monitor` and feeds `scope` from now on.
    pub fn attach(&mut self, monitor: Arc<BusMonitor>, scope: Arc<Scope>) {
        self.monitor = Some(monitor);
        self.scope = Some(scope);
    }

    /// The next transaction is caused by `origin`.
    pub fn cause(&mut self, origin: Origin) {
        self.origin = origin;
    }

    /// A request went out: `frame` (unit, PDU, CRC) to `unit`, its first
    /// byte at `sent_at`, attempt `attempt` (1 = first).
    pub fn request(&mut self, unit: u8, frame: &[u8], sent_at: Instant, attempt: u8) {
        self.unit = unit;
        self.last_unit = unit;
        self.attempt = attempt;
        let kept = frame.len().min(REQUEST_HEAD);
        self.request[..kept].copy_from_slice(&frame[..kept]);
        self.request_len = kept as u8;
        self.request_whole = kept == frame.len();
        self.request_end = sent_at + self.line.wire_time(frame.len());
        let Some(monitor) = &self.monitor else {
            return;
        };
        monitor.counters().add(unit, WireEvent::Attempt);
        if attempt == 1
            && let Some(scope) = &self.scope
            && frame.get(1).is_some_and(|&f| is_write(f))
        {
            scope.on_write(unit, &self.origin, sent_at);
        }
        if let Some(ring) = monitor.ring() {
            let at_ns = monitor.ns_since_start(sent_at);
            let origin = &self.origin;
            ring.push(|r| {
                r.at_ns = at_ns;
                r.direction = Direction::Request;
                r.unit = unit;
                r.attempt = attempt;
                r.outcome = if unit == 0 {
                    FrameOutcome::Broadcast
                } else {
                    FrameOutcome::Sent
                };
                r.detail = "";
                r.turnaround_us = None;
                r.origin.clone_from(origin);
                r.request_len = 0;
                r.set_bytes(frame);
            });
        }
    }

    /// The reply to the request in progress: `frame` (the bytes framed,
    /// `None` when the wait ended without a whole frame), its last byte at
    /// `end`, and what was wrong with it (`None`: a valid reply).
    pub fn reply(&mut self, frame: Option<&[u8]>, end: Instant, fault: Option<&Fault>) {
        let Some(monitor) = &self.monitor else {
            return;
        };
        let bytes = frame.unwrap_or(&[]);
        let (outcome, detail) = match fault {
            None if bytes.get(1).is_some_and(|f| f & EXCEPTION_BIT != 0) => {
                (FrameOutcome::Exception, "")
            }
            None => (FrameOutcome::Ok, ""),
            Some(Fault::Timeout) => (FrameOutcome::Timeout, ""),
            Some(Fault::Crc) => (FrameOutcome::CrcError, ""),
            Some(Fault::Mismatch(why)) => (FrameOutcome::BadReply, *why),
        };
        let counters = monitor.counters();
        match outcome {
            FrameOutcome::Exception => counters.add(self.unit, WireEvent::Exception),
            FrameOutcome::Timeout => counters.add(self.unit, WireEvent::Timeout),
            FrameOutcome::CrcError => counters.add(self.unit, WireEvent::CrcError),
            FrameOutcome::BadReply => counters.add(self.unit, WireEvent::BadReply),
            _ => {}
        }
        if outcome == FrameOutcome::Ok
            && let Some(scope) = &self.scope
        {
            scope.on_reply(
                self.unit,
                &self.request[..usize::from(self.request_len)],
                bytes,
                self.request_end,
            );
        }
        let Some(ring) = monitor.ring() else {
            return;
        };
        // The drive's turnaround: from the end of the request to the start
        // of the reply, which ended at `end` after its own wire time.
        let turnaround = (!bytes.is_empty()).then(|| {
            let started = end
                .checked_sub(self.line.wire_time(bytes.len()))
                .unwrap_or(end);
            let t = started.saturating_duration_since(self.request_end);
            u32::try_from(t.as_micros()).unwrap_or(u32::MAX)
        });
        let at_ns = monitor.ns_since_start(end);
        let (unit, attempt, origin) = (self.unit, self.attempt, &self.origin);
        let request = &self.request[..usize::from(self.request_len)];
        let whole = self.request_whole;
        ring.push(|r| {
            r.at_ns = at_ns;
            r.direction = Direction::Reply;
            r.unit = unit;
            r.attempt = attempt;
            r.outcome = outcome;
            r.detail = detail;
            r.turnaround_us = turnaround;
            r.origin.clone_from(origin);
            r.set_request(request, whole);
            r.set_bytes(bytes);
        });
    }

    /// Bytes that belong to no reply, read at `at`.
    pub fn stray(&mut self, bytes: &[u8], at: Instant) {
        let Some(monitor) = &self.monitor else {
            return;
        };
        if bytes.is_empty() {
            return;
        }
        monitor.counters().add_stray(self.last_unit, bytes.len());
        let Some(ring) = monitor.ring() else {
            return;
        };
        let at_ns = monitor.ns_since_start(at);
        let unit = self.last_unit;
        ring.push(|r| {
            r.at_ns = at_ns;
            r.direction = Direction::Noise;
            r.unit = unit;
            r.attempt = 0;
            r.outcome = FrameOutcome::Stray;
            r.detail = "";
            r.turnaround_us = None;
            r.origin = Origin::Internal;
            r.request_len = 0;
            r.set_bytes(bytes);
        });
    }

    /// Time a frame of `bytes` takes on the wire.
    pub fn wire_time(&self, bytes: usize) -> Duration {
        self.line.wire_time(bytes)
    }
}

/// Function codes that change a device: the scope's write trigger.
pub fn is_write(function: u8) -> bool {
    matches!(function, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::rtu_frame::encode;
    use crate::monitor::MonitorSettings;
    use crate::scope::ScopeSettings;

    fn tap() -> (WireTap, Arc<BusMonitor>) {
        let line = LineTiming::new_8n1(115_200);
        let monitor = Arc::new(BusMonitor::new(
            MonitorSettings::default(),
            line,
            vec![1, 2],
        ));
        let scope = Arc::new(Scope::new(ScopeSettings::default(), line, vec![1, 2]));
        let mut tap = WireTap::detached(line);
        tap.attach(monitor.clone(), scope);
        (tap, monitor)
    }

    #[test]
    fn records_a_transaction_with_its_retry_and_counts_per_attempt() {
        let (mut tap, monitor) = tap();
        tap.cause(Origin::Http {
            who: "scada".into(),
        });
        let read = encode(1, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
        let t0 = Instant::now();
        tap.request(1, &read, t0, 1);
        let mut bad = encode(1, &[0x03, 0x0E, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        bad[5] ^= 1;
        tap.reply(Some(&bad), t0 + Duration::from_millis(3), Some(&Fault::Crc));
        tap.stray(&[0x55, 0xAA], t0 + Duration::from_millis(4));
        tap.request(1, &read, t0 + Duration::from_millis(60), 2);
        let good = encode(1, &[0x03, 0x0E, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        let end =
            t0 + Duration::from_millis(60) + tap.wire_time(8 + 19) + Duration::from_micros(500);
        tap.reply(Some(&good), end, None);

        let frames = monitor.last(10);
        let kinds: Vec<_> = frames
            .iter()
            .map(|r| (r.direction, r.outcome, r.attempt))
            .collect();
        assert_eq!(
            kinds,
            [
                (Direction::Request, FrameOutcome::Sent, 1),
                (Direction::Reply, FrameOutcome::CrcError, 1),
                (Direction::Noise, FrameOutcome::Stray, 0),
                (Direction::Request, FrameOutcome::Sent, 2),
                (Direction::Reply, FrameOutcome::Ok, 2),
            ]
        );
        assert!(
            frames
                .iter()
                .filter(|r| r.direction != Direction::Noise)
                .all(|r| r.origin.kind() == "http")
        );
        // The turnaround of the good reply: 500 µs.
        let t = frames[4].turnaround_us.unwrap();
        assert!((499..=501).contains(&t), "{t}");
        assert_eq!(frames[4].request(), &read[..REQUEST_HEAD]);
        let c = monitor.counters().unit(1);
        assert_eq!(
            (c.attempts, c.crc_errors, c.timeouts, c.stray_bytes),
            (2, 1, 0, 2)
        );
    }

    #[test]
    fn a_timeout_is_a_reply_without_bytes() {
        let (mut tap, monitor) = tap();
        tap.cause(Origin::Poller);
        let t0 = Instant::now();
        tap.request(2, &encode(2, &[0x03, 0x00, 0xC0, 0x00, 0x07]), t0, 1);
        tap.reply(None, t0 + Duration::from_millis(51), Some(&Fault::Timeout));
        let last = &monitor.last(1)[0];
        assert_eq!(
            (last.outcome, last.len, last.turnaround_us),
            (FrameOutcome::Timeout, 0, None)
        );
        assert_eq!(monitor.counters().unit(2).timeouts, 1);
    }
}
