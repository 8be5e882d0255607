//! The motor-safety lease of MQTT's commands: it ends with
//! `comm_loss_action` when the primary host goes offline, and when the
//! broker is gone for longer than `comm_loss_ms`. (A restart's end of it
//! is the safety journal's, as for every communication-loss lease.)

use std::time::Duration;

use drivegate::mqtt::metric::Value;

use super::commands::{born, run};
use super::config;
use crate::support::metrics::counter;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{Host, number};
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);

/// The ends of the MQTT session's leases on bus `sim`, by reason.
const MQTT_CLOSED: &str = "drivegate_mqtt_comm_loss_stops_total{bus=\"sim\",reason=\"closed\"}";
const MQTT_TIMEOUT: &str = "drivegate_mqtt_comm_loss_stops_total{bus=\"sim\",reason=\"timeout\"}";

/// Waits until the conveyor's DDATA says it turns faster than 100 rpm.
async fn turning(host: &mut Host) {
    host.next(WAIT, "the conveyor turning", |m| {
        m.is("DDATA", Some("conveyor"))
            && m.value("status/speed_rpm")
                .and_then(|v| number(&v))
                .is_some_and(|s| s > 100.0)
    })
    .await;
}

/// Waits until the conveyor (unit 1) is at rest with no lease on it.
async fn stopped(d: &TestDaemon, why: &str) {
    eventually(WAIT, why, || {
        let s = d.plant.buses()[0].handle.drive(1)?.status?;
        (s.speed_rpm.abs() <= 2 && d.control().lease(0).is_none()).then_some(())
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_primary_host_offline_stops_the_motor_it_commanded() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "scada-host", Some("scada")).await;
        host.announce(true).await;
        let d = TestDaemon::start(&config(
            &broker.url(),
            "primary_host_id = \"scada\"\ncommands = \"operator\"\nunauthenticated_commands = true\ncomm_loss_ms = 60000",
        ))
        .await;
        born(&mut host).await;
        assert_eq!(
            counter(&d, MQTT_CLOSED),
            0.0,
            "not counted before the host went offline"
        );
        run(&host, "conveyor", 200.0).await;
        turning(&mut host).await;
        host.announce(false).await;
        // At once, not after comm_loss_ms (a minute here).
        stopped(&d, "the conveyor stopped after the host went offline").await;
        // Counted as MQTT's, not as a Modbus TCP client's.
        eventually(WAIT, "the end of the MQTT lease counted", || {
            (counter(&d, MQTT_CLOSED) == 1.0).then_some(())
        })
        .await;
        assert_eq!(counter(&d, MQTT_TIMEOUT), 0.0);
        assert_eq!(
            counter(
                &d,
                "drivegate_modbus_tcp_comm_loss_stops_total{bus=\"sim\",reason=\"closed\"}"
            ),
            0.0
        );
        // The node says goodbye, and comes back with the next bdSeq once
        // the host is online again.
        let ndeath = host.next(WAIT, "NDEATH", |m| m.is("NDEATH", None)).await;
        assert_eq!(ndeath.value("bdSeq"), Some(Value::Int(0)));
        host.announce(true).await;
        let nbirth = host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
        assert_eq!(nbirth.value("bdSeq"), Some(Value::Int(1)));
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn births_wait_for_the_primary_host() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "late-host", Some("late")).await;
        let d = TestDaemon::start(&config(&broker.url(), "primary_host_id = \"late\"")).await;
        eventually(WAIT, "the daemon connected", || {
            (crate::support::metrics::counter(&d, "drivegate_mqtt_connected") == 1.0).then_some(())
        })
        .await;
        assert!(
            !host.seen.iter().any(|m| m.kind == "NBIRTH"),
            "no birth before the host is online"
        );
        host.announce(true).await;
        host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn losing_the_broker_stops_the_motor_after_comm_loss_ms() {
    bounded(Duration::from_secs(90), async {
        let mut broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "loss-host", None).await;
        let d = TestDaemon::start(&config(
            &broker.url(),
            "commands = \"operator\"\nunauthenticated_commands = true\ncomm_loss_ms = 500",
        ))
        .await;
        born(&mut host).await;
        run(&host, "conveyor", 200.0).await;
        turning(&mut host).await;
        broker.stop();
        stopped(&d, "the conveyor stopped after the broker was lost").await;
        eventually(WAIT, "the end of the MQTT lease counted", || {
            (counter(&d, MQTT_TIMEOUT) == 1.0).then_some(())
        })
        .await;
        assert_eq!(counter(&d, MQTT_CLOSED), 0.0);
        d.stop().await;
    })
    .await;
}
