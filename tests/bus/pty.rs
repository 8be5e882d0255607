//! The bus engine (scheduler, queue, safe stops) against scripted peers on
//! real ptys: the failures the simulator cannot produce on purpose, such as
//! an adapter that goes away in the middle of a transaction.

use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::Duration;

use crate::support::eventually;
use crate::support::pty::pty;
use drivegate::bus::handle::{JobOptions, PortState};
use drivegate::bus::scheduler::{self, BusSettings};
use drivegate::bus::{BusError, BusHandle, Origin, Priority};
use drivegate::control::stop_action::{self, StopAction};
use drivegate::drive::DriveRequest;
use drivegate::modbus::rtu_frame::{self, FrameLength};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;

const LIMIT: Duration = Duration::from_secs(10);

/// What the peer does with one request frame.
enum Reply {
    /// Send these bytes back.
    Bytes(Vec<u8>),
    /// Say nothing.
    Nothing,
    /// Close the pty, as an unplugged adapter: the daemon's next read fails.
    HangUp,
}

/// The far end of a pty, answering each request with a script.
struct Peer {
    /// The pty the bus opens.
    path: String,
    /// Every request frame the peer received, in order.
    requests: mpsc::UnboundedReceiver<Vec<u8>>,
    _keep: OwnedFd,
}

/// A pty whose far end answers each whole request frame with `answer`.
fn start_peer(mut answer: impl FnMut(&[u8]) -> Reply + Send + 'static) -> Peer {
    let (mut ptm, path, keep) = pty();
    let (tx, requests) = mpsc::unbounded_channel();
    tokio::spawn(async move {
        let mut buf = Vec::new();
        let mut chunk = [0u8; 256];
        loop {
            let n = match ptm.read(&mut chunk).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            buf.extend_from_slice(&chunk[..n]);
            while let FrameLength::Known(len) = rtu_frame::request_length(&buf) {
                if buf.len() < len {
                    break;
                }
                let frame: Vec<u8> = buf.drain(..len).collect();
                let reply = answer(&frame);
                let _ = tx.send(frame);
                match reply {
                    Reply::Bytes(bytes) => ptm.write_all(&bytes).await.unwrap(),
                    Reply::Nothing => {}
                    Reply::HangUp => return,
                }
            }
        }
    });
    Peer {
        path,
        requests,
        _keep: keep,
    }
}

/// A bus on `path` with no polled drives: only the test's jobs go on the wire.
fn bus_on(path: &str) -> (BusHandle, JoinHandle<()>) {
    scheduler::spawn(BusSettings::new("pty", path, 115_200, vec![])).unwrap()
}

/// Waits for the port to open.
async fn port_up(bus: &BusHandle) {
    eventually(LIMIT, "the port to open", || {
        matches!(bus.port_state(), PortState::Up { .. }).then_some(())
    })
    .await;
}

/// Stops the bus and waits for its thread.
async fn stop(bus: &BusHandle, thread: JoinHandle<()>) {
    bus.stop();
    tokio::time::timeout(LIMIT, tokio::task::spawn_blocking(move || thread.join()))
        .await
        .expect("the bus thread stops")
        .unwrap()
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_port_failing_after_the_request_was_sent_leaves_the_outcome_unknown() {
    // The first write is echoed; at the second the adapter goes away once
    // the write has reached the drive, before its echo: the drive may be
    // running the new setpoint.
    let mut writes = 0;
    let mut peer = start_peer(move |frame| {
        writes += 1;
        if writes == 1 {
            Reply::Bytes(frame.to_vec())
        } else {
            Reply::HangUp
        }
    });
    let (bus, thread) = bus_on(&peer.path);
    port_up(&bus).await;
    let first = DriveRequest::Speed { rpm: 50 };
    bus.execute(1, &first, JobOptions::default()).await.unwrap();
    let write = DriveRequest::Speed { rpm: 100 };
    let err = bus
        .execute(1, &write, JobOptions::default())
        .await
        .unwrap_err();
    for expected in [&first, &write] {
        assert_eq!(
            tokio::time::timeout(LIMIT, peer.requests.recv())
                .await
                .unwrap(),
            Some(expected.frame(1).unwrap()),
            "the drive received {expected:?}"
        );
    }
    assert!(!err.not_sent(), "reported as never sent: {err}");
    assert!(
        matches!(&err, BusError::BusDownAfterSend { unit: 1, .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("may have carried it out"), "{err}");
    // The bus is down now, and says so to whoever comes next.
    eventually(LIMIT, "the bus to go down", || {
        matches!(bus.port_state(), PortState::Down { .. }).then_some(())
    })
    .await;
    let refused = bus
        .execute(1, &write, JobOptions::default())
        .await
        .unwrap_err();
    assert!(
        matches!(refused, BusError::BusDown { .. }) && refused.not_sent(),
        "{refused}"
    );
    stop(&bus, thread).await;
}

/// Points `link` at `target` in one step (a rename), as udev does for a
/// replugged adapter.
fn relink(link: &Path, target: &str) {
    let next = link.with_extension("next");
    let _ = std::fs::remove_file(&next);
    std::os::unix::fs::symlink(target, &next).unwrap();
    std::fs::rename(&next, link).unwrap();
}

/// An adapter that opens fine and fails at its first request, every time:
/// behind `link` there is always a fresh pty, and each one goes away as
/// soon as the bus writes to it (a replacement is linked first, so the
/// bus could reopen at once).
fn flaky_adapter(link: PathBuf, stop: CancellationToken) -> tokio::task::JoinHandle<u64> {
    /// The pty behind the link now.
    struct Plugged {
        ptm: SerialStream,
        _keep: OwnedFd,
    }
    fn plug_in(link: &Path) -> Plugged {
        let (ptm, path, keep) = pty();
        relink(link, &path);
        Plugged { ptm, _keep: keep }
    }
    tokio::spawn(async move {
        let mut plugged = plug_in(&link);
        let mut failed = 0;
        let mut bytes = [0u8; 64];
        loop {
            tokio::select! {
                read = plugged.ptm.read(&mut bytes) => match read {
                    Ok(n) if n > 0 => {}
                    _ => continue,
                },
                () = stop.cancelled() => return failed,
            }
            failed += 1;
            // Dropping the old far end is the adapter failing under the bus.
            plugged = plug_in(&link);
        }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_port_that_opens_and_fails_at_once_is_reopened_with_backoff() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyFLAKY");
    let stop_adapter = CancellationToken::new();
    let adapter = flaky_adapter(link.clone(), stop_adapter.clone());
    eventually(LIMIT, "the adapter's link", || link.exists().then_some(())).await;
    let mut settings = BusSettings::new(
        "flaky",
        &link.display().to_string(),
        115_200,
        vec![(1, Duration::ZERO)],
    );
    settings.reopen_backoff = (Duration::from_millis(50), Duration::from_millis(400));
    let (bus, thread) = scheduler::spawn(settings).unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stats = bus.stats();
    stop_adapter.cancel();
    let failed = adapter.await.unwrap();
    stop(&bus, thread).await;
    // Backing off 50, 100, 200, 400, 400 ... ms, 2 s hold about 7 reopens;
    // a bus thread that reopens at once does hundreds.
    assert!(
        (2..=12).contains(&stats.reopens),
        "{} reopens in 2 s ({failed} ptys failed under the bus): {stats:?}",
        stats.reopens
    );
    assert!(stats.port_errors <= 13, "{stats:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_job_accepted_while_the_bus_stops_is_answered() {
    // Silent drives: each emergency read takes its two attempts and guard
    // times (about 200 ms), long enough to submit more while it is on the wire.
    let mut peer = start_peer(|_| Reply::Nothing);
    let (bus, thread) = bus_on(&peer.path);
    port_up(&bus).await;
    let emergency = JobOptions::with_priority(Priority::Emergency);
    let read = DriveRequest::ReadStatus;
    let submit = |unit: u8| bus.submit(unit, read.pdu().unwrap(), emergency.clone());
    let on_wire = |unit: u8| read.frame(unit).unwrap();

    let first = submit(1).unwrap();
    assert_eq!(peer.requests.recv().await, Some(on_wire(1)));
    bus.stop();
    // Queued while the bus is stopping: the stop's last round sends it.
    let second = submit(2).unwrap();
    assert_eq!(peer.requests.recv().await, Some(on_wire(1)), "the retry");
    assert_eq!(peer.requests.recv().await, Some(on_wire(2)));
    // Submitted while that last round is on the wire: sent too, or refused
    // once the bus has taken its last job; either way answered.
    let third = submit(3);
    for (unit, rx) in [(1, Ok(first)), (2, Ok(second)), (3, third)] {
        let Ok(rx) = rx else { continue };
        let answer = tokio::time::timeout(LIMIT, rx)
            .await
            .unwrap_or_else(|_| panic!("the job to unit {unit} was never answered"));
        assert!(
            matches!(answer, Ok(Err(BusError::Timeout { .. }))),
            "unit {unit}: {answer:?}"
        );
    }
    stop(&bus, thread).await;
    // After the bus has stopped, nothing is taken, not even an emergency.
    let after = submit(4).unwrap_err();
    assert!(after.not_sent(), "{after}");
    assert!(after.to_string().contains("shutting down"), "{after}");
    assert!(
        !matches!(bus.port_state(), PortState::Up { .. }),
        "{:?}",
        bus.port_state()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_speed_with_the_mode_unknown_zeroes_both_setpoints() {
    // A drive whose status cannot be read (it answers the read with an
    // exception): its mode is unknown (the last poll's, or a lease's, may
    // be out of date). It may be in torque mode, where a zero speed
    // setpoint would leave it pushing.
    let mut peer = start_peer(|frame| match frame[1] {
        0x03 => Reply::Bytes(rtu_frame::encode(frame[0], &[0x83, 0x04])),
        _ => Reply::Bytes(frame.to_vec()),
    });
    let (bus, thread) = bus_on(&peer.path);
    port_up(&bus).await;
    let outcome = stop_action::stop_drive(&bus, 1, StopAction::ZeroSpeed, true, Origin::Internal)
        .await
        .unwrap();
    let speed = DriveRequest::Speed { rpm: 0 };
    let torque = DriveRequest::Torque { counts: 0 };
    // The frames as the drive saw them, a retry (a reply late on a loaded
    // machine) counted once: the read, then both writes.
    let expected: Vec<_> = [&DriveRequest::ReadStatus, &speed, &torque]
        .iter()
        .map(|request| request.frame(1).unwrap())
        .collect();
    let mut seen: Vec<Vec<u8>> = Vec::new();
    while seen.last() != expected.last() {
        let frame = tokio::time::timeout(LIMIT, peer.requests.recv())
            .await
            .unwrap_or_else(|_| panic!("only {seen:02x?} were sent, not {expected:02x?}"))
            .expect("the peer is running");
        if seen.last() != Some(&frame) {
            seen.push(frame);
        }
    }
    assert_eq!(seen, expected);
    assert_eq!((outcome.mode, outcome.moving), (None, true));
    // What was confirmed, for the audit: both writes, in order.
    assert_eq!(outcome.requests().collect::<Vec<_>>(), [&speed, &torque]);
    stop(&bus, thread).await;
}
