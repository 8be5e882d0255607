//! The master's tap on the wire: it keeps the transaction in progress (its
//! unit, attempt, the first bytes of the request, who caused it) and shows
//! each frame to the bus's [`WireObserver`]s as it goes out or comes in.
//!
//! The master calls it at three places: a request sent, a reply received
//! (or its absence), stray bytes. The scheduler tells it, before each
//! transaction, who caused it ([`WireTap::cause`]). Nothing here waits or
//! allocates.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::fault::Fault;
use super::observers::{Received, Sent, WireObserver};
use super::origin::Origin;
use crate::modbus::timing::LineTiming;

/// How many bytes of a request a reply is shown with: enough for the unit,
/// function, address and count of any request the drives know.
pub const REQUEST_HEAD: usize = 8;

/// The tap of one master.
pub struct WireTap {
    observers: Vec<Arc<dyn WireObserver>>,
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
    /// A tap that shows nothing (a master without observers).
    pub fn detached(line: LineTiming) -> Self {
        Self {
            observers: Vec::new(),
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

    /// Shows every frame to `observers` from now on, in their order.
    pub fn attach(&mut self, observers: Vec<Arc<dyn WireObserver>>) {
        self.observers = observers;
    }

    /// The next transaction is caused by `origin`.
    pub fn cause(&mut self, origin: Origin) {
        self.origin = origin;
    }

    /// A request went out: `frame` (unit, PDU, CRC) to `unit`, its first
    /// byte at `sent_at`, attempt `attempt` (1 = first), after `silence`
    /// since the end of the last frame (as the master measured it).
    pub fn request(
        &mut self,
        unit: u8,
        frame: &[u8],
        sent_at: Instant,
        attempt: u8,
        silence: Duration,
    ) {
        self.unit = unit;
        self.last_unit = unit;
        self.attempt = attempt;
        let kept = frame.len().min(REQUEST_HEAD);
        self.request[..kept].copy_from_slice(&frame[..kept]);
        self.request_len = kept as u8;
        self.request_whole = kept == frame.len();
        self.request_end = sent_at + self.line.wire_time(frame.len());
        let sent = Sent {
            unit,
            attempt,
            frame,
            at: sent_at,
            silence,
            origin: &self.origin,
        };
        for observer in &self.observers {
            observer.sent(&sent);
        }
    }

    /// The reply to the request in progress: `frame` (the bytes framed,
    /// `None` when the wait ended without a whole frame), its last byte at
    /// `end`, and what was wrong with it (`None`: a valid reply).
    pub fn reply(&mut self, frame: Option<&[u8]>, end: Instant, fault: Option<&Fault>) {
        let received = Received {
            unit: self.unit,
            attempt: self.attempt,
            origin: &self.origin,
            request: &self.request[..usize::from(self.request_len)],
            request_whole: self.request_whole,
            request_end: self.request_end,
            frame: frame.unwrap_or(&[]),
            end,
            fault,
        };
        for observer in &self.observers {
            observer.received(&received);
        }
    }

    /// Bytes that belong to no reply, read at `at`.
    pub fn stray(&mut self, bytes: &[u8], at: Instant) {
        if bytes.is_empty() {
            return;
        }
        for observer in &self.observers {
            observer.stray(self.last_unit, bytes, at);
        }
    }

    /// Time a frame of `bytes` takes on the wire.
    pub fn wire_time(&self, bytes: usize) -> Duration {
        self.line.wire_time(bytes)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::modbus::rtu_frame::encode;

    /// What one observer was shown, in order.
    #[derive(Debug, Clone, PartialEq)]
    enum Shown {
        Sent {
            unit: u8,
            attempt: u8,
            len: usize,
            origin: String,
        },
        Received {
            unit: u8,
            attempt: u8,
            origin: String,
            request: Vec<u8>,
            whole: bool,
            frame: Vec<u8>,
            fault: Option<Fault>,
            request_end: Instant,
        },
        Stray {
            unit: u8,
            bytes: Vec<u8>,
        },
    }

    #[derive(Default)]
    struct Recorder(Mutex<Vec<Shown>>);

    impl Recorder {
        fn shown(&self) -> Vec<Shown> {
            self.0.lock().unwrap().clone()
        }
    }

    impl WireObserver for Recorder {
        fn sent(&self, s: &Sent<'_>) {
            self.0.lock().unwrap().push(Shown::Sent {
                unit: s.unit,
                attempt: s.attempt,
                len: s.frame.len(),
                origin: s.origin.kind().to_string(),
            });
        }

        fn received(&self, r: &Received<'_>) {
            self.0.lock().unwrap().push(Shown::Received {
                unit: r.unit,
                attempt: r.attempt,
                origin: r.origin.kind().to_string(),
                request: r.request.to_vec(),
                whole: r.request_whole,
                frame: r.frame.to_vec(),
                fault: r.fault.cloned(),
                request_end: r.request_end,
            });
        }

        fn stray(&self, unit: u8, bytes: &[u8], _at: Instant) {
            self.0.lock().unwrap().push(Shown::Stray {
                unit,
                bytes: bytes.to_vec(),
            });
        }
    }

    fn line() -> LineTiming {
        LineTiming::new_8n1(115_200)
    }

    fn attached(observers: usize) -> (WireTap, Vec<Arc<Recorder>>) {
        let recorders: Vec<Arc<Recorder>> = (0..observers)
            .map(|_| Arc::new(Recorder::default()))
            .collect();
        let mut tap = WireTap::detached(line());
        tap.attach(
            recorders
                .iter()
                .map(|r| r.clone() as Arc<dyn WireObserver>)
                .collect(),
        );
        (tap, recorders)
    }

    #[test]
    fn a_reply_is_shown_with_its_request_head_cause_and_the_end_of_the_request() {
        let (mut tap, rec) = attached(1);
        tap.cause(Origin::Http { who: "op".into() });
        // Unit 3 reads 7 registers from 0x00C0: 8 bytes, kept whole.
        let read = encode(3, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
        let t0 = Instant::now();
        tap.request(3, &read, t0, 2, Duration::ZERO);
        let reply = encode(3, &[0x03, 0x02, 0x12, 0x34]);
        tap.reply(Some(&reply), t0 + Duration::from_millis(2), None);
        let shown = rec[0].shown();
        assert_eq!(
            shown[0],
            Shown::Sent {
                unit: 3,
                attempt: 2,
                len: 8,
                origin: "http".into()
            }
        );
        assert_eq!(
            shown[1],
            Shown::Received {
                unit: 3,
                attempt: 2,
                origin: "http".into(),
                request: read.to_vec(),
                whole: true,
                frame: reply.to_vec(),
                fault: None,
                // 8 bytes at 115200 8N1 after the first byte went out.
                request_end: t0 + line().wire_time(8),
            }
        );
    }

    #[test]
    fn a_long_request_is_shown_by_its_head_and_said_not_to_be_whole() {
        let (mut tap, rec) = attached(1);
        // Write 3 registers from 0x0100: 15 bytes, more than the head.
        let write = encode(1, &[0x10, 0x01, 0x00, 0x00, 0x03, 0x06, 0, 1, 0, 2, 0, 3]);
        assert!(write.len() > REQUEST_HEAD);
        let t0 = Instant::now();
        tap.request(1, &write, t0, 1, Duration::ZERO);
        tap.reply(None, t0 + Duration::from_millis(50), Some(&Fault::Timeout));
        let Shown::Received {
            request,
            whole,
            frame,
            fault,
            ..
        } = &rec[0].shown()[1]
        else {
            panic!("no reply shown: {:?}", rec[0].shown());
        };
        assert_eq!(request.as_slice(), &write[..REQUEST_HEAD]);
        assert!(!whole);
        assert!(frame.is_empty(), "a timeout has no bytes");
        assert_eq!(fault, &Some(Fault::Timeout));
    }

    #[test]
    fn stray_bytes_are_put_down_to_the_last_unit_and_nothing_is_no_stray() {
        let (mut tap, rec) = attached(1);
        tap.stray(&[0xFF], Instant::now());
        tap.request(
            4,
            &encode(4, &[0x03, 0x00, 0xC0, 0x00, 0x07]),
            Instant::now(),
            1,
            Duration::ZERO,
        );
        tap.stray(&[], Instant::now());
        tap.stray(&[0x55, 0xAA], Instant::now());
        let strays: Vec<_> = rec[0]
            .shown()
            .into_iter()
            .filter(|s| matches!(s, Shown::Stray { .. }))
            .collect();
        assert_eq!(
            strays,
            [
                // Before any transaction: unit 0.
                Shown::Stray {
                    unit: 0,
                    bytes: vec![0xFF]
                },
                Shown::Stray {
                    unit: 4,
                    bytes: vec![0x55, 0xAA]
                },
            ]
        );
    }

    #[test]
    fn every_observer_is_shown_every_frame_and_a_cause_lasts_until_the_next() {
        let (mut tap, rec) = attached(2);
        let read = encode(1, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
        tap.cause(Origin::Scope);
        tap.request(1, &read, Instant::now(), 1, Duration::ZERO);
        tap.reply(None, Instant::now(), Some(&Fault::Crc));
        tap.request(1, &read, Instant::now(), 2, Duration::ZERO);
        tap.cause(Origin::Poller);
        tap.request(1, &read, Instant::now(), 1, Duration::ZERO);
        assert_eq!(rec[0].shown(), rec[1].shown());
        let origins: Vec<String> = rec[0]
            .shown()
            .iter()
            .filter_map(|s| match s {
                Shown::Sent { origin, .. } => Some(origin.clone()),
                _ => None,
            })
            .collect();
        assert_eq!(origins, ["scope", "scope", "poller"]);
    }

    #[test]
    fn attaching_replaces_the_observers() {
        let (mut tap, rec) = attached(1);
        let read = encode(1, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
        tap.request(1, &read, Instant::now(), 1, Duration::ZERO);
        tap.attach(Vec::new());
        tap.request(1, &read, Instant::now(), 2, Duration::ZERO);
        tap.stray(&[1, 2, 3], Instant::now());
        assert_eq!(rec[0].shown().len(), 1, "{:?}", rec[0].shown());
    }
}
