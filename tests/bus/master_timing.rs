//! The RTU master's deadlines against a peer on a real pty that writes
//! frames whole, in pieces, late or never: the guard after a drive that
//! stays silent, and the reply deadline that follows the wire once a reply
//! has begun (long replies at low baud rates).
//!
//! Bounds come from the design, not from an idle machine: lower bounds are
//! what the master must wait at least; upper bounds sit far from the old
//! behaviour they rule out.

use std::time::{Duration, Instant};

use crate::support::pty::{master, pty};
use drivegate::bus::master::{Fault, Guard, MasterSettings};
use drivegate::bus::stats::Outcome;
use drivegate::modbus::rtu_frame;
use drivegate::modbus::timing::LineTiming;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_serial::SerialStream;

/// What the peer does with each request it reads.
#[derive(Debug, Clone)]
enum Step {
    /// Nothing.
    Silence,
    /// After `delay`, write `bytes` at once.
    Write { delay: Duration, bytes: Vec<u8> },
}

/// A peer on the far end of a pty running `script`, one step per request;
/// reports each request's arrival time.
fn peer(
    mut ptm: SerialStream,
    script: Vec<Step>,
) -> (
    mpsc::UnboundedReceiver<Instant>,
    mpsc::UnboundedReceiver<Instant>,
) {
    let (arrived_tx, arrived) = mpsc::unbounded_channel();
    let (written_tx, written) = mpsc::unbounded_channel();
    tokio::spawn(async move {
        let mut buf = Vec::new();
        for step in script {
            loop {
                let mut chunk = [0u8; 256];
                let n = match ptm.read(&mut chunk).await {
                    Ok(0) | Err(_) => return,
                    Ok(n) => n,
                };
                let at = Instant::now();
                buf.extend_from_slice(&chunk[..n]);
                if let rtu_frame::FrameLength::Known(len) = rtu_frame::request_length(&buf)
                    && buf.len() >= len
                {
                    buf.drain(..len);
                    let _ = arrived_tx.send(at);
                    break;
                }
            }
            if let Step::Write { delay, bytes } = step {
                tokio::time::sleep(delay).await;
                ptm.write_all(&bytes).await.unwrap();
                let _ = written_tx.send(Instant::now());
            }
        }
        std::future::pending::<()>().await;
    });
    (arrived, written)
}

fn settings(baud: u32, timeout_ms: u64, retries: u8) -> MasterSettings {
    MasterSettings::new(baud, Duration::from_millis(timeout_ms), retries)
}

/// Read `count` holding registers from 0.
fn read(count: u16) -> Vec<u8> {
    let [hi, lo] = count.to_be_bytes();
    vec![0x03, 0x00, 0x00, hi, lo]
}

/// The reply frame of unit 100 to `read(count)`, register `a` holding `a + offset`.
fn reply(count: u16, offset: u16) -> Vec<u8> {
    let mut pdu = vec![0x03, (count * 2) as u8];
    for a in 0..count {
        pdu.extend_from_slice(&(a + offset).to_be_bytes());
    }
    rtu_frame::encode(100, &pdu)
}

#[tokio::test]
async fn a_silent_drive_is_probed_once_with_a_short_guard() {
    let (ptm, path, _keep) = pty();
    let (mut arrived, _) = peer(ptm, vec![Step::Silence, Step::Silence]);
    let mut m = master(&path, settings(115_200, 200, 1)).await;
    let status = [0x03, 0x00, 0xC0, 0x00, 0x07];
    // Before the first request is written: the lower bound is measured
    // from here, so a peer woken late for the first request (a loaded
    // machine) cannot make the master look hasty.
    let asked = Instant::now();
    for _ in 0..2 {
        let r = m.probe(1, &status).await.unwrap();
        // One attempt whatever the retries.
        assert_eq!((r.outcome, r.attempts), (Outcome::Timeout, 1));
        assert_eq!(r.fault, Some(Fault::Timeout));
    }
    let first = arrived.recv().await.unwrap();
    let second = arrived.recv().await.unwrap();
    let gap = second - first;
    // A drive never heard is probed with the shortest timeout (the floor),
    // then the guard: as long as a 19-byte reply starting then would take
    // (1.65 ms), t3.5 and the timeout again; then t3.5 before the next...
    let line = LineTiming::new_8n1(115_200);
    let floor = drivegate::bus::master::DEFAULT_REPLY_TIMEOUT_FLOOR;
    let least = line.wire_time(8) + floor + line.wire_time(19) + line.t3_5() + floor + line.t3_5();
    let since_asked = second - asked;
    assert!(
        since_asked >= least - Duration::from_micros(200),
        "{since_asked:?} from the first probe to the second request"
    );
    // ...not the 200 ms response timeout.
    assert!(gap < Duration::from_millis(200), "{gap:?}");
}

#[tokio::test]
async fn a_late_reply_answers_the_retry_of_its_request_and_nothing_shifts() {
    // The drive answers in 2 ms once, and its timeout is learned; then a
    // reply comes 600 ms after its request, past that timeout and its
    // guard but before the 2 s ceiling. It is the answer to the same
    // request, which the retry repeats: taken (values + 0). The retry's own
    // reply (values + 1) comes after it and is discarded before the next
    // request, whose reply (values + 2) is its own.
    let (ptm, path, _keep) = pty();
    let line = LineTiming::new_8n1(115_200);
    let (_, _) = peer(
        ptm,
        vec![
            Step::Write {
                delay: line.wire_time(8) + Duration::from_millis(2),
                bytes: reply(7, 9),
            },
            Step::Write {
                delay: line.wire_time(8) + Duration::from_millis(600),
                bytes: reply(7, 0),
            },
            Step::Write {
                delay: Duration::ZERO,
                bytes: reply(7, 1),
            },
            Step::Write {
                delay: Duration::ZERO,
                bytes: reply(7, 2),
            },
        ],
    );
    let mut m = master(&path, settings(115_200, 2000, 1)).await;
    let r = m.transact(100, &read(7), None).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::Ok, 1));
    // Learned from one reply: three times its turnaround and the margin,
    // with its guard (twice that and 3.4 ms) far below 600 ms.
    let learned = m.reply_timeout(100);
    assert!(learned < Duration::from_millis(250), "{learned:?}");
    let r = m.transact(100, &read(7), None).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::Ok, 2));
    assert_eq!(&r.reply.unwrap()[2..4], &[0x00, 0x00]);
    // A different read of the same length is held until the first
    // attempt's reply could no longer come; the same one may go.
    let now = Instant::now();
    assert!(m.held_until(100, &read(7), now).is_none());
    let other = [0x03, 0x00, 0x10, 0x00, 0x07];
    assert!(m.held_until(100, &other, now).is_some());
    assert!(m.held_until(101, &other, now).is_none(), "another unit");
    // The late reply raised the timeout.
    assert!(m.reply_timeout(100) > learned, "{:?}", m.reply_timeout(100));
    // The same read may go at once (above): the retry's own reply (values
    // + 1) answers an identical request, so when a busy machine delivers it
    // after the flush it is this read's answer, a few milliseconds old; else
    // it was discarded and this read gets its own (values + 2). Either way
    // in one attempt, and never a reply to another request.
    let r = m.transact(100, &read(7), None).await.unwrap();
    let reply = r.reply.unwrap();
    assert_eq!(r.attempts, 1);
    assert!(
        matches!(reply[2..4], [0x00, 0x01 | 0x02]),
        "{:02x?}",
        &reply[2..4]
    );
}

#[tokio::test]
async fn a_fixed_guard_is_kept_after_a_silent_timeout() {
    let (ptm, path, _keep) = pty();
    let (mut arrived, _) = peer(ptm, vec![Step::Silence, Step::Silence]);
    let mut s = settings(115_200, 50, 1);
    s.guard = Guard::Fixed(Duration::from_millis(150));
    let mut m = master(&path, s).await;
    let start = Instant::now();
    let r = m
        .transact(1, &[0x03, 0x00, 0xC0, 0x00, 0x07], None)
        .await
        .unwrap();
    assert_eq!(r.outcome, Outcome::Timeout);
    let first = arrived.recv().await.unwrap();
    let retry = arrived.recv().await.unwrap();
    // The timeout, then the whole 150 ms guard, from when the request was
    // sent (the peer may see the first request late on a busy machine,
    // never the retry early).
    assert!(first >= start);
    assert!(
        retry - start >= Duration::from_millis(200),
        "{:?}",
        retry - start
    );
}

#[tokio::test]
async fn a_reply_that_starts_while_a_probe_keeps_the_line_is_taken_whole() {
    // 9600 baud: after a probe's short timeout (t3.5 + 1 ms) the line is
    // kept as long as the 255-byte reply takes (266 ms). The reply starts
    // 70 ms after the request, late but inside that time: it is read whole
    // and taken, as the drive's answer, and counted late; the next
    // request's reply (values + 1) is the next request's.
    let (ptm, path, _keep) = pty();
    let line = LineTiming::new_8n1(9600);
    let late = line.wire_time(8) + Duration::from_millis(70);
    let (_, _) = peer(
        ptm,
        vec![
            Step::Write {
                delay: late,
                bytes: reply(125, 0),
            },
            Step::Write {
                delay: Duration::ZERO,
                bytes: reply(125, 1),
            },
        ],
    );
    let mut m = master(&path, settings(9600, 50, 1)).await;
    let r = m.probe(100, &read(125)).await.unwrap();
    assert_eq!((r.outcome, r.attempts, r.late_replies), (Outcome::Ok, 1, 1));
    assert_eq!(&r.reply.unwrap()[2..4], &[0x00, 0x00]);
    assert_eq!(r.stray_bytes, 0);
    // Its turnaround (~70 ms) is learned: past the 50 ms ceiling, so the
    // ceiling it is.
    assert_eq!(m.reply_timeout(100), Duration::from_millis(50));
    let r = m.probe(100, &read(125)).await.unwrap();
    assert_eq!(r.outcome, Outcome::Ok);
    assert_eq!(&r.reply.unwrap()[2..4], &[0x00, 0x01], "its own reply");
}

#[tokio::test]
async fn long_replies_at_low_baud_follow_the_wire_not_the_timeout() {
    for baud in [9600, 19_200] {
        let line = LineTiming::new_8n1(baud);
        let (mut ptm, path, _keep) = pty();
        let mut m = master(&path, settings(baud, 50, 0)).await;
        // A peer that writes the 255-byte reply at the wire's pace, a few
        // bytes at a time, after a 1 ms turnaround.
        let pacer = tokio::spawn(async move {
            let mut request = [0u8; 8];
            ptm.read_exact(&mut request).await.unwrap();
            let frame = reply(125, 0);
            let start = Instant::now() + Duration::from_millis(1);
            for (i, piece) in frame.chunks(4).enumerate() {
                let due = start + line.wire_time((i + 1) * 4);
                tokio::time::sleep_until(due.into()).await;
                ptm.write_all(piece).await.unwrap();
            }
            ptm
        });
        let sent = Instant::now();
        let r = m.transact(100, &read(125), None).await.unwrap();
        assert_eq!(r.outcome, Outcome::Ok, "{baud} baud: {:?}", r.fault);
        let pdu = r.reply.unwrap();
        assert_eq!(pdu.len(), 252);
        assert_eq!(&pdu[248..], &[0x00, 123, 0x00, 124]);
        // It took its wire time, far more than the 50 ms timeout.
        assert!(sent.elapsed() >= line.wire_time(255), "{baud} baud");
        drop(pacer.await.unwrap());
    }
}

#[tokio::test]
async fn a_reply_that_stops_halfway_is_cut_short_once_the_rest_is_overdue() {
    let line = LineTiming::new_8n1(9600);
    let (ptm, path, _keep) = pty();
    let mut frame = reply(125, 0);
    frame.truncate(100);
    let (_, mut written) = peer(
        ptm,
        vec![Step::Write {
            delay: Duration::from_millis(1),
            bytes: frame,
        }],
    );
    let mut m = master(&path, settings(9600, 50, 0)).await;
    let r = m.transact(100, &read(125), None).await.unwrap();
    let done = Instant::now();
    assert_eq!(r.outcome, Outcome::BadReply);
    assert_eq!(r.fault, Some(Fault::Mismatch("reply cut short")));
    // Not before the 155 missing bytes could have come, plus t3.5.
    let written = written.recv().await.unwrap();
    assert!(done - written >= line.wire_time(155) + line.t3_5());
}

#[tokio::test]
async fn a_long_reply_whose_first_byte_is_late_is_a_timeout() {
    let line = LineTiming::new_8n1(9600);
    let (ptm, path, _keep) = pty();
    let (_, _) = peer(
        ptm,
        vec![Step::Write {
            delay: line.wire_time(8) + Duration::from_millis(60),
            bytes: reply(125, 0),
        }],
    );
    let mut m = master(&path, settings(9600, 50, 0)).await;
    let r = m.transact(100, &read(125), None).await.unwrap();
    assert_eq!(
        (r.outcome, r.fault),
        (Outcome::Timeout, Some(Fault::Timeout))
    );
    // The reply starts after the ceiling: a different read of the same
    // length waits until it has passed; the same read may go (the late
    // reply is its answer).
    let now = Instant::now();
    assert!(m.held_until(100, &read(125), now).is_none());
    let mut other = read(125);
    other[2] = 0x10;
    assert!(m.held_until(100, &other, now).is_some());
}
