//! The USB adapter unplugged and plugged back twice while eight drives
//! take writes and reads: the simulator's pty disappears from under the
//! daemon (its link with it) and a new one appears at the same path. The
//! daemon marks the bus down, fails what was queued, refuses new work with
//! a clear error, reopens the port by itself and carries on; no reply from
//! before the unplug answers a request from after it, and `/metrics`
//! counts the port errors, the reopens and every job the outage failed.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use crate::support::faults::{
    PollCounter, Setting, Truth, UNITS, Wire, assert_polled, drive_up, eight_drives,
    stop_and_scrape, traffic_on,
};
use crate::support::{TestDaemon, eventually};
use drivegate::bus::BusEvent;
use drivegate::bus::cache::Link;
use drivegate::bus::handle::{JobOptions, PortState};
use drivegate::sim::SimConfig;
use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;

const LIMIT: Duration = Duration::from_secs(45);
const BUS: &str = "line";
const UNPLUGS: u64 = 2;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_adapter_unplugged_during_traffic_is_reopened_and_nothing_is_lost() {
    tokio::time::timeout(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-drives");
        let truth = Arc::new(Truth::linked(SimConfig::for_units(UNITS), &link));
        let d = TestDaemon::start(&eight_drives(
            &link.display().to_string(),
            crate::support::WIRE_TIMING,
            "",
        ))
        .await;
        let bus = d.plant.buses()[0].handle.clone();
        let mut events = bus.subscribe();
        let polls = PollCounter::start(&bus);
        let stop = CancellationToken::new();

        let traffic = tokio::spawn({
            let (bus, truth, stop) = (bus.clone(), truth.clone(), stop.clone());
            async move {
                traffic_on(
                    &bus,
                    &truth,
                    UNITS,
                    10_000,
                    &["bus_down", "bus_down_after_send", "timeout"],
                    &stop,
                )
                .await
            }
        });
        for _ in 0..UNPLUGS {
            tokio::time::sleep(Duration::from_millis(500)).await;
            truth.unplug_for(Duration::from_millis(300)).await;
            eventually(
                Duration::from_secs(10),
                "the bus back up with every drive",
                || {
                    (matches!(bus.port_state(), PortState::Up { .. })
                        && bus.drives().iter().all(|s| s.link == Link::Online))
                    .then_some(())
                },
            )
            .await;
        }
        // The traffic goes on until every drive has answered four polls
        // since the last replug: an event, not a time, as a loaded machine
        // polls more slowly.
        let mut after = bus.subscribe();
        let mut polled: BTreeMap<u8, u32> = BTreeMap::new();
        tokio::time::timeout(Duration::from_secs(20), async {
            while UNITS
                .into_iter()
                .any(|u| polled.get(&u).copied().unwrap_or(0) < 4)
            {
                match after.recv().await {
                    Ok(BusEvent::Status { unit, .. }) => *polled.entry(unit).or_default() += 1,
                    Ok(_) | Err(RecvError::Lagged(_)) => {}
                    Err(RecvError::Closed) => panic!("the bus's events ended"),
                }
            }
        })
        .await
        .unwrap_or_else(|_| panic!("drives polled after the outages: {polled:?}"));
        stop.cancel();
        let (total, each) = traffic.await.unwrap();
        let polls = polls.finish().await;

        let (mut down, mut up) = (0, 0);
        while let Ok(event) = events.try_recv() {
            match event {
                BusEvent::BusDown { reason, .. } => {
                    // The reason names the port and what happened.
                    assert!(
                        reason.contains("ttyUSB-drives") || reason.contains("/dev/pts"),
                        "{reason}"
                    );
                    down += 1;
                }
                BusEvent::BusUp { .. } => up += 1,
                _ => {}
            }
        }
        // After the outages every drive takes a write and reads it back.
        for unit in UNITS {
            let (request, value) = Setting::SpeedRamp.write(900_000 + u32::from(unit));
            bus.execute(unit, &request, JobOptions::default())
                .await
                .unwrap_or_else(|e| panic!("unit {unit} after the outages: {e}"));
            let read = bus
                .transact(unit, Setting::SpeedRamp.read_pdu(), JobOptions::default())
                .await
                .unwrap_or_else(|e| panic!("unit {unit} after the outages: {e}"));
            assert_eq!(
                Setting::SpeedRamp.decode(&read.reply),
                Some(value),
                "unit {unit}"
            );
        }
        let (s, _plant) = stop_and_scrape(d).await;
        let wire = Wire::of(&s, BUS);
        eprintln!("{total:?}\n{wire:?}\npolls {polls:?}\ndown {down} up {up}");

        total.assert_nothing_lost();
        // The outages hit traffic: accepted jobs failed, new ones were
        // refused unsent while the bus was down.
        assert!(total.failed_bus_down >= 1, "{total:?}");
        assert!(total.writes_refused + total.reads_refused >= 1, "{total:?}");
        // Between the outages every drive worked, and after them each took
        // a write and read it back (above, before the stop: how much
        // traffic fits between the outages depends on how fast the machine
        // is, not on the daemon).
        for (unit, tally) in &each {
            assert!(tally.writes_confirmed >= 1, "unit {unit}: {tally:?}");
        }
        assert_polled(&polls, UNITS, 4);
        // Each outage is one bus-down and one bus-up event, one reopen.
        assert_eq!((down, up), (UNPLUGS, UNPLUGS));
        assert_eq!(wire.reopens, UNPLUGS, "{wire:?}");
        // The failure of the open port, then (once per outage, while the
        // link is missing) the failure to open it again.
        assert!(wire.port_errors >= UNPLUGS, "{wire:?}");
        assert_eq!(wire.port_open, 1);
        // Exact: every accepted job the outages failed is one port_error
        // transaction (refused ones never became transactions).
        assert_eq!(wire.port_error, total.failed_bus_down, "{wire:?} {total:?}");
        for unit in UNITS {
            assert_eq!(drive_up(&s, BUS, unit), 1.0, "unit {unit}");
        }
    })
    .await
    .expect("test did not finish in time");
}
