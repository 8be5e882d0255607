//! Faults of one drive among eight, through the real pty: a drive that
//! goes silent, and a drive whose power is cut while the bus is busy. The
//! seven others keep being polled and lose nothing; every request to the
//! faulty drive is confirmed or reported failed; what the drive reports
//! after its reboot is what it holds; `/metrics` counts every unanswered
//! attempt and shows the drive's link state.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::support::bounded;
use crate::support::faults::{
    JOB_LIMIT, PollCounter, Setting, Truth, UNITS, Wire, assert_late_replies_discarded,
    assert_polled, drive_up, eight_drives, late_by_the_machine, stop_and_scrape, traffic_on,
};
use crate::support::{TestDaemon, eventually};
use drivegate::bus::cache::Link;
use drivegate::bus::handle::JobOptions;
use drivegate::bus::{BusError, BusHandle, SourceId};
use drivegate::sim::model::Settings;
use tokio_util::sync::CancellationToken;

const LIMIT: Duration = Duration::from_secs(45);
const ROUNDS: u32 = 24;
/// A cap on rounds for traffic that runs until the scenario is over.
const MAX_ROUNDS: u32 = 10_000;
const BUS: &str = "line";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_drive_goes_offline_costs_little_and_fails_only_its_own_requests() {
    bounded(LIMIT, async {
        const SILENT: u8 = 8;
        // Only the silent drive's replies are missing; one the machine's
        // scheduling delays past the timeout arrives in the guard time.
        let d = TestDaemon::start(&eight_drives(
            "sim",
            "response_timeout_ms = 250\nguard_ms = 50",
            "",
        ))
        .await;
        let bus = d.plant.buses()[0].handle.clone();
        let truth = Arc::new(Truth::of_plant(d.plant.clone()));
        d.sim().set_silent(SILENT, true);
        let silenced = Instant::now();
        let polls = PollCounter::start(&bus);

        // Writes to the silent drive while the seven others work.
        let lone = tokio::spawn({
            let bus = bus.clone();
            async move {
                let source = SourceId::new_unique();
                let mut errors = Vec::new();
                for i in 0..8 {
                    let (request, _) = Setting::SpeedRamp.write(i);
                    let result = tokio::time::timeout(
                        JOB_LIMIT,
                        bus.execute(SILENT, &request, JobOptions::from_source(source)),
                    )
                    .await
                    .expect("a write to a silent drive is answered in time");
                    errors.push(result.expect_err("a silent drive confirms nothing"));
                    tokio::time::sleep(Duration::from_millis(300)).await;
                }
                errors
            }
        });
        let (total, each) = traffic_on(
            &bus,
            &truth,
            1..SILENT,
            ROUNDS,
            &[],
            &CancellationToken::new(),
        )
        .await;
        let errors = lone.await.unwrap();
        let polls = polls.finish().await;

        // The others lost nothing and were not slowed into failures.
        total.assert_nothing_lost();
        assert_eq!(total.writes_confirmed, u64::from(ROUNDS) * 7, "{each:?}");
        assert_eq!(total.reads_answered, u64::from(ROUNDS) * 7, "{each:?}");
        assert_polled(&polls, 1..SILENT, 4);
        // A poll under way when the drive fell silent may still report it.
        assert!(polls.get(&SILENT).copied().unwrap_or(0) <= 1, "{polls:?}");

        // Every write to the silent drive was reported as a timeout; once the
        // drive was offline, after one attempt only.
        for e in &errors {
            assert!(matches!(e, BusError::Timeout { unit: SILENT, .. }), "{e}");
            assert!(e.to_string().contains("did not answer"), "{e}");
        }
        assert!(
            matches!(errors.last(), Some(BusError::Timeout { attempts: 1, .. })),
            "{errors:?}"
        );
        // ... and none reached the drive.
        let silent_settings = truth.settings_since(0, SILENT).await;
        assert!(silent_settings.iter().all(|s| *s == Settings::FACTORY));
        let snapshot = bus.drive(SILENT).unwrap();
        assert_eq!(snapshot.link, Link::Offline);
        assert!(snapshot.consecutive_failures >= 3);

        let elapsed = silenced.elapsed().as_secs_f64();
        let (s, plant) = stop_and_scrape(d).await;
        let sim = plant.buses()[0].sim.as_ref().unwrap().stats();
        let wire = Wire::of(&s, BUS);
        eprintln!("{total:?}\n{wire:?}\n{sim}\npolls {polls:?}");
        // /metrics: the drive is down, the others up.
        assert_eq!(drive_up(&s, BUS, SILENT), 0.0);
        for unit in 1..SILENT {
            assert_eq!(drive_up(&s, BUS, unit), 1.0, "unit {unit}");
        }
        assert!(
            s.get(
                "drivegate_drive_consecutive_poll_failures",
                &[("bus", BUS), ("unit", "8")]
            ) >= 3.0
        );
        // Exact: every attempt at the silent drive went unanswered and timed
        // out, and no other attempt failed but for a reply the machine made
        // late (rare, discarded when it came, retried).
        let late = late_by_the_machine(&wire, &sim);
        assert_late_replies_discarded(&wire, &sim, late);
        assert_eq!(
            wire.retries + wire.timeout + wire.bad_reply,
            sim.unanswered + late,
            "{wire:?} {sim}"
        );
        assert_eq!(wire.crc_error, 0);
        assert!(wire.bad_reply <= late, "{wire:?}");
        assert_eq!(
            wire.timeout + wire.bad_reply,
            wire.poll_failures + errors.len() as u64
        );
        assert_eq!(sim.requests, wire.attempts());
        // It costs little: offline after 3 failed polls, then polled with a
        // backoff of 1 s doubling, so within `elapsed` seconds at most
        // 3 + log2(elapsed + 1) polls (+ 1 under way when it went silent).
        let bound = 3 + (elapsed + 1.0).log2().floor() as u64 + 1;
        assert!(
            wire.poll_failures <= bound,
            "{} failed polls of the silent drive in {elapsed:.1} s (at most {bound})",
            wire.poll_failures
        );
    })
    .await;
}

/// Waits until `unit`, power-cycled at `cut`, has answered a poll after
/// its reboot time (600 ms).
async fn answered_after_reboot(bus: &BusHandle, unit: u8, cut: Instant) {
    let rebooted = cut + Duration::from_millis(600);
    eventually(
        Duration::from_secs(10),
        "the drive to answer after its reboot",
        || {
            bus.drive(unit)
                .filter(|s| s.link == Link::Online && s.seen_instant.is_some_and(|t| t > rebooted))
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_power_cycled_drive_comes_back_with_what_its_flash_holds() {
    bounded(LIMIT, async {
        const CYCLED: u8 = 3;
        let d = TestDaemon::start(&eight_drives(
            "sim",
            "response_timeout_ms = 250\nguard_ms = 50\noffline_backoff_ms = 200",
            // Long enough that the traffic meets it even on a loaded machine.
            "reboot_ms = 2000",
        ))
        .await;
        let bus = d.plant.buses()[0].handle.clone();
        let truth = Arc::new(Truth::of_plant(d.plant.clone()));
        let polls = PollCounter::start(&bus);
        let stop = CancellationToken::new();

        // Two power cuts while every drive takes writes and reads; the
        // traffic stops a little after the drive is back the second time.
        let cutter = tokio::spawn({
            let truth = truth.clone();
            let bus = bus.clone();
            let stop = stop.clone();
            async move {
                for _ in 0..2 {
                    tokio::time::sleep(Duration::from_millis(400)).await;
                    truth.power_cycle(CYCLED).await;
                    answered_after_reboot(&bus, CYCLED, Instant::now()).await;
                }
                // Then at least the bus work of 8 more rounds of the
                // others (a write and a read each), however slow the
                // machine.
                let requests = |s: &drivegate::sim::SimHandle| s.stats().requests;
                let after = truth.with_sim(requests).await + 8 * 2 * (UNITS.len() as u64 - 1);
                while truth.with_sim(requests).await < after {
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                stop.cancel();
            }
        });
        let (total, each) = traffic_on(&bus, &truth, UNITS, MAX_ROUNDS, &["timeout"], &stop).await;
        cutter.await.unwrap();
        let polls = polls.finish().await;
        eprintln!("{total:?}\npolls {polls:?}");

        total.assert_nothing_lost();
        // Only the power-cycled drive's requests failed, and each was
        // reported; the others had every write confirmed.
        for (unit, tally) in &each {
            if *unit != CYCLED {
                assert!(tally.failures.is_empty(), "unit {unit}: {tally:?}");
                assert!(tally.writes_confirmed >= 8, "unit {unit}: {tally:?}");
            }
        }
        assert!(
            each[&CYCLED].writes_failed + each[&CYCLED].reads_failed >= 1,
            "the power cuts hit traffic: {:?}",
            each[&CYCLED]
        );
        assert_polled(&polls, UNITS.filter(|u| *u != CYCLED), 4);

        // Once more, then read: the unsaved ramp written before the cut is
        // gone, and the daemon reports the drive's flash value, not a copy.
        let (request, value) = Setting::SpeedRamp.write(999);
        bus.execute(CYCLED, &request, JobOptions::default())
            .await
            .unwrap();
        truth.power_cycle(CYCLED).await;
        let epoch = truth.epoch();
        answered_after_reboot(&bus, CYCLED, Instant::now()).await;
        let read = bus
            .transact(CYCLED, Setting::SpeedRamp.read_pdu(), JobOptions::default())
            .await
            .unwrap();
        let alpha = Setting::SpeedRamp.decode(&read.reply).unwrap();
        assert_ne!(alpha, value);
        assert_eq!(alpha, u64::from(Settings::FACTORY.speed_alpha));
        let states = truth.settings_since(epoch, CYCLED).await;
        assert_eq!(states.len(), 1);
        assert_eq!(Setting::SpeedRamp.of(&states[0]), alpha);

        let (s, plant) = stop_and_scrape(d).await;
        let sim = plant.buses()[0].sim.as_ref().unwrap().stats();
        let wire = Wire::of(&s, BUS);
        eprintln!("{wire:?}\n{sim}");
        // Exact: every attempt at the rebooting drive went unanswered and
        // timed out; nothing else failed but for a reply the machine made
        // late (rare, discarded when it came, retried).
        assert!(sim.unanswered >= 2, "{sim}");
        let late = late_by_the_machine(&wire, &sim);
        assert_late_replies_discarded(&wire, &sim, late);
        assert_eq!(
            wire.retries + wire.timeout + wire.bad_reply,
            sim.unanswered + late,
            "{wire:?} {sim}"
        );
        assert_eq!(
            wire.timeout + wire.bad_reply,
            wire.poll_failures + total.writes_failed + total.reads_failed
        );
        assert_eq!(wire.crc_error, 0);
        assert!(wire.bad_reply <= late, "{wire:?}");
        assert_eq!(sim.requests, wire.attempts());
        // The drive is back up in /metrics.
        for unit in UNITS {
            assert_eq!(drive_up(&s, BUS, unit), 1.0, "unit {unit}");
        }
    })
    .await;
}
