//! The simulator through its real pty, opened with tokio-serial as a bus
//! master opens it: raw request frames in, reply frames and their timing out.
//!
//! Timing assertions are lower bounds only (the model never answers early);
//! how much later than the theory a machine delivers is measured and printed,
//! not asserted.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly by design

use crate::support::bounded;
use crate::support::vectors::vectors;
use std::time::{Duration, Instant};

use drivegate::clock::PreciseTimer;
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest, Fault, Status};
use drivegate::modbus::crc::frame_crc_ok;
use drivegate::modbus::rtu_frame::{self, FrameLength, response_length};
use drivegate::modbus::timing::LineTiming;
use drivegate::sim::{FaultRates, SimConfig, SimError, SimHandle, SimStats, Simulator};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{SerialPortBuilderExt, SerialStream};

const BAUD: u32 = 115_200;

/// How long the master waits for a reply it expects. The simulator answers
/// within milliseconds, but on a thread of this process: on a loaded
/// machine it can wait 100 ms and more for a CPU.
const REPLY_WAIT: Duration = Duration::from_secs(1);

/// A bus master on the simulator's pty, keeping bytes that arrive early.
struct Master {
    port: SerialStream,
    line: LineTiming,
    pending: Vec<u8>,
    timer: PreciseTimer,
    /// Bytes dropped before a reply because no frame starts with them.
    skipped: usize,
}

/// One reply as the master saw it.
struct Reply {
    frame: Vec<u8>,
    first_byte: Instant,
    last_byte: Instant,
}

impl Master {
    fn open(handle: &SimHandle) -> Master {
        Master::open_at(handle, BAUD)
    }

    /// Opens the pty for a bus modelled at `baud`.
    fn open_at(handle: &SimHandle, baud: u32) -> Master {
        let path = handle.port_path().to_string_lossy().into_owned();
        Master {
            port: tokio_serial::new(path, baud).open_native_async().unwrap(),
            line: LineTiming::new_8n1(baud),
            pending: Vec::new(),
            timer: PreciseTimer::new().unwrap(),
            skipped: 0,
        }
    }

    async fn send(&mut self, frame: &[u8]) -> Instant {
        let sent = Instant::now();
        self.port.write_all(frame).await.unwrap();
        sent
    }

    /// Reads bytes until `until` (or `None` when none came).
    async fn read_until(&mut self, until: Instant) -> Option<Instant> {
        let mut chunk = [0u8; 256];
        let left = until.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, self.port.read(&mut chunk)).await {
            Ok(Ok(n)) if n > 0 => {
                self.pending.extend_from_slice(&chunk[..n]);
                Some(Instant::now())
            }
            Ok(Ok(_)) => panic!("the pty reported end of file"),
            Ok(Err(e)) => panic!("read failed: {e}"),
            Err(_) => None,
        }
    }

    /// Waits up to `wait` for one reply frame.
    async fn reply(&mut self, wait: Duration) -> Option<Reply> {
        let deadline = Instant::now() + wait;
        let mut first_byte = (!self.pending.is_empty()).then(Instant::now);
        let mut last_byte = first_byte;
        loop {
            if let FrameLength::Known(n) = response_length(&self.pending)
                && self.pending.len() >= n
            {
                let frame: Vec<u8> = self.pending.drain(..n).collect();
                return Some(Reply {
                    frame,
                    first_byte: first_byte?,
                    last_byte: last_byte?,
                });
            }
            let at = self.read_until(deadline).await?;
            first_byte.get_or_insert(at);
            last_byte = Some(at);
        }
    }

    /// Waits up to `wait` for a reply from `unit` (function 0x03), skipping
    /// bytes that cannot start it (noise).
    async fn reply_from(&mut self, unit: u8, wait: Duration) -> Option<Reply> {
        let deadline = Instant::now() + wait;
        loop {
            let starts = |p: &[u8]| p.len() < 2 || (p[0] == unit && (p[1] == 0x03 || p[1] == 0x83));
            while !self.pending.is_empty() && !starts(&self.pending) {
                self.pending.remove(0);
                self.skipped += 1;
            }
            if self.pending.len() >= 2 {
                return self
                    .reply(deadline.saturating_duration_since(Instant::now()))
                    .await;
            }
            self.read_until(deadline).await?;
        }
    }

    /// Waits the inter-frame silence after a reply's last byte, as a correct
    /// master does.
    async fn silence_after(&mut self, reply: &Reply) {
        self.timer
            .sleep_until(reply.last_byte + self.line.t3_5())
            .await
            .unwrap();
    }

    /// Sends a request and returns its reply, then keeps the silence.
    async fn transact(&mut self, frame: &[u8]) -> Option<Vec<u8>> {
        self.send(frame).await;
        let reply = self.reply(REPLY_WAIT).await?;
        self.silence_after(&reply).await;
        Some(reply.frame)
    }

    /// Returns the bytes that arrive until the line has been quiet for
    /// `quiet`, listening at least until `until`.
    async fn drain_until_quiet(&mut self, until: Instant, quiet: Duration) -> Vec<u8> {
        let mut deadline = until.max(Instant::now() + quiet);
        while let Some(at) = self.read_until(deadline).await {
            deadline = deadline.max(at + quiet);
        }
        std::mem::take(&mut self.pending)
    }
}

fn start(units: &[u8], turnaround_ms: f64) -> SimHandle {
    let mut config = SimConfig::for_units(units.iter().copied());
    config.turnaround_ms = turnaround_ms;
    Simulator::start(config).unwrap()
}

fn frame(unit: u8, request: DriveRequest) -> Vec<u8> {
    request.frame(unit).unwrap()
}

/// The status a reply frame carries.
fn status_of(reply: &[u8]) -> Status {
    let (_, pdu) = rtu_frame::decode(reply).unwrap();
    match DriveRequest::ReadStatus.parse_reply(pdu).unwrap() {
        DriveReply::Status(s) => s,
        other => panic!("not a status: {other:?}"),
    }
}

#[tokio::test]
async fn status_read_matches_the_drives_status() {
    bounded(Duration::from_secs(10), async {
        let handle = start(&[1, 2], 0.0);
        let mut master = Master::open(&handle);
        let reply = master
            .transact(&frame(2, DriveRequest::ReadStatus))
            .await
            .unwrap();
        assert_eq!(reply.len(), 19);
        assert_eq!(reply[..3], [2, 0x03, 0x0E]);
        let status = status_of(&reply);
        assert_eq!(status, handle.drive(2).unwrap().status);
        assert!(status.calibrated() && !status.active());
        assert_eq!((status.voltage_v, status.temperature_c), (24, 25));
    })
    .await;
}

#[tokio::test]
async fn every_golden_request_gets_the_manuals_reply() {
    bounded(Duration::from_secs(20), async {
        let all = vectors();
        let mut checked = 0;
        for (i, v) in all.iter().enumerate() {
            if !v.direction.starts_with("request") {
                continue;
            }
            // A fresh bus for each vector: an active, calibrated drive.
            let unit = if v.bytes[0] == 0 { 1 } else { v.bytes[0] };
            let handle = start(&[1, 7], 0.0);
            let mut master = Master::open(&handle);
            let activate = frame(unit, DriveRequest::Config(ConfigCommand::Activate));
            assert_eq!(master.transact(&activate).await, Some(activate.clone()));

            master.send(&v.bytes).await;
            let reply = master.reply(REPLY_WAIT).await.map(|r| r.frame);
            match v.direction.as_str() {
                "request+echo" => assert_eq!(reply.as_ref(), Some(&v.bytes), "{}", v.name),
                _ if v.name == "set_address_5" => {
                    assert_eq!(reply, None, "a broadcast gets no reply");
                    assert_eq!(handle.drive(5).unwrap().address, 5);
                }
                _ if v.name == "status_read" => {
                    let status = status_of(&reply.unwrap());
                    assert!(status.active());
                    assert_eq!(status, handle.drive(1).unwrap().status);
                }
                _ => {
                    // The acknowledgement follows its request in the file.
                    let ack = &all[i + 1];
                    assert_eq!(ack.direction, "response", "{}", v.name);
                    assert_eq!(
                        reply.as_ref(),
                        Some(&ack.bytes),
                        "{} -> {}",
                        v.name,
                        ack.name
                    );
                }
            }
            checked += 1;
        }
        assert_eq!(checked, 26);

        // exception_illegal_address: a read of the hole at 0x0004.
        let handle = start(&[1], 0.0);
        let mut master = Master::open(&handle);
        let read_hole = rtu_frame::encode(1, &[0x03, 0x00, 0x04, 0x00, 0x01]);
        let expected = &all
            .iter()
            .find(|v| v.name == "exception_illegal_address")
            .unwrap()
            .bytes;
        assert_eq!(master.transact(&read_hole).await.as_ref(), Some(expected));
        assert_eq!(handle.stats().exceptions, 1);
    })
    .await;
}

#[tokio::test]
async fn replies_respect_the_wire_time_the_silence_and_the_turnaround() {
    bounded(Duration::from_secs(10), async {
        let turnaround = Duration::from_micros(500);
        let handle = start(&[1], 0.5);
        let mut master = Master::open(&handle);
        let line = LineTiming::new_8n1(BAUD);
        let request = frame(1, DriveRequest::ReadStatus);
        let first_due = line.wire_time(8) + line.t3_5() + turnaround + line.wire_time(1);
        let last_due = line.wire_time(8) + line.t3_5() + turnaround + line.wire_time(19);
        let (mut late, mut spread) = (Vec::new(), Vec::new());
        for _ in 0..50 {
            let sent = master.send(&request).await;
            let reply = master.reply(REPLY_WAIT).await.unwrap();
            assert!(reply.first_byte - sent >= first_due, "first byte after {:?}", reply.first_byte - sent);
            assert!(reply.last_byte - sent >= last_due, "last byte after {:?}", reply.last_byte - sent);
            late.push(reply.last_byte - sent - last_due);
            spread.push(reply.last_byte - reply.first_byte);
            master.silence_after(&reply).await;
        }
        late.sort();
        spread.sort();
        eprintln!(
            "status reply complete {:?} after the request was written (theory {:?}); beyond theory: \
             median {:?}, max {:?}; first to last byte: median {:?} (theory {:?})",
            last_due + late[25],
            last_due,
            late[25],
            late[49],
            spread[25],
            line.wire_time(18)
        );
        assert_eq!(handle.stats().gap_violations, 0);
    })
    .await;
}

#[tokio::test]
async fn back_to_back_polls_run_at_the_lines_limit_not_faster() {
    bounded(Duration::from_secs(10), async {
        let handle = start(&[1], 0.0);
        let mut master = Master::open(&handle);
        let line = LineTiming::new_8n1(BAUD);
        let request = frame(1, DriveRequest::ReadStatus);
        let polls = 300;
        let started = Instant::now();
        for _ in 0..polls {
            assert!(master.transact(&request).await.is_some());
        }
        let per_poll = started.elapsed() / polls;
        let limit = line.transaction_time(8, 19, Duration::ZERO);
        eprintln!(
            "{polls} status polls: {per_poll:?} each, {:.0} polls/s (limit {limit:?}, {:.0}/s)",
            1.0 / per_poll.as_secs_f64(),
            1.0 / limit.as_secs_f64()
        );
        assert!(per_poll >= limit);
        let stats = handle.stats();
        assert_eq!(
            (stats.requests, stats.replies, stats.gap_violations),
            (300, 300, 0)
        );
    })
    .await;
}

#[tokio::test]
async fn gap_violations_are_counted_only_without_the_silence() {
    bounded(Duration::from_secs(20), async {
        let handle = start(&[1], 0.0);
        let mut master = Master::open(&handle);
        let request = frame(1, DriveRequest::ReadStatus);

        // A master that waits t3.5 after every reply never violates the gap.
        for _ in 0..20 {
            assert!(master.transact(&request).await.is_some());
        }
        assert_eq!(handle.stats().gap_violations, 0);

        // Two requests written back to back: the second arrives while the
        // first is still on the wire.
        let mut twice = request.clone();
        twice.extend_from_slice(&request);
        master.send(&twice).await;
        let first = master.reply(REPLY_WAIT).await.unwrap();
        let second = master.reply(REPLY_WAIT).await.unwrap();
        master.silence_after(&second).await;
        assert!(second.first_byte >= first.last_byte);
        assert_eq!(handle.stats().gap_violations, 1);

        assert_eq!(handle.stats().replies, 22);

        // A request sent as soon as the reply's last byte is in. At 600
        // baud t3.5 is 58 ms, so a busy machine does not hide the violation
        // (the simulator would have to be kept from reading the request
        // that long).
        let mut config = SimConfig::for_units([1]);
        config.baud = 600;
        let slow = Simulator::start(config).unwrap();
        let mut master = Master::open_at(&slow, 600);
        for _ in 0..7 {
            master.send(&request).await;
            master.reply(Duration::from_secs(2)).await.unwrap();
        }
        let violations = slow.stats().gap_violations;
        assert!(
            violations >= 5,
            "only {violations} of 6 immediate requests counted"
        );
    })
    .await;
}

#[tokio::test]
async fn bad_crc_unknown_units_and_unknown_functions() {
    bounded(Duration::from_secs(10), async {
        let handle = start(&[1], 0.0);
        let mut master = Master::open(&handle);
        let mut bad = frame(1, DriveRequest::ReadStatus);
        bad[6] ^= 0x01;
        master.send(&bad).await;
        assert!(master.reply(Duration::from_millis(20)).await.is_none());
        master.send(&frame(9, DriveRequest::ReadStatus)).await;
        assert!(master.reply(Duration::from_millis(20)).await.is_none());
        // 0x41 has no known length: framed by silence, refused with 0x01.
        let custom = rtu_frame::encode(1, &[0x41, 0x01, 0x02]);
        let reply = master.transact(&custom).await.unwrap();
        assert_eq!(reply, rtu_frame::encode(1, &[0xC1, 0x01]));
        // Input registers (0x04): the drive has none.
        let reply = master
            .transact(&rtu_frame::encode(1, &[0x04, 0, 0xC0, 0, 7]))
            .await
            .unwrap();
        assert_eq!(reply, rtu_frame::encode(1, &[0x84, 0x01]));
        let stats = handle.stats();
        assert_eq!(
            (stats.bad_crc_requests, stats.unanswered, stats.exceptions),
            (1, 1, 2)
        );
    })
    .await;
}

/// What the master saw of one poll under fault injection, leaving out
/// lateness (a loaded machine can delay any reply).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Seen {
    Answer { corrupted: bool, noise: usize },
    Nothing,
}

/// One run of the fault suite as the master saw it.
struct FaultyRun {
    seen: Vec<Seen>,
    late: u64,
    silent_answers: usize,
    stats: SimStats,
}

/// 200 polls of unit 1 and 10 of the silent unit 2, classified as the master
/// sees them.
async fn faulty_run(seed: u64) -> FaultyRun {
    let mut config = SimConfig::for_units([1, 2]);
    config.turnaround_ms = 0.0;
    config.seed = seed;
    config.faults = FaultRates {
        drop_rate: 0.1,
        crc_error_rate: 0.1,
        late_rate: 0.1,
        late_ms: 150.0,
        noise_rate: 0.1,
        silent_units: vec![2],
    };
    let handle = Simulator::start(config).unwrap();
    let mut master = Master::open(&handle);
    let line = master.line;
    let mut run = FaultyRun {
        seen: Vec::new(),
        late: 0,
        silent_answers: 0,
        stats: SimStats::default(),
    };
    for i in 0..210 {
        let unit = if i % 21 == 20 { 2 } else { 1 };
        let sent = master.send(&frame(unit, DriveRequest::ReadStatus)).await;
        // Long enough for a late reply held up by a loaded machine too.
        let reply = master.reply_from(unit, Duration::from_millis(400)).await;
        // Noise that came after the last poll's listening window.
        let stray = std::mem::take(&mut master.skipped);
        if let Some(Seen::Answer { noise, .. }) = run.seen.last_mut() {
            *noise += stray;
        }
        if unit == 2 {
            run.silent_answers += usize::from(reply.is_some());
            continue;
        }
        let Some(reply) = reply else {
            run.seen.push(Seen::Nothing);
            continue;
        };
        // Late replies come 150 ms late, the others within 5 ms (or as late
        // as the machine holds the simulator up: those are counted late too).
        if reply.last_byte - sent > Duration::from_millis(75) {
            run.late += 1;
        }
        // Noise comes about t3.5 after the reply: listen until the line has
        // been quiet a while after that.
        let earliest = reply.last_byte + line.t3_5() + line.wire_time(4);
        let noise = master
            .drain_until_quiet(earliest, Duration::from_millis(4))
            .await
            .len();
        run.seen.push(Seen::Answer {
            corrupted: !frame_crc_ok(&reply.frame),
            noise,
        });
    }
    run.stats = handle.stats();
    run
}

#[tokio::test]
async fn fault_injection_meets_its_rates_and_repeats_with_the_seed() {
    bounded(Duration::from_secs(45), async {
        // Each run on its own thread, so one cannot delay the other's reads.
        let run = |seed| {
            tokio::task::spawn_blocking(move || {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .unwrap();
                runtime.block_on(faulty_run(seed))
            })
        };
        let (a, b) = tokio::join!(run(42), run(42));
        let (a, b) = (a.unwrap(), b.unwrap());
        // Which polls were dropped or corrupted is the seed's alone; which
        // poll a noise burst is counted with is the machine's too (a loaded
        // one can hold a burst past its poll's window), so noise is
        // compared as counts below.
        let faults = |run: &FaultyRun| {
            run.seen
                .iter()
                .map(|s| match s {
                    Seen::Answer { corrupted, .. } => Some(*corrupted),
                    Seen::Nothing => None,
                })
                .collect::<Vec<_>>()
        };
        assert_eq!(faults(&a), faults(&b), "same seed, same faults");
        assert_eq!(a.stats, b.stats, "same seed, same counters");

        assert_eq!(a.silent_answers, 0, "a silent unit never answers");
        let count = |p: &dyn Fn(&Seen) -> bool| a.seen.iter().filter(|s| p(s)).count() as u64;
        let dropped = count(&|s| *s == Seen::Nothing);
        let corrupted = count(&|s| {
            matches!(
                s,
                Seen::Answer {
                    corrupted: true,
                    ..
                }
            )
        });
        let noisy = count(&|s| matches!(s, Seen::Answer { noise, .. } if *noise > 0));
        eprintln!(
            "200 polls: {dropped} dropped, {corrupted} bad CRC, {} late, {noisy} with noise",
            a.late
        );
        // 10 % each (the last three of the 90 % not dropped), seed 42.
        for (what, n) in [
            ("dropped", dropped),
            ("corrupted", corrupted),
            ("late", a.late),
            ("noisy", noisy),
        ] {
            assert!((8..=36).contains(&n), "{what}: {n} of 200");
        }
        // The master saw what the simulator counted; a stalled machine can
        // only make more replies look late (up to 6 % of the polls on a
        // machine loaded twenty times over).
        let s = a.stats;
        assert_eq!((s.dropped, s.corrupted), (dropped, corrupted));
        // Every burst is seen, two may fall in one poll's window.
        assert!(
            noisy <= s.noise_bursts && noisy * 5 >= s.noise_bursts * 4,
            "{noisy} polls with noise, {} bursts sent",
            s.noise_bursts
        );
        assert!(
            a.late >= s.late && a.late <= s.late + 12,
            "{} late seen, {} sent",
            a.late,
            s.late
        );
        assert_eq!(s.unanswered, 10);
        assert!(
            a.seen
                .iter()
                .all(|s| !matches!(s, Seen::Answer { noise, .. } if *noise > 4))
        );
    })
    .await;
}

#[tokio::test]
async fn broadcast_address_setting_readdresses_the_drive() {
    bounded(Duration::from_secs(10), async {
        let handle = start(&[1], 0.0);
        let mut master = Master::open(&handle);
        master
            .send(&frame(0, DriveRequest::SetAddress { address: 5 }))
            .await;
        assert!(master.reply(Duration::from_millis(20)).await.is_none());
        assert!(
            master
                .transact(&frame(1, DriveRequest::ReadStatus))
                .await
                .is_none()
        );
        let reply = master
            .transact(&frame(5, DriveRequest::ReadStatus))
            .await
            .unwrap();
        assert_eq!(reply[0], 5);
        let stats = handle.stats();
        assert_eq!(
            (stats.broadcasts, stats.unanswered, stats.replies),
            (1, 1, 1)
        );
        // Kept over power loss.
        handle.power_cycle(5).unwrap();
        assert_eq!(handle.drive(5).unwrap().flash.address, 5);
    })
    .await;
}

#[tokio::test]
async fn power_cycle_silences_the_drive_then_it_returns_with_saved_values() {
    bounded(Duration::from_secs(10), async {
        let mut config = SimConfig::for_units([1]);
        config.reboot_ms = 100.0;
        let handle = Simulator::start(config).unwrap();
        let mut master = Master::open(&handle);
        let inertia_saved = DriveRequest::LoadInertia {
            ratio: 10,
            save: true,
        };
        let protection_unsaved = DriveRequest::OverCurrent {
            limit_counts: 128,
            stall_ms: 500,
            save: false,
        };
        for req in [inertia_saved, protection_unsaved] {
            assert!(master.transact(&frame(1, req)).await.is_some());
        }
        let read = |address: u16, count: u16| {
            let mut pdu = vec![0x03];
            pdu.extend_from_slice(&address.to_be_bytes());
            pdu.extend_from_slice(&count.to_be_bytes());
            rtu_frame::encode(1, &pdu)
        };
        let reply = master.transact(&read(0x000C, 2)).await.unwrap();
        assert_eq!(reply[3..7], [0, 128, 0x01, 0xF4]);

        let cut = Instant::now();
        handle.power_cycle(1).unwrap();
        let status = frame(1, DriveRequest::ReadStatus);
        assert!(master.transact(&status).await.is_none(), "silent while off");
        let back = loop {
            if master.transact(&status).await.is_some() {
                break Instant::now();
            }
            assert!(
                cut.elapsed() < Duration::from_secs(5),
                "the drive never came back"
            );
        };
        assert!(
            back - cut >= Duration::from_millis(100),
            "back after {:?}",
            back - cut
        );
        // Saved inertia kept; unsaved protection back to the factory values.
        let reply = master.transact(&read(0x0024, 1)).await.unwrap();
        assert_eq!(reply[3..5], [0, 10]);
        let reply = master.transact(&read(0x000C, 2)).await.unwrap();
        assert_eq!(
            reply[3..7],
            [0x06, 0x00, 0x0B, 0xB8],
            "1536 counts, 3000 ms"
        );
    })
    .await;
}

#[tokio::test]
async fn dropping_the_handle_unplugs_the_bus() {
    bounded(Duration::from_secs(10), async {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyDRIVES");
        std::fs::write(&link, b"not a link").unwrap();
        let mut handle = start(&[1], 0.0);
        assert!(
            handle.link_at(&link).is_err(),
            "a real file is never replaced"
        );
        std::fs::remove_file(&link).unwrap();
        std::os::unix::fs::symlink("/dev/null", &link).unwrap();
        handle.link_at(&link).unwrap();
        assert_eq!(std::fs::read_link(&link).unwrap(), handle.port_path());

        let mut port = tokio_serial::new(link.to_string_lossy(), BAUD)
            .open_native_async()
            .unwrap();
        port.write_all(&frame(1, DriveRequest::ReadStatus))
            .await
            .unwrap();
        let mut reply = [0u8; 19];
        port.read_exact(&mut reply).await.unwrap();
        assert_eq!(status_of(&reply), handle.drive(1).unwrap().status);

        drop(handle);
        assert!(
            !link.exists() && std::fs::symlink_metadata(&link).is_err(),
            "the link is removed"
        );
        let mut buf = [0u8; 8];
        let read = tokio::time::timeout(Duration::from_secs(2), port.read(&mut buf)).await;
        match read {
            Ok(Ok(0)) | Ok(Err(_)) => {}
            other => panic!("the master still reads from an unplugged bus: {other:?}"),
        }
    })
    .await;
}

#[tokio::test]
async fn handle_controls_show_in_the_status_on_the_wire() {
    bounded(Duration::from_secs(10), async {
        let handle = start(&[1, 2], 0.0);
        let mut master = Master::open(&handle);
        let status = |unit| frame(unit, DriveRequest::ReadStatus);
        let fault_reset = frame(1, DriveRequest::Config(ConfigCommand::FaultReset));

        handle.set_supply_voltage(1, 17.0).unwrap();
        handle.set_ambient_temperature(2, 40.0).unwrap();
        tokio::time::sleep(Duration::from_millis(5)).await;
        let s = status_of(&master.transact(&status(1)).await.unwrap());
        assert_eq!((s.voltage_v, s.fault()), (17, Fault::UnderVoltage));
        // The drive warms towards a new ambient with a minute's time constant.
        let s = status_of(&master.transact(&status(2)).await.unwrap());
        assert_eq!((s.temperature_c, s.fault()), (25, Fault::None));
        let view = handle.drive(2).unwrap();
        assert!(view.environment.ambient == 40.0 && view.temperature_c > 25.0);
        handle.set_supply_voltage(1, 24.0).unwrap();
        master.transact(&fault_reset).await.unwrap();

        handle.inject_fault(1, Fault::PowerStage).unwrap();
        master.transact(&fault_reset).await.unwrap();
        let s = status_of(&master.transact(&status(1)).await.unwrap());
        assert_eq!(s.fault(), Fault::PowerStage, "still injected");
        handle.clear_fault(1).unwrap();
        master.transact(&fault_reset).await.unwrap();
        let s = status_of(&master.transact(&status(1)).await.unwrap());
        assert_eq!(s.fault(), Fault::None);

        // A load on a free shaft turns it backwards.
        handle.set_load_torque(2, 0.5).unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
        let s = status_of(&master.transact(&status(2)).await.unwrap());
        assert!(s.speed_rpm < 0, "{s:?}");

        handle.set_silent(2, true);
        assert!(master.transact(&status(2)).await.is_none());
        handle.set_silent(2, false);
        assert!(master.transact(&status(2)).await.is_some());

        assert_eq!(
            handle
                .drives()
                .iter()
                .map(|d| d.address)
                .collect::<Vec<_>>(),
            [1, 2]
        );
        assert!(matches!(
            handle.inject_fault(9, Fault::Encoder),
            Err(SimError::UnknownUnit(9))
        ));
        assert!(handle.set_supply_voltage(1, f64::NAN).is_err());
        assert!(
            handle
                .set_fault_rates(FaultRates {
                    drop_rate: 1.5,
                    ..FaultRates::default()
                })
                .is_err()
        );
        handle
            .set_fault_rates(FaultRates {
                drop_rate: 1.0,
                ..FaultRates::default()
            })
            .unwrap();
        assert!(master.transact(&status(1)).await.is_none());
        assert_eq!(handle.fault_rates().drop_rate, 1.0);
    })
    .await;
}

#[tokio::test]
async fn the_daemons_simulator_gives_up_a_reply_once_the_master_has_spoken_again() {
    bounded(Duration::from_secs(20), async {
        // Drives answering in 300 ms, and the limit of the daemon's own
        // simulator: a master that gave up waiting (as a learned timeout
        // does, far sooner than the simulator's limit) and sent another
        // request must not get the first reply across it.
        let mut config = SimConfig::for_units([1, 2]);
        config.turnaround_ms = 300.0;
        config.max_lag = Some(Duration::from_millis(250));
        let handle = Simulator::start(config).unwrap();
        let mut master = Master::open(&handle);
        master.send(&frame(1, DriveRequest::ReadStatus)).await;
        // Well after the first request's end and t3.5, long before its
        // reply is due.
        tokio::time::sleep(Duration::from_millis(30)).await;
        master.send(&frame(2, DriveRequest::ReadStatus)).await;
        // The one reply is the second request's.
        let reply = master.reply(Duration::from_secs(3)).await.unwrap();
        assert_eq!(reply.frame[0], 2, "{:02x?}", reply.frame);
        master.silence_after(&reply).await;
        assert!(master.reply(Duration::from_millis(500)).await.is_none());
        let stats = handle.stats();
        assert_eq!(
            (
                stats.requests,
                stats.replies,
                stats.stalled,
                stats.gap_violations
            ),
            (2, 1, 1, 0),
            "{stats}"
        );
    })
    .await;
}
