//! The bus engine against the built-in simulator through a real pty:
//! polling, commands, priorities, offline drives, stale jobs, a full queue,
//! injected wire faults, an adapter unplugged and plugged back, and the
//! safe stop of every drive at shutdown whatever the queue limits.

use std::time::Duration;

use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::cache::Link;
use drivegate::bus::handle::{JobOptions, PortState};
use drivegate::bus::stats::Outcome;
use drivegate::bus::{BusError, BusEvent, SourceId};
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest};
use drivegate::plant::SimRef;
use drivegate::sim::{SimConfig, Simulator};

const LIMIT: Duration = Duration::from_secs(10);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drives_are_polled_and_commands_confirmed() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let (drive, bus) = d.plant.drive("conveyor").unwrap();
    let unit = drive.unit;
    for request in [
        DriveRequest::Config(ConfigCommand::Activate),
        DriveRequest::Config(ConfigCommand::SpeedMode),
        DriveRequest::Speed { rpm: 100 },
    ] {
        let reply = bus
            .execute(unit, &request, JobOptions::default())
            .await
            .unwrap();
        assert_eq!(reply, DriveReply::Confirmed, "{request:?}");
    }
    // The polled status follows the drive up to speed.
    let status = eventually(LIMIT, "speed near 100 rpm", || {
        bus.drive(unit)
            .and_then(|s| s.status)
            .filter(|s| (s.speed_rpm - 100).abs() <= 2)
    })
    .await;
    assert!(status.active());
    assert_eq!(d.sim().drive(unit).unwrap().setpoints.speed_rpm, 100);
    // Every drive has been polled and is online.
    for snapshot in bus.drives() {
        assert_eq!(snapshot.link, Link::Online, "{snapshot:?}");
        assert!(snapshot.seen_at.is_some());
    }
    let stats = bus.stats();
    assert!(stats.polls >= 4 && stats.poll_failures == 0, "{stats:?}");
    assert_eq!(stats.count(Outcome::Ok), stats.on_wire());
    assert_eq!(d.sim().stats().gap_violations, 0);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn polling_is_round_robin() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let bus = &d.plant.buses()[0].handle;
    let mut events = bus.subscribe();
    let mut order = Vec::new();
    while order.len() < 24 {
        let event = tokio::time::timeout(LIMIT, events.recv())
            .await
            .unwrap()
            .unwrap();
        if let BusEvent::Status { unit, .. } = event {
            order.push(unit);
        }
    }
    // Each window of four consecutive polls covers the four drives.
    for window in order.windows(4) {
        let mut w = window.to_vec();
        w.sort();
        assert_eq!(w, vec![1, 2, 3, 4], "order {order:?}");
    }
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_emergency_brake_overtakes_queued_commands() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let bus = &d.plant.buses()[0].handle;
    let source = SourceId::new_unique();
    let write = DriveRequest::Rs485Control { enabled: true }.pdu().unwrap();
    let queued: Vec<_> = (0..12)
        .map(|_| {
            bus.submit(1, write.clone(), JobOptions::from_source(source))
                .unwrap()
        })
        .collect();
    let brake = DriveRequest::Config(ConfigCommand::EmergencyBrake);
    bus.execute(2, &brake, JobOptions::default()).await.unwrap();
    // When the brake is confirmed, at most the command that was on the wire
    // (and one picked in the same instant) has finished.
    let mut waiting = Vec::new();
    let mut done = 0;
    for mut rx in queued {
        match rx.try_recv() {
            Ok(result) => {
                result.unwrap();
                done += 1;
            }
            // Still queued: answered after the brake (a receiver that has
            // given its answer, or its sender's end, is not asked again).
            Err(tokio::sync::oneshot::error::TryRecvError::Empty) => waiting.push(rx),
            Err(closed) => panic!("a queued command was never answered: {closed}"),
        }
    }
    assert!(done <= 2, "{done} queued commands went before the brake");
    for rx in waiting {
        if let Ok(result) = tokio::time::timeout(LIMIT, rx).await.unwrap() {
            result.unwrap();
        }
    }
    assert!(d.sim().drive(2).unwrap().braking);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_drive_goes_offline_backs_off_and_comes_back() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let bus = &d.plant.buses()[0].handle;
    d.sim().set_silent(2, true);
    eventually(LIMIT, "drive 2 offline", || {
        bus.drive(2).filter(|s| s.link == Link::Offline)
    })
    .await;
    // While it is offline it costs little: while the others are polled 30
    // times, at most one timed-out probe per backoff period (2 s by default)
    // that passed, so a loaded machine that stretches the polls is allowed
    // the probes its extra time brings, and no more.
    let before = bus.stats();
    let mut events = bus.subscribe();
    let start = tokio::time::Instant::now();
    let mut others = 0;
    while others < 30 {
        match tokio::time::timeout(LIMIT, events.recv()).await {
            Ok(Ok(BusEvent::Status { unit, .. })) => {
                assert_ne!(unit, 2);
                others += 1;
            }
            Ok(Ok(_)) | Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => {}
            other => panic!("the bus's events ended: {other:?}"),
        }
    }
    let elapsed = start.elapsed();
    let after = bus.stats();
    let timeouts = after.count(Outcome::Timeout) - before.count(Outcome::Timeout);
    let allowed = 1 + (elapsed.as_secs_f64() / 2.0) as u64;
    assert!(
        timeouts <= allowed,
        "{timeouts} probes of an offline drive while the others were polled 30 times in {elapsed:?}"
    );
    // A command to the offline drive gets one attempt and a clear error.
    let err = bus
        .execute(2, &DriveRequest::ReadStatus, JobOptions::default())
        .await
        .unwrap_err();
    assert!(
        matches!(
            err,
            BusError::Timeout {
                unit: 2,
                attempts: 1,
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("did not answer"), "{err}");
    // It answers again: it is back online after its backoff.
    d.sim().set_silent(2, false);
    eventually(LIMIT, "drive 2 online again", || {
        bus.drive(2).filter(|s| s.link == Link::Online)
    })
    .await;
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_whose_caller_left_never_reach_the_wire() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let bus = &d.plant.buses()[0].handle;
    let source = SourceId::new_unique();
    let write = DriveRequest::Rs485Control { enabled: true }.pdu().unwrap();
    let before = bus.stats().count(Outcome::Dropped);
    for _ in 0..40 {
        // The receiver is dropped at once: the caller has gone.
        drop(
            bus.submit(3, write.clone(), JobOptions::from_source(source))
                .unwrap(),
        );
    }
    eventually(LIMIT, "the queue to drain", || {
        (bus.queue_depths()[1] == 0).then_some(())
    })
    .await;
    let dropped = bus.stats().count(Outcome::Dropped) - before;
    // At most the one picked before its receiver was dropped went out.
    assert!(dropped >= 39, "{dropped} of 40 abandoned jobs dropped");
    let writes = bus
        .stats()
        .transactions
        .get(&(0x06, Outcome::Ok))
        .copied()
        .unwrap_or(0);
    assert!(writes <= 1, "{writes} abandoned writes reached the wire");

    // A deadline that passes in the queue: refused unsent, with the wait.
    let options = JobOptions {
        queue_timeout: Some(Duration::ZERO),
        ..JobOptions::default()
    };
    let err = bus
        .execute(3, &DriveRequest::ReadStatus, options)
        .await
        .unwrap_err();
    assert!(
        matches!(err, BusError::Expired { .. }) && err.not_sent(),
        "{err}"
    );
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_says_busy() {
    let config = ConfigBuilder::four_drives()
        .with_bus("sim", |b| {
            b.keys("queue_capacity = 4\nqueue_per_client = 4")
        })
        .toml();
    let d = TestDaemon::start(&config).await;
    let bus = &d.plant.buses()[0].handle;
    let write = DriveRequest::Rs485Control { enabled: true }.pdu().unwrap();
    let mut accepted = Vec::new();
    let mut busy = None;
    for _ in 0..20 {
        match bus.submit(1, write.clone(), JobOptions::default()) {
            Ok(rx) => accepted.push(rx),
            Err(e) => {
                busy = Some(e);
                break;
            }
        }
    }
    let busy = busy.expect("the queue filled up");
    assert!(matches!(busy, BusError::Busy { capacity: 4, .. }), "{busy}");
    assert!(busy.to_string().contains("busy"), "{busy}");
    // What was accepted is still carried out and confirmed.
    for rx in accepted {
        let exchange = tokio::time::timeout(LIMIT, rx)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(exchange.reply, write);
    }
    assert!(bus.stats().busy_rejections >= 1);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn injected_faults_never_deliver_a_reply_to_the_wrong_request() {
    // 5 % dropped, 5 % corrupted, 5 % late (250 ms: past the 100 ms
    // timeout, well inside the 350 ms guard), 5 % noise after replies. The
    // margins of 150 and 200 ms are for a loaded machine, which can hold
    // the simulator up: a reply it makes late fails its attempt (timeout,
    // bad reply), never delivers another request's value, and the late
    // bytes never meet the next request on the wire.
    let config = ConfigBuilder::four_drives()
        .with_bus("sim", |b| {
            b.timing(100, 350).sim_faults(
                "drop_rate = 0.05\ncrc_error_rate = 0.05\nlate_rate = 0.05\nlate_ms = 250\nnoise_rate = 0.05",
            )
        })
        .toml();
    let d = TestDaemon::start(&config).await;
    let bus = &d.plant.buses()[0].handle;
    let (mut confirmed, mut failed) = (0, 0);
    // Each fault costs about half a second of bus time: 100 rounds.
    for i in 0..100u32 {
        let unit = (i % 4) as u8 + 1;
        // Every write is unique, every read must return what was written.
        let alpha = 100_000 + i * 17 + u32::from(unit);
        let write = DriveRequest::SpeedRamp { alpha, save: false };
        match bus.execute(unit, &write, JobOptions::default()).await {
            Ok(reply) => assert_eq!(reply, DriveReply::Confirmed),
            Err(e) => {
                assert!(
                    matches!(e, BusError::Timeout { .. } | BusError::BadReply { .. }),
                    "{e}"
                );
                failed += 1;
                continue;
            }
        }
        // Read SPEED_TD_R_HIGH and _LOW back (two registers from 0x0018).
        match bus
            .transact(
                unit,
                vec![0x03, 0x00, 0x18, 0x00, 0x02],
                JobOptions::default(),
            )
            .await
        {
            Ok(exchange) => {
                let r = exchange.reply;
                assert_eq!(r.len(), 6, "{r:?}");
                let got = u32::from_be_bytes([r[2], r[3], r[4], r[5]]);
                assert_eq!(got, alpha, "unit {unit} read back another request's value");
                assert_eq!(d.sim().drive(unit).unwrap().settings.speed_alpha, alpha);
                confirmed += 1;
            }
            Err(e) => {
                assert!(
                    matches!(e, BusError::Timeout { .. } | BusError::BadReply { .. }),
                    "{e}"
                );
                failed += 1;
            }
        }
    }
    // With one retry, a 20 % fault rate leaves a few percent failing twice.
    assert!(confirmed >= 75, "{confirmed} confirmed, {failed} failed");
    let stats = bus.stats();
    let sim = d.sim().stats();
    assert!(
        sim.dropped > 0 && sim.corrupted > 0 && sim.late > 0 && sim.noise_bursts > 0,
        "{sim:?}"
    );
    assert!(
        stats.count(Outcome::Ok) > 0 && stats.retries > 0,
        "{stats:?}"
    );
    assert!(
        stats.stray_bytes > 0,
        "noise and late replies are counted as stray bytes"
    );
    assert_eq!(sim.gap_violations, 0);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unplugged_adapter_marks_the_bus_down_and_it_reconnects() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyDRIVES");
    let mut sim = Simulator::start(SimConfig::for_units(1..=2)).unwrap();
    sim.link_at(&link).unwrap();
    let config = format!(
        r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
enabled = false
[[bus]]
name = "line1"
port = "{}"
[[bus.drive]]
unit = 1
name = "a"
[[bus.drive]]
unit = 2
name = "b"
"#,
        link.display()
    );
    let d = TestDaemon::start(&config).await;
    let bus = d.plant.buses()[0].handle.clone();
    let mut events = bus.subscribe();

    // Unplug: the pty disappears.
    drop(sim);
    eventually(LIMIT, "the bus to go down", || {
        matches!(bus.port_state(), PortState::Down { .. }).then_some(())
    })
    .await;
    let err = bus
        .execute(1, &DriveRequest::ReadStatus, JobOptions::default())
        .await
        .unwrap_err();
    assert!(matches!(err, BusError::BusDown { .. }), "{err}");

    // Plug back in: a new pty at the same path.
    let mut sim = Simulator::start(SimConfig::for_units(1..=2)).unwrap();
    sim.link_at(&link).unwrap();
    let came_back = tokio::time::timeout(LIMIT, async {
        while !matches!(bus.port_state(), PortState::Up { .. }) {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert!(
        came_back.is_ok(),
        "the bus did not come back: {:?} {:?}",
        bus.port_state(),
        bus.stats().last_port_error
    );
    let reply = bus
        .execute(1, &DriveRequest::ReadStatus, JobOptions::default())
        .await
        .unwrap();
    assert!(matches!(reply, DriveReply::Status(_)));
    let stats = bus.stats();
    assert!(
        stats.reopens >= 1 && stats.port_open && stats.port_errors >= 1,
        "{stats:?}"
    );
    let mut saw = (false, false);
    while let Ok(event) = events.try_recv() {
        match event {
            BusEvent::BusDown { .. } => saw.0 = true,
            BusEvent::BusUp { .. } => saw.1 = true,
            _ => {}
        }
    }
    assert_eq!(saw, (true, true), "bus down and up events");
    d.stop().await;
    drop(sim);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn address_setting_is_a_broadcast() {
    let mut config = SimConfig::for_units([1]);
    config.turnaround_ms = 0.0;
    let sim = Simulator::start(config).unwrap();
    let toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n[[bus]]\nname = \"b\"\nport = \"{}\"\n[[bus.drive]]\nunit = 1\nname = \"only\"\n",
        sim.port_path().display()
    );
    let d = TestDaemon::start(&toml).await;
    let bus = &d.plant.buses()[0].handle;
    let reply = bus
        .execute(
            1,
            &DriveRequest::SetAddress { address: 9 },
            JobOptions::default(),
        )
        .await
        .unwrap();
    assert_eq!(reply, DriveReply::None);
    let reply = bus
        .execute(9, &DriveRequest::ReadStatus, JobOptions::default())
        .await
        .unwrap();
    assert!(matches!(reply, DriveReply::Status(_)));
    assert_eq!(sim.stats().broadcasts, 1);
    assert_eq!(sim.drive(9).unwrap().address, 9);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn several_buses_each_have_their_own_scheduler() {
    let two = ConfigBuilder::four_drives()
        .bus("second", |b| b.drive(1, "press").drive(2, "saw"))
        .toml();
    let d = TestDaemon::start(&two).await;
    assert_eq!(d.plant.buses().len(), 2);
    // The same unit on two buses is two drives, found by name.
    let (press, press_bus) = d.plant.drive("press").unwrap();
    let (conveyor, conveyor_bus) = d.plant.drive("conveyor").unwrap();
    assert_eq!((press.unit, conveyor.unit), (1, 1));
    assert_ne!(press_bus.name(), conveyor_bus.name());
    // With several buses a bare unit number is ambiguous.
    assert!(d.plant.drive("1").is_err());
    press_bus
        .execute(
            1,
            &DriveRequest::Config(ConfigCommand::Activate),
            JobOptions::default(),
        )
        .await
        .unwrap();
    let second_sim = SimRef::of(d.plant.buses()[1].clone()).unwrap();
    assert!(second_sim.drive(1).unwrap().active);
    assert!(
        !d.sim().drive(1).unwrap().active,
        "the first bus's unit 1 was not touched"
    );
    // Both buses poll at the same time, each on its own thread.
    for bus in d.plant.buses() {
        assert!(bus.handle.drives().iter().all(|s| s.link == Link::Online));
    }
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_stops_every_drive_even_beyond_the_queue_limits() {
    // Four moving drives, but a queue that takes one job per source and two
    // per class: the safe stops of all four go at once from the daemon
    // itself, and none of them may be refused as busy.
    let config = ConfigBuilder::four_drives()
        .with_bus("sim", |b| {
            b.keys("queue_capacity = 2\nqueue_per_client = 1")
        })
        .toml();
    let d = TestDaemon::start(&config).await;
    let bus = d.plant.buses()[0].handle.clone();
    for unit in 1..=4 {
        for request in [
            DriveRequest::Config(ConfigCommand::Activate),
            DriveRequest::Config(ConfigCommand::SpeedMode),
            DriveRequest::Speed { rpm: 100 },
        ] {
            bus.execute(unit, &request, JobOptions::default())
                .await
                .unwrap();
        }
    }
    for unit in 1..=4 {
        eventually(LIMIT, "every drive turning", || {
            bus.drive(unit)
                .and_then(|s| s.status)
                .filter(|s| s.speed_rpm != 0)
        })
        .await;
    }
    let plant = d.plant.clone();
    d.stop().await;
    let sim = SimRef::of(plant.buses()[0].clone()).unwrap();
    for unit in 1..=4 {
        let drive = sim.drive(unit).unwrap();
        assert_eq!(
            drive.setpoints.speed_rpm, 0,
            "unit {unit} was left turning at shutdown"
        );
    }
    let stats = bus.stats();
    assert_eq!(stats.busy_rejections, 0, "{stats:?}");
}

/// Two drives polled every 400 ms; a client reads the first one's status
/// every 50 ms.
const TWO_DRIVES_AT_400_MS: &str = r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
enabled = false
[[bus]]
name = "line"
port = "sim"
poll_interval_ms = 400
response_timeout_ms = 250
guard_ms = 50
[bus.sim]
turnaround_ms = 0.5
[[bus.drive]]
unit = 1
name = "read"
[[bus.drive]]
unit = 2
name = "polled"
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_status_a_client_reads_spares_that_drives_polls() {
    let d = TestDaemon::start(TWO_DRIVES_AT_400_MS).await;
    let bus = d.plant.buses()[0].handle.clone();
    let status = DriveRequest::ReadStatus;
    // The first client read goes before the window, so unit 1's poll is
    // already pushed on when it starts.
    bus.execute(1, &status, JobOptions::default())
        .await
        .unwrap();
    let before = bus.stats().polls;
    let start = std::time::Instant::now();
    let mut reads = 0;
    while start.elapsed() < Duration::from_secs(4) {
        let reply = bus.execute(1, &status, JobOptions::default()).await;
        assert!(matches!(reply, Ok(DriveReply::Status(_))), "{reply:?}");
        reads += 1;
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let polls = bus.stats().polls - before;
    // Unit 2 is polled every 400 ms, 10 times in 4 s (11 at the window's
    // edges). Unit 1's polls are all made by the client's reads, but for
    // one whenever the machine holds the client up for over 200 ms (half
    // the interval); unpolled, it would add 10 more.
    assert!((9..=14).contains(&polls), "{polls} polls, {reads} reads");
    // Both statuses are fresh.
    for unit in [1, 2] {
        let age = bus.drive(unit).unwrap().age().unwrap();
        assert!(age < Duration::from_secs(1), "unit {unit}: {age:?}");
    }
    d.stop().await;
}
