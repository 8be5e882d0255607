//! The monitor's side of the bus's wire tap: it records each frame the
//! master shows in the monitor's ring and counts faults per attempt, on
//! the bus thread. Nothing here waits or allocates.

use std::time::Instant;

use super::BusMonitor;
use super::counters::WireEvent;
use super::record::{Direction, FrameOutcome};
use crate::bus::Origin;
use crate::bus::fault::Fault;
use crate::bus::observers::{Received, Sent, WireObserver};
use crate::modbus::function::EXCEPTION_BIT;

impl WireObserver for BusMonitor {
    fn sent(&self, sent: &Sent<'_>) {
        let (unit, attempt) = (sent.unit, sent.attempt);
        self.counters().add(unit, WireEvent::Attempt);
        let Some(ring) = self.ring() else {
            return;
        };
        let at_ns = self.ns_since_start(sent.at);
        let silence = u32::try_from(sent.silence.as_micros()).unwrap_or(u32::MAX);
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
            r.silence_us = Some(silence);
            r.origin.clone_from(sent.origin);
            r.request_len = 0;
            r.set_bytes(sent.frame);
        });
    }

    fn received(&self, got: &Received<'_>) {
        let bytes = got.frame;
        let (outcome, detail) = match got.fault {
            None if bytes.get(1).is_some_and(|f| f & EXCEPTION_BIT != 0) => {
                (FrameOutcome::Exception, "")
            }
            None => (FrameOutcome::Ok, ""),
            Some(Fault::Timeout) => (FrameOutcome::Timeout, ""),
            Some(Fault::Crc) => (FrameOutcome::CrcError, ""),
            Some(Fault::Mismatch(why)) => (FrameOutcome::BadReply, *why),
        };
        let counters = self.counters();
        match outcome {
            FrameOutcome::Exception => counters.add(got.unit, WireEvent::Exception),
            FrameOutcome::Timeout => counters.add(got.unit, WireEvent::Timeout),
            FrameOutcome::CrcError => counters.add(got.unit, WireEvent::CrcError),
            FrameOutcome::BadReply => counters.add(got.unit, WireEvent::BadReply),
            _ => {}
        }
        let Some(ring) = self.ring() else {
            return;
        };
        // The drive's turnaround: from the end of the request to the start
        // of the reply, which ended at `end` after its own wire time.
        let end = got.end;
        let turnaround = (!bytes.is_empty()).then(|| {
            let started = end.checked_sub(self.wire_time(bytes.len())).unwrap_or(end);
            let t = started.saturating_duration_since(got.request_end);
            u32::try_from(t.as_micros()).unwrap_or(u32::MAX)
        });
        let at_ns = self.ns_since_start(end);
        ring.push(|r| {
            r.at_ns = at_ns;
            r.direction = Direction::Reply;
            r.unit = got.unit;
            r.attempt = got.attempt;
            r.outcome = outcome;
            r.detail = detail;
            r.turnaround_us = turnaround;
            r.silence_us = turnaround;
            r.origin.clone_from(got.origin);
            r.set_request(got.request, got.request_whole);
            r.set_bytes(bytes);
        });
    }

    fn stray(&self, unit: u8, bytes: &[u8], at: Instant) {
        self.counters().add_stray(unit, bytes.len());
        let Some(ring) = self.ring() else {
            return;
        };
        let at_ns = self.ns_since_start(at);
        ring.push(|r| {
            r.at_ns = at_ns;
            r.direction = Direction::Noise;
            r.unit = unit;
            r.attempt = 0;
            r.outcome = FrameOutcome::Stray;
            r.detail = "";
            r.turnaround_us = None;
            r.silence_us = None;
            r.origin = Origin::Internal;
            r.request_len = 0;
            r.set_bytes(bytes);
        });
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::time::Duration;

    use super::*;
    use crate::bus::tap::{REQUEST_HEAD, WireTap};
    use crate::modbus::rtu_frame::encode;
    use crate::modbus::timing::LineTiming;
    use crate::monitor::MonitorSettings;

    fn tap() -> (WireTap, Arc<BusMonitor>) {
        let line = LineTiming::new_8n1(115_200);
        let monitor = Arc::new(BusMonitor::new(
            MonitorSettings::default(),
            line,
            vec![1, 2],
        ));
        let mut tap = WireTap::detached(line);
        tap.attach(vec![monitor.clone()]);
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
        tap.request(1, &read, t0, 1, Duration::ZERO);
        let mut bad = encode(1, &[0x03, 0x0E, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        bad[5] ^= 1;
        tap.reply(Some(&bad), t0 + Duration::from_millis(3), Some(&Fault::Crc));
        tap.stray(&[0x55, 0xAA], t0 + Duration::from_millis(4));
        tap.request(1, &read, t0 + Duration::from_millis(60), 2, Duration::ZERO);
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
        tap.request(
            2,
            &encode(2, &[0x03, 0x00, 0xC0, 0x00, 0x07]),
            t0,
            1,
            Duration::ZERO,
        );
        tap.reply(None, t0 + Duration::from_millis(51), Some(&Fault::Timeout));
        let last = &monitor.last(1)[0];
        assert_eq!(
            (last.outcome, last.len, last.turnaround_us),
            (FrameOutcome::Timeout, 0, None)
        );
        assert_eq!(monitor.counters().unit(2).timeouts, 1);
    }
}
