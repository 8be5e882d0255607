//! Commands from a host (DCMD) through the control core: a setpoint that
//! runs a drive and comes back confirmed, and refusals in words.

use std::time::Duration;

use drivegate::mqtt::metric::Value;

use super::{GROUP, NODE, config};
use crate::support::api::Api;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{Host, bool_metric, double_metric, number, string_metric};
use crate::support::{TestDaemon, bounded};

const WAIT: Duration = Duration::from_secs(20);

/// Waits for the node's births (the NBIRTH and the conveyor's DBIRTH).
pub async fn born(host: &mut Host) {
    host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
    host.next(WAIT, "the conveyor's DBIRTH", |m| {
        m.is("DBIRTH", Some("conveyor"))
    })
    .await;
}

/// The words of the next `command/last_result` of `device`.
pub async fn last_result(host: &mut Host, device: &str) -> String {
    let m = host
        .next(WAIT, "a command/last_result", |m| {
            m.is("DDATA", Some(device)) && m.metric("command/last_result").is_some()
        })
        .await;
    match m.value("command/last_result") {
        Some(Value::Text(t)) => t,
        other => panic!("command/last_result is {other:?}"),
    }
}

/// Activates `device`, puts it in speed mode and runs it at `rpm`, in one
/// DCMD.
pub async fn run(host: &Host, device: &str, rpm: f64) {
    host.dcmd(
        GROUP,
        NODE,
        device,
        vec![
            bool_metric("command/activate", true),
            string_metric("mode", "speed"),
            double_metric("setpoint/speed_rpm", rpm),
        ],
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dcmd_setpoint_runs_the_drive_and_is_confirmed() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "dcmd-host", None).await;
        crate::support::logs::capture_logs();
        let d = TestDaemon::start(&config(
            &broker.url(),
            "commands = \"operator\"\nunauthenticated_commands = true",
        ))
        .await;
        born(&mut host).await;
        run(&host, "conveyor", 120.0).await;
        // The value the drive confirmed, and an empty last result.
        let confirmed = host
            .next(WAIT, "the confirmed setpoint", |m| {
                m.is("DDATA", Some("conveyor")) && m.metric("setpoint/speed_rpm").is_some()
            })
            .await;
        assert_eq!(
            confirmed.value("setpoint/speed_rpm"),
            Some(Value::Double(120.0))
        );
        assert_eq!(
            confirmed.value("command/last_result"),
            Some(Value::Text(String::new()))
        );
        // The motor turns.
        host.next(WAIT, "the conveyor turning", |m| {
            m.is("DDATA", Some("conveyor"))
                && m.value("status/speed_rpm")
                    .and_then(|v| number(&v))
                    .is_some_and(|s| s > 60.0)
        })
        .await;
        // Held by a lease of the MQTT session's communication-loss function.
        let index = d
            .plant
            .drives()
            .iter()
            .position(|x| x.name == "conveyor")
            .unwrap();
        let lease = d.control().lease(index).expect("a lease on the conveyor");
        assert!(lease.comm_loss, "{lease:?}");
        // Without a login nor a primary host, only the broker is known.
        let who = format!("unauthenticated broker 127.0.0.1:{}", broker.port);
        assert_eq!(&*lease.owner, format!("mqtt {who}"));
        // Audited as every face's writes are.
        let log = crate::support::logs::log_text();
        assert!(
            log.lines().any(|l| l.contains("drivegate::audit")
                && l.contains("write confirmed")
                && l.contains("mqtt")
                && l.contains(&who)),
            "no audit line of the MQTT face's write"
        );
        // The bus monitor shows MQTT as the frames' source.
        let api = Api::new(d.http, None);
        let frames = api
            .get("/api/v1/buses/sim/monitor/frames?source=mqtt")
            .await
            .expect(200);
        let frames = frames["frames"].as_array().unwrap();
        assert!(
            frames.len() >= 6,
            "the activation, the mode and the setpoint, each with its echo: {frames:#?}"
        );
        assert!(frames.iter().all(|f| f["source"] == "mqtt"));
        assert_eq!(
            crate::support::metrics::counter(
                &d,
                "drivegate_mqtt_commands_total{result=\"confirmed\"}"
            ),
            3.0
        );
        d.stop().await;
    })
    .await;
}

/// Waits for the audit's line of a refused write of `what` from the MQTT
/// face, naming the valid range.
pub(crate) async fn audited(what: &str) {
    crate::support::eventually(
        Duration::from_secs(10),
        &format!("the audit of {what}"),
        || {
            crate::support::logs::log_text()
                .lines()
                .any(|l| {
                    l.contains("drivegate::audit")
                        && l.contains("write failed")
                        && l.contains("face=\"mqtt\"")
                        && l.contains(what)
                        && l.contains("refused: ")
                        && l.contains("valid -2048 to 2047")
                })
                .then_some(())
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_commands_say_why() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "refusal-host", None).await;
        crate::support::logs::capture_logs();
        let d = TestDaemon::start(&config(
            &broker.url(),
            "commands = \"operator\"\nunauthenticated_commands = true",
        ))
        .await;
        born(&mut host).await;
        // Out of range: the drive's range, in the words of every face.
        host.dcmd(
            GROUP,
            NODE,
            "conveyor",
            vec![double_metric("setpoint/speed_rpm", 5001.0)],
        )
        .await;
        let words = last_result(&mut host, "conveyor").await;
        assert!(
            words.contains("setpoint/speed_rpm")
                && words.contains("-2048")
                && words.contains("2047"),
            "{words}"
        );
        // Refused before it became a request, and audited all the same.
        audited("speed setpoint 5001 rpm").await;
        // An inactive drive: the core refuses as it would over HTTP.
        host.dcmd(
            GROUP,
            NODE,
            "lift",
            vec![double_metric("setpoint/speed_rpm", 50.0)],
        )
        .await;
        let words = last_result(&mut host, "lift").await;
        assert!(words.contains("refused"), "{words}");
        assert!(words.contains("not active"), "{words}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_only_commands_are_refused_by_the_core() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "viewer-host", None).await;
        // No `commands` key: read only.
        let d = TestDaemon::start(&config(&broker.url(), "")).await;
        born(&mut host).await;
        run(&host, "conveyor", 100.0).await;
        let words = last_result(&mut host, "conveyor").await;
        assert!(
            words.contains("refused")
                && words.contains("operator role")
                && words.contains("viewer"),
            "{words}"
        );
        // Nothing reached the drive.
        let status = d.plant.buses()[0].handle.drive(1).unwrap().status.unwrap();
        assert!(!status.active(), "a refused command changed nothing");
        assert_eq!(
            crate::support::metrics::counter(
                &d,
                "drivegate_mqtt_commands_total{result=\"refused\"}"
            ),
            1.0
        );
        d.stop().await;
    })
    .await;
}
