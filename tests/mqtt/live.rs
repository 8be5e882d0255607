//! Only a live command moves a motor. Commands left on the broker before
//! the daemon starts (a retained Sparkplug DCMD and NCMD, a retained JSON
//! command with its MQTT 5 response topic) and a QoS 1 DCMD published
//! while the daemon is down move nothing: each drive's own state (the
//! simulator's, not the daemon's words) stays as it was, nothing of MQTT's
//! reaches the bus monitor, the refusals are in the audit log and answered
//! (`command/last_result`, the JSON reply), and the retained messages,
//! which are not the node's, are still on the broker afterwards. One
//! broker and one daemon of each format serve every case.

use std::time::Duration;

use drivegate::mqtt::metric::Value;
use drivegate::mqtt::sparkplug_b::Payload;
use drivegate::mqtt::sparkplug_b::payload::Metric;
use prost::Message;
use serde_json::json;

use super::{GROUP, NODE, config};
use crate::support::api::Api;
use crate::support::metrics::counter;
use crate::support::mosquitto::{Mosquitto, Sub, publish_retained};
use crate::support::sparkplug::{Host, bool_metric, double_metric, string_metric};
use crate::support::{TestDaemon, bounded};

const WAIT: Duration = Duration::from_secs(20);

/// What an audit line of a command ignored begins with.
const IGNORED: &str = "a retained command was ignored";

/// A Sparkplug payload of `metrics`, stamped now.
fn payload(metrics: Vec<Metric>) -> Vec<u8> {
    Payload {
        timestamp: Some(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_millis() as u64,
        ),
        metrics,
        ..Default::default()
    }
    .encode_to_vec()
}

/// The DCMD that would activate `drive` and turn it at `rpm`.
fn turn(rpm: f64) -> Vec<Metric> {
    vec![
        bool_metric("command/activate", true),
        string_metric("mode", "speed"),
        double_metric("setpoint/speed_rpm", rpm),
    ]
}

/// The audit lines of ignored commands that name `drive`.
fn ignored(drive: &str) -> Vec<String> {
    crate::support::logs::log_text()
        .lines()
        .filter(|l| l.contains("drivegate::audit") && l.contains(IGNORED) && l.contains(drive))
        .map(str::to_string)
        .collect()
}

/// Waits until `n` audit lines of ignored commands name `what`.
async fn until_ignored(what: &str, n: usize) {
    let start = tokio::time::Instant::now();
    while ignored(what).len() < n {
        assert!(start.elapsed() < WAIT, "{what}: {:#?}", ignored(what));
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(ignored(what).len(), n, "{:#?}", ignored(what));
}

/// The simulated drive at `unit` of `d` is as it was at power-on: not
/// active, no speed setpoint, not turning; and no frame of MQTT's reached
/// its bus.
async fn untouched(d: &TestDaemon, unit: u8) {
    let drive = d.sim().drive(unit).expect("a simulated drive");
    assert!(
        !drive.active && drive.setpoints.speed_rpm == 0 && drive.status.speed_rpm == 0,
        "unit {unit} was moved: {drive:?}"
    );
    let frames = Api::new(d.http, None)
        .get("/api/v1/buses/sim/monitor/frames?source=mqtt")
        .await
        .expect(200);
    assert_eq!(
        frames["frames"].as_array().map(Vec::len),
        Some(0),
        "{frames:#}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retained_and_offline_commands_move_nothing_and_are_answered() {
    bounded(Duration::from_secs(120), async {
        let broker = Mosquitto::start();
        crate::support::logs::capture_logs();
        let dcmd_topic = format!("spBv1.0/{GROUP}/DCMD/{NODE}/conveyor");
        let json_command = format!("drivegate/{NODE}/lift/command");
        // Left on the broker before any daemon runs: a DCMD that would
        // turn the conveyor at 123 rpm, a rebirth, and a JSON command that
        // would turn the lift at 88 rpm, with where to answer it.
        publish_retained(broker.port, &dcmd_topic, &payload(turn(123.0)), &[]).await;
        publish_retained(
            broker.port,
            &format!("spBv1.0/{GROUP}/NCMD/{NODE}"),
            &payload(vec![bool_metric("Node Control/Rebirth", true)]),
            &[],
        )
        .await;
        let setpoint = json!({"type": "command", "id": "r-88", "op": "setpoint", "body": {"speed_rpm": 88}});
        publish_retained(
            broker.port,
            &json_command,
            setpoint.to_string().as_bytes(),
            &[
                ("response-topic", "app/replies/live"),
                ("correlation-data", "corr-88"),
            ],
        )
        .await;
        // The application that waits for the reply: subscribed once its
        // own retained marker came back.
        publish_retained(broker.port, "app/replies/ready", b"1", &[]).await;
        let mut replies = Sub::start(broker.port, &["app/replies/#"]);
        replies
            .next(WAIT, "the marker", |m| m.topic == "app/replies/ready")
            .await;
        let mut host = Host::connect(broker.port, "live-host", None).await;

        let keys = "commands = \"operator\"\nunauthenticated_commands = true";
        let sparkplug = TestDaemon::start(&config(&broker.url(), keys)).await;
        let json_node =
            TestDaemon::start(&config(&broker.url(), &format!("format = \"json\"\n{keys}")))
                .await;

        // Sparkplug: answered in the conveyor's command/last_result (in
        // its DBIRTH if the refusal came first, else a DDATA).
        let answered = host
            .next(WAIT, "the refusal in command/last_result", |m| {
                (m.is("DBIRTH", Some("conveyor")) || m.is("DDATA", Some("conveyor")))
                    && matches!(
                        m.value("command/last_result"),
                        Some(Value::Text(t)) if t.contains(IGNORED)
                    )
            })
            .await;
        let Some(Value::Text(words)) = answered.value("command/last_result") else {
            unreachable!()
        };
        assert!(
            words.starts_with("command/activate, mode, setpoint/speed_rpm: refused: a retained command was ignored"),
            "{words}"
        );
        // JSON: answered on its response topic with its correlation data.
        let reply = replies
            .next(WAIT, "the reply to the retained command", |m| {
                m.topic == "app/replies/live"
            })
            .await;
        assert_eq!(reply.correlation, "corr-88");
        let v = reply.json();
        assert_eq!((&v["id"], &v["ok"]), (&json!("r-88"), &json!(false)), "{v}");
        assert_eq!(v["problem"]["type"], "urn:drivegate:problem:not-live", "{v}");
        assert!(
            v["problem"]["detail"]
                .as_str()
                .is_some_and(|d| d.starts_with(IGNORED)),
            "{v}"
        );
        // Audited with who sent it and what it asked.
        let conveyor = ignored("conveyor");
        assert_eq!(conveyor.len(), 1, "{conveyor:#?}");
        assert!(
            conveyor[0].contains("setpoint/speed_rpm = 123") && conveyor[0].contains("mqtt"),
            "{conveyor:#?}"
        );
        let lift = ignored("lift");
        assert_eq!(lift.len(), 1, "{lift:#?}");
        assert!(lift[0].contains("setpoint") && lift[0].contains("88"), "{lift:#?}");
        until_ignored("NCMD", 1).await;
        for d in [&sparkplug, &json_node] {
            assert!(counter(d, "drivegate_mqtt_commands_total{result=\"refused\"}") >= 1.0);
        }
        // Nothing moved, on either drive.
        untouched(&sparkplug, 1).await;
        untouched(&json_node, 2).await;

        // A QoS 1 DCMD published while the Sparkplug daemon is down: the
        // broker has it (the host, subscribed, got it), but the daemon's
        // session started clean, so nobody kept it for the daemon.
        sparkplug.stop().await;
        host.dcmd(GROUP, NODE, "conveyor", turn(77.0)).await;
        host.next(WAIT, "the DCMD at the broker", |m| {
            m.is("DCMD", Some("conveyor"))
                && m.value("setpoint/speed_rpm") == Some(Value::Double(77.0))
        })
        .await;
        let again = TestDaemon::start(&config(&broker.url(), keys)).await;
        host.next(WAIT, "the DBIRTH of the restarted node", |m| {
            m.is("DBIRTH", Some("conveyor"))
        })
        .await;
        // The retained DCMD is refused again after the new subscription;
        // anything a kept session held would have come before it.
        until_ignored("conveyor", 2).await;
        untouched(&again, 1).await;

        // The retained commands are not the node's: still on the broker.
        let mut late = Sub::start(broker.port, &[&json_command]);
        let kept = late
            .next(WAIT, "the retained JSON command", |m| m.retained)
            .await;
        assert_eq!(kept.json()["id"], "r-88");
        late.stop().await;
        let mut fresh = Host::connect(broker.port, "late-host", None).await;
        let kept = fresh
            .next(WAIT, "the retained DCMD", |m| m.is("DCMD", Some("conveyor")))
            .await;
        assert_eq!(
            kept.value("setpoint/speed_rpm"),
            Some(Value::Double(123.0))
        );
        replies.stop().await;
        again.stop().await;
        json_node.stop().await;
    })
    .await;
}
