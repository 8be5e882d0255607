//! An OPC UA write its client gave up on is not sent. asyncua writes a
//! speed setpoint with a request timeout of 1 s (its `TimeoutHint`) while
//! the wire is held for 3 s: the request ends at its client's deadline,
//! and the setpoint, still queued for the bus, is dropped unsent when the
//! wire is free. Before, the server's own ceiling (300 s) stood in for the
//! hint, and the setpoint turned the motor 2 s after its client had given
//! up on it.

use std::time::Duration;

use drivegate::bus::stats::Outcome;

use super::opcua::{Client, LIMIT, Ua, operator, section};
use crate::support::bus::hold_the_wire;
use crate::support::config::ConfigBuilder;
use crate::support::{bounded, eventually};

/// Status reads of the bus so far (polls), to wait for the polls after
/// the held wire: a write still queued then goes out before them.
fn reads(bus: &drivegate::bus::BusHandle) -> u64 {
    bus.stats()
        .transactions
        .iter()
        .filter(|((function, _), _)| *function == 0x03)
        .map(|(_, n)| n)
        .sum()
}

fn dir_of(file: &std::path::Path) -> &std::path::Path {
    file.parent().unwrap_or(file)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_still_queued_at_its_clients_timeout_hint_is_not_sent() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let opcua = section(dir.path());
        let go = dir.path().join("go");
        // The held wire lasts one response timeout: 3 s, three times the
        // client's hint, and the queue timeout (5 s) longer still.
        let plant =
            ConfigBuilder::four_drives().with_bus("sim", |b| b.keys("response_timeout_ms = 3000"));
        let ua = Ua::start_plant(plant, false, dir, opcua).await;
        let bus = ua.d.plant.buses()[0].handle.clone();

        let mut args = operator();
        args.extend([
            "--value".into(),
            "300".into(),
            "--hint-ms".into(),
            "1000".into(),
            "--go".into(),
            go.display().to_string(),
        ]);
        let mut client = Client::asyncua(&ua.url, "late", &args);
        client.until("ready").await;
        eventually(
            Duration::from_secs(10),
            "the conveyor polled active",
            || {
                bus.drive(1)
                    .and_then(|s| s.status)
                    .is_some_and(|s| s.active())
                    .then_some(())
            },
        )
        .await;

        let sent_before = bus
            .stats()
            .transactions
            .get(&(0x06, Outcome::Ok))
            .copied()
            .unwrap_or(0);
        let blocker = hold_the_wire(&bus).await;
        std::fs::write(&go, b"").unwrap();
        let written = client.until("written").await;
        let status = written["status"].as_str().unwrap_or_default();
        assert!(
            status == "timeout" || status == "BadTimeout",
            "the client's deadline: {written}"
        );
        assert!(blocker.await.is_ok(), "the held wire's end");

        // Polls after the wire was free: a write still queued would have
        // gone out before them.
        let polled = reads(&bus);
        eventually(Duration::from_secs(10), "four polls after the hold", || {
            (reads(&bus) >= polled + 4).then_some(())
        })
        .await;
        let drive = ua.d.sim().drive(1).unwrap();
        assert_eq!(drive.setpoints.speed_rpm, 0, "{drive:?}");
        // The bus dropped it unsent at its turn: no write went out.
        let after = bus.stats().transactions;
        let writes = |outcome: Outcome| after.get(&(0x06, outcome)).copied().unwrap_or(0);
        assert_eq!(
            writes(Outcome::Ok),
            sent_before,
            "no write went out: {after:?}"
        );
        assert_eq!(
            writes(Outcome::Dropped),
            1,
            "the setpoint dropped: {after:?}"
        );
        std::fs::write(dir_of(&go).join("go.end"), b"").unwrap();
        drop(client);
        ua.d.stop().await;
    })
    .await;
}
