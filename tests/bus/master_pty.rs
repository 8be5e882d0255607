//! The RTU master against a scripted peer on a real pty: each wire hazard is
//! produced on purpose and the master must never hand a reply to the wrong
//! request.

use std::os::fd::OwnedFd;
use std::time::{Duration, Instant};

use crate::support::pty::{master, pty};
use drivegate::bus::master::{Guard, MasterSettings, RtuMaster};
use drivegate::bus::port::{self, Direction, Rs485Settings};
use drivegate::bus::stats::Outcome;
use drivegate::drive::{DriveReply, DriveRequest, Status};
use drivegate::modbus::rtu_frame::{self, FrameLength};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_serial::{SerialPort, SerialStream};

/// What the peer does with one request.
#[derive(Debug, Clone)]
enum Answer {
    /// Reply with this PDU from this unit, after this delay.
    Reply {
        unit: u8,
        pdu: Vec<u8>,
        delay: Duration,
    },
    /// Send these raw bytes (noise, corrupted frames), then maybe a reply.
    Raw(Vec<u8>, Duration),
    /// Say nothing.
    Silence,
}

struct Peer {
    /// Requests the peer received, with their arrival time.
    requests: mpsc::UnboundedReceiver<(Vec<u8>, Instant)>,
    /// Times the peer finished writing each answer.
    _keep: OwnedFd,
}

/// A pty whose far end answers with `script`, one entry per request.
fn start_peer(script: Vec<Answer>) -> (String, Peer, mpsc::UnboundedReceiver<Instant>) {
    let (mut ptm, path, keep) = pty();
    let (req_tx, req_rx) = mpsc::unbounded_channel();
    let (done_tx, done_rx) = mpsc::unbounded_channel();
    tokio::spawn(async move {
        let mut buf = Vec::new();
        for answer in script {
            // Read one whole request.
            loop {
                let mut chunk = [0u8; 256];
                let n = match ptm.read(&mut chunk).await {
                    Ok(0) | Err(_) => return,
                    Ok(n) => n,
                };
                let at = Instant::now();
                buf.extend_from_slice(&chunk[..n]);
                let len = match rtu_frame::request_length(&buf) {
                    FrameLength::Known(len) => len,
                    // The test peer takes an unknown function's frame as the chunk read.
                    FrameLength::BySilence => buf.len(),
                    FrameLength::NeedMore => usize::MAX,
                };
                if buf.len() >= len {
                    let frame: Vec<u8> = buf.drain(..len).collect();
                    req_tx.send((frame, at)).unwrap();
                    break;
                }
            }
            match answer {
                Answer::Reply { unit, pdu, delay } => {
                    tokio::time::sleep(delay).await;
                    ptm.write_all(&rtu_frame::encode(unit, &pdu)).await.unwrap();
                }
                Answer::Raw(bytes, delay) => {
                    tokio::time::sleep(delay).await;
                    ptm.write_all(&bytes).await.unwrap();
                }
                Answer::Silence => {}
            }
            let _ = done_tx.send(Instant::now());
        }
        // Keep the pty open until the test ends.
        std::future::pending::<()>().await;
    });
    (
        path,
        Peer {
            requests: req_rx,
            _keep: keep,
        },
        done_rx,
    )
}

fn status_reply(turns: u16) -> Vec<u8> {
    let status = Status {
        turns,
        ..Status::default()
    };
    let mut pdu = vec![0x03, 0x0E];
    pdu.extend_from_slice(&status.to_bytes());
    pdu
}

/// The response timeout and guard time of these tests: far longer than a
/// loaded machine keeps the peer (a task on this test's thread) from
/// answering, so only the script's own silences and delays are faults.
const TIMEOUT: Duration = Duration::from_millis(500);
const GUARD: Duration = Duration::from_millis(600);

/// The drives' time to act on a broadcast in these tests.
const BROADCAST_DELAY: Duration = Duration::from_millis(1000);

fn settings() -> MasterSettings {
    let mut s = MasterSettings::new(115_200, TIMEOUT, 1);
    s.guard = Guard::Fixed(GUARD);
    s
}

fn read_status() -> Vec<u8> {
    DriveRequest::ReadStatus.pdu().unwrap()
}

fn turns_of(reply: &[u8]) -> u16 {
    match DriveRequest::ReadStatus.parse_reply(reply).unwrap() {
        DriveReply::Status(s) => s.turns,
        other => panic!("not a status: {other:?}"),
    }
}

const NOW: Duration = Duration::ZERO;

#[tokio::test]
async fn a_status_read_and_its_reply() {
    let (path, mut peer, _) = start_peer(vec![Answer::Reply {
        unit: 1,
        pdu: status_reply(7),
        delay: NOW,
    }]);
    let mut m = master(&path, settings()).await;
    let report = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!(report.outcome, Outcome::Ok);
    assert_eq!(report.attempts, 1);
    assert_eq!(turns_of(report.reply.as_ref().unwrap()), 7);
    let (frame, _) = peer.requests.recv().await.unwrap();
    assert_eq!(frame, DriveRequest::ReadStatus.frame(1).unwrap());
}

#[tokio::test]
async fn the_next_request_waits_for_the_silent_interval() {
    let script = (0..20)
        .map(|i| Answer::Reply {
            unit: 1,
            pdu: status_reply(i),
            delay: NOW,
        })
        .collect();
    let (path, mut peer, mut done) = start_peer(script);
    let mut m = master(&path, settings()).await;
    for i in 0..20 {
        let report = m.transact(1, &read_status(), None).await.unwrap();
        assert_eq!(turns_of(report.reply.as_ref().unwrap()), i);
    }
    // Each request arrived at least t3.5 after the previous reply was written.
    let _first = peer.requests.recv().await.unwrap();
    for _ in 1..20 {
        let reply_written = done.recv().await.unwrap();
        let (_, arrival) = peer.requests.recv().await.unwrap();
        let gap = arrival - reply_written;
        assert!(
            gap >= Duration::from_micros(1750),
            "gap of {gap:?} violates t3.5"
        );
    }
}

#[tokio::test]
async fn a_timeout_is_retried_and_a_late_reply_is_not_taken_for_the_next() {
    // First request: the reply comes 800 ms late (300 ms past the timeout,
    // 300 ms before the end of the guard that follows it). The retry is
    // answered with turns=2. Then a second transaction must get turns=3,
    // never the stale turns=1.
    let (path, _peer, _) = start_peer(vec![
        Answer::Reply {
            unit: 1,
            pdu: status_reply(1),
            delay: TIMEOUT + GUARD / 2,
        },
        Answer::Reply {
            unit: 1,
            pdu: status_reply(2),
            delay: NOW,
        },
        Answer::Reply {
            unit: 1,
            pdu: status_reply(3),
            delay: NOW,
        },
    ]);
    let mut m = master(&path, settings()).await;
    let first = m.transact(1, &read_status(), None).await.unwrap();
    // The late reply arrived during the guard time after the timeout and was
    // discarded; but the peer only sees the retry after it sent that late
    // reply, so the retry's answer is turns=2.
    assert_eq!(first.outcome, Outcome::Ok);
    assert_eq!(first.attempts, 2);
    assert_eq!(turns_of(first.reply.as_ref().unwrap()), 2);
    assert!(
        first.stray_bytes >= 19,
        "the late reply was discarded: {}",
        first.stray_bytes
    );
    let second = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!(turns_of(second.reply.as_ref().unwrap()), 3);
}

#[tokio::test]
async fn corrupted_and_foreign_replies_are_rejected() {
    let mut corrupted = rtu_frame::encode(1, &status_reply(9));
    corrupted[5] ^= 0x10;
    let (path, _peer, _) = start_peer(vec![
        Answer::Raw(corrupted, NOW),
        Answer::Reply {
            unit: 1,
            pdu: status_reply(10),
            delay: NOW,
        },
        // Next transaction: a reply from unit 2 to a request for unit 1.
        Answer::Reply {
            unit: 2,
            pdu: status_reply(11),
            delay: NOW,
        },
        Answer::Reply {
            unit: 1,
            pdu: status_reply(12),
            delay: NOW,
        },
        // Next: noise before the reply.
        Answer::Raw(
            [
                vec![0xFF, 0x00, 0x13],
                rtu_frame::encode(1, &status_reply(13)),
            ]
            .concat(),
            NOW,
        ),
        Answer::Reply {
            unit: 1,
            pdu: status_reply(14),
            delay: NOW,
        },
    ]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!((r.attempts, turns_of(r.reply.as_ref().unwrap())), (2, 10));
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!((r.attempts, turns_of(r.reply.as_ref().unwrap())), (2, 12));
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!((r.attempts, turns_of(r.reply.as_ref().unwrap())), (2, 14));
}

#[tokio::test]
async fn out_of_retries_reports_the_fault() {
    let (path, _peer, _) = start_peer(vec![Answer::Silence, Answer::Silence]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!(r.outcome, Outcome::Timeout);
    assert_eq!(r.attempts, 2);
    assert!(r.reply.is_none());

    let mut crc = rtu_frame::encode(1, &status_reply(1));
    let last = crc.len() - 1;
    crc[last] ^= 1;
    let (path, _peer, _) = start_peer(vec![Answer::Raw(crc, NOW)]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &read_status(), Some(1)).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::CrcError, 1));
}

#[tokio::test]
async fn an_echo_must_repeat_the_write() {
    let write = DriveRequest::Speed { rpm: 100 }.pdu().unwrap();
    let stale = DriveRequest::Speed { rpm: 50 }.pdu().unwrap();
    let (path, _peer, _) = start_peer(vec![
        Answer::Reply {
            unit: 1,
            pdu: stale,
            delay: NOW,
        },
        Answer::Reply {
            unit: 1,
            pdu: write.clone(),
            delay: NOW,
        },
    ]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &write, None).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::Ok, 2));
    assert_eq!(r.reply.unwrap(), write);
}

#[tokio::test]
async fn exceptions_are_replies_not_retried() {
    let (path, _peer, _) = start_peer(vec![Answer::Reply {
        unit: 1,
        pdu: vec![0x83, 0x02],
        delay: NOW,
    }]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::Exception, 1));
    assert_eq!(r.reply.unwrap(), vec![0x83, 0x02]);
}

#[tokio::test]
async fn unknown_function_codes_are_framed_by_silence() {
    // 0x41 has no known length: the reply ends at t3.5 of silence.
    let (path, _peer, _) = start_peer(vec![Answer::Reply {
        unit: 1,
        pdu: vec![0x41, 1, 2, 3, 4, 5],
        delay: NOW,
    }]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &[0x41, 0xAA], None).await.unwrap();
    assert_eq!(r.outcome, Outcome::Ok);
    assert_eq!(r.reply.unwrap(), vec![0x41, 1, 2, 3, 4, 5]);
}

#[tokio::test]
async fn a_broadcast_expects_nothing_and_waits_the_turnaround() {
    let (path, mut peer, _) = start_peer(vec![
        Answer::Silence,
        Answer::Reply {
            unit: 5,
            pdu: status_reply(5),
            delay: NOW,
        },
    ]);
    let mut s = settings();
    // Long enough that a loaded machine's stalls cannot pass for it.
    s.broadcast_delay = BROADCAST_DELAY;
    let mut m = master(&path, s).await;
    let set = DriveRequest::SetAddress { address: 5 }.pdu().unwrap();
    let start = Instant::now();
    let r = m.transact(0, &set, None).await.unwrap();
    assert_eq!(
        (r.outcome, r.reply.as_deref()),
        (Outcome::Ok, Some(&[][..]))
    );
    assert!(
        start.elapsed() < BROADCAST_DELAY,
        "a broadcast does not wait for a reply"
    );
    let r = m.transact(5, &read_status(), None).await.unwrap();
    assert_eq!(turns_of(r.reply.as_ref().unwrap()), 5);
    let (b, _) = peer.requests.recv().await.unwrap();
    assert_eq!(b, DriveRequest::SetAddress { address: 5 }.frame(0).unwrap());
    // Measured from before the broadcast left: the peer may read it late
    // on a loaded machine, never early.
    let (_, t_next) = peer.requests.recv().await.unwrap();
    assert!(t_next - start >= BROADCAST_DELAY, "{:?}", t_next - start);
}

#[tokio::test]
async fn a_byte_during_the_broadcast_turnaround_does_not_cut_it_short() {
    // Right after the broadcast, a byte of noise (or a drive that answered
    // a broadcast it should not have): the drives still get their whole
    // turnaround before the next request.
    let (path, mut peer, _) = start_peer(vec![
        Answer::Raw(vec![0x00], NOW),
        Answer::Reply {
            unit: 5,
            pdu: status_reply(5),
            delay: NOW,
        },
    ]);
    let mut s = settings();
    s.broadcast_delay = BROADCAST_DELAY;
    let mut m = master(&path, s).await;
    let set = DriveRequest::SetAddress { address: 5 }.pdu().unwrap();
    let start = Instant::now();
    m.transact(0, &set, None).await.unwrap();
    let r = m.transact(5, &read_status(), None).await.unwrap();
    assert_eq!(turns_of(r.reply.as_ref().unwrap()), 5);
    assert_eq!(r.stray_bytes, 1, "the noise was discarded");
    // Measured from before the broadcast left: the peer may read it late
    // on a loaded machine, never early.
    let _broadcast = peer.requests.recv().await.unwrap();
    let (_, t_next) = peer.requests.recv().await.unwrap();
    assert!(
        t_next - start >= BROADCAST_DELAY,
        "the next request came {:?} after the broadcast",
        t_next - start
    );
}

#[tokio::test]
async fn a_burst_of_noise_longer_than_any_frame_is_a_bad_reply_not_an_unplug() {
    // 1 KiB in one write, starting like a reply from unit 1 with a function
    // code whose length is unknown (framed by silence): more than the
    // master's buffer holds. It is a bad frame; the adapter is still there.
    let noise = [vec![0x01, 0x41], vec![0x5A; 1022]].concat();
    let (path, _peer, _) = start_peer(vec![
        Answer::Raw(noise, NOW),
        Answer::Reply {
            unit: 1,
            pdu: status_reply(8),
            delay: NOW,
        },
    ]);
    let mut m = master(&path, settings()).await;
    let r = m.transact(1, &read_status(), Some(1)).await.unwrap();
    assert_eq!((r.outcome, r.attempts), (Outcome::BadReply, 1), "{r:?}");
    // The port works on: the next request gets its reply.
    let r = m.transact(1, &read_status(), None).await.unwrap();
    assert_eq!(turns_of(r.reply.as_ref().unwrap()), 8);
}

#[tokio::test]
async fn a_closed_port_is_an_error_not_a_timeout() {
    let (mut ptm, slave) = SerialStream::pair().unwrap();
    let path = slave.name().unwrap();
    drop(slave);
    let mut m = master(&path, settings()).await;
    // The far end goes away (adapter unplugged).
    let _ = ptm.write_all(&[]).await;
    drop(ptm);
    let result = m.transact(1, &read_status(), None).await;
    // Found before anything was written: the request never left.
    match result {
        Err(failure) => assert!(!failure.request_sent(), "{failure}"),
        Ok(report) => panic!("a closed port answered {report:?}"),
    }
}

#[tokio::test]
async fn a_port_closed_after_the_request_left_says_it_was_sent() {
    let (mut ptm, slave) = SerialStream::pair().unwrap();
    let path = slave.name().unwrap();
    drop(slave);
    let mut m = master(&path, settings()).await;
    // The far end takes the request, then goes away before any reply.
    let hang_up = tokio::spawn(async move {
        let mut request = [0u8; 8];
        ptm.read_exact(&mut request).await.unwrap();
        drop(ptm);
        request
    });
    let result = m.transact(1, &read_status(), None).await;
    assert_eq!(
        hang_up.await.unwrap().to_vec(),
        DriveRequest::ReadStatus.frame(1).unwrap()
    );
    match result {
        Err(failure) => assert!(failure.request_sent(), "{failure}"),
        Ok(report) => panic!("a closed port answered {report:?}"),
    }
}

#[tokio::test]
async fn rts_direction_control_works_on_a_pty_and_kernel_mode_is_refused_clearly() {
    let (path, _peer, _) = start_peer(vec![Answer::Reply {
        unit: 1,
        pdu: status_reply(4),
        delay: NOW,
    }]);
    let mut s = settings();
    s.rs485 = Rs485Settings {
        direction: Direction::Rts,
        delay_before_send_us: 100,
        delay_after_send_us: 100,
        ..Rs485Settings::default()
    };
    // A pty has no modem lines: RTS control fails there, and says so.
    match port::open(&path, 115_200, &s.rs485) {
        Ok(p) => {
            let mut m = RtuMaster::new(p, s).unwrap();
            let r = m.transact(1, &read_status(), None).await.unwrap();
            assert_eq!(turns_of(r.reply.as_ref().unwrap()), 4);
        }
        Err(e) => assert!(e.to_string().contains(&path), "{e}"),
    }
    let kernel = Rs485Settings {
        direction: Direction::Kernel,
        ..Rs485Settings::default()
    };
    let (path, _peer2, _) = start_peer(vec![]);
    let err = port::open(&path, 115_200, &kernel).unwrap_err().to_string();
    assert!(err.contains("kernel's RS-485 mode"), "{err}");
}
