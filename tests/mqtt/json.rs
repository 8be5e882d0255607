//! The JSON format (`format = "json"`) with third-party clients, Debian's
//! `mosquitto_sub` and `mosquitto_pub` over MQTT 5: the retained state
//! and statuses, a command that turns a drive and its reply, refusals in
//! the API's words, the MQTT 5 response topic with its correlation data,
//! malformed messages, events, the session's lease ended by losing the
//! broker, and `kill -9` leaving the will `offline`.

use std::process::Stdio;
use std::time::Duration;

use serde_json::{Value, json};

use super::{NODE, config};
use crate::support::metrics::counter;
use crate::support::mosquitto::{Mosquitto, Received, Sub, publish};
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);

/// The default prefix of the tests' node.
fn prefix() -> String {
    format!("drivegate/{NODE}")
}

fn topic(rest: &str) -> String {
    format!("{}/{rest}", prefix())
}

/// A daemon with the JSON format and `keys`.
async fn daemon(broker: &Mosquitto, keys: &str) -> TestDaemon {
    TestDaemon::start(&config(
        &broker.url(),
        &format!("format = \"json\"\n{keys}"),
    ))
    .await
}

/// A client subscribed to `topics` and to the state: once the retained
/// `online` came, its subscriptions are in place.
async fn subscribed(broker: &Mosquitto, topics: &[&str]) -> Sub {
    let state = topic("state");
    let mut all = vec![state.as_str()];
    all.extend_from_slice(topics);
    let mut sub = Sub::start(broker.port, &all);
    sub.next(WAIT, "the state online", |m| {
        m.topic == state && m.payload == "online"
    })
    .await;
    sub
}

/// Sends command `op` with `body` to the conveyor, id `id`.
async fn command(broker: &Mosquitto, id: Value, op: &str, body: Value) {
    let message = json!({"type": "command", "id": id, "op": op, "body": body});
    publish(
        broker.port,
        &topic("conveyor/command"),
        &message.to_string(),
        &[],
    )
    .await;
}

/// The conveyor's reply to `id`.
async fn reply(sub: &mut Sub, id: Value) -> Value {
    let reply_topic = topic("conveyor/reply");
    let m = sub
        .next(WAIT, &format!("the reply to {id}"), |m| {
            m.topic == reply_topic && m.json()["id"] == id
        })
        .await;
    let v = m.json();
    assert_eq!(v["type"], "reply", "{v}");
    v
}

/// The problem of a refused reply.
fn problem(v: &Value) -> &Value {
    assert_eq!(v["ok"], false, "{v}");
    &v["problem"]
}

fn is_status(m: &Received, speed_over: f64) -> bool {
    m.topic == topic("conveyor/status")
        && m.json()["speed_rpm"]
            .as_f64()
            .is_some_and(|s| s > speed_over)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retained_state_and_status_and_a_command_that_turns_a_drive() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let d = daemon(
            &broker,
            "commands = \"operator\"\nunauthenticated_commands = true",
        )
        .await;
        // A client that comes later gets the state and each drive's status
        // from the broker (retained), in the API's status JSON.
        let status_topic = topic("conveyor/status");
        let mut sub = subscribed(&broker, &[&status_topic, &topic("conveyor/reply")]).await;
        sub.next(WAIT, "the conveyor's status", |m| m.topic == status_topic)
            .await;
        // Published once at least: a client that comes now gets it from
        // the broker at once, retained.
        let mut late = Sub::start(broker.port, &[&status_topic]);
        let status = late
            .next(WAIT, "the conveyor's retained status", |m| m.retained)
            .await
            .json();
        late.stop().await;
        assert_eq!(
            (&status["drive"], &status["bus"], &status["unit"]),
            (&json!("conveyor"), &json!("sim"), &json!(1))
        );
        for field in ["speed_rpm", "angle_deg", "mode", "fault", "link", "seen_at"] {
            assert!(status.get(field).is_some(), "{field} missing: {status}");
        }

        command(&broker, json!(1), "activate", json!({})).await;
        let v = reply(&mut sub, json!(1)).await;
        assert_eq!(v["ok"], true, "{v}");
        assert_eq!(v["result"]["command"], "activate");
        command(&broker, json!(2), "mode", json!({"mode": "speed"})).await;
        assert_eq!(reply(&mut sub, json!(2)).await["ok"], true);
        command(
            &broker,
            json!("turn"),
            "setpoint",
            json!({"speed_rpm": 200}),
        )
        .await;
        let v = reply(&mut sub, json!("turn")).await;
        assert_eq!(v["ok"], true, "{v}");
        assert_eq!(v["result"]["drive"], "conveyor");
        // The MQTT session's communication-loss lease covers it.
        assert_eq!(v["result"]["lease"]["comm_loss"], true, "{v}");
        sub.next(WAIT, "the conveyor turning in its status", |m| {
            is_status(m, 100.0)
        })
        .await;
        assert!(counter(&d, "drivegate_mqtt_commands_total{result=\"confirmed\"}") >= 3.0);
        // A status read through MQTT, as the stream's `status` op.
        command(&broker, json!(4), "status", json!({"fresh": true})).await;
        let v = reply(&mut sub, json!(4)).await;
        assert_eq!(
            (&v["ok"], &v["result"]["source"]),
            (&json!(true), &json!("bus"))
        );
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_and_malformed_messages_are_replied_in_the_apis_words() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        crate::support::logs::capture_logs();
        let d = daemon(
            &broker,
            "commands = \"operator\"\nunauthenticated_commands = true",
        )
        .await;
        let mut sub = subscribed(&broker, &[&topic("conveyor/reply")]).await;
        command(&broker, json!(1), "activate", json!({})).await;
        reply(&mut sub, json!(1)).await;
        command(&broker, json!(2), "mode", json!({"mode": "speed"})).await;
        reply(&mut sub, json!(2)).await;
        // Out of range: refused naming the range, as the API does.
        command(&broker, json!(3), "setpoint", json!({"speed_rpm": 5002})).await;
        let v = reply(&mut sub, json!(3)).await;
        let p = problem(&v);
        assert_eq!(p["type"], "urn:drivegate:problem:out-of-range", "{v}");
        assert_eq!(
            (&p["valid_range"]["min"], &p["valid_range"]["max"]),
            (&json!(-2048.0), &json!(2047.0)),
            "{v}"
        );
        assert!(
            p["detail"].as_str().unwrap().contains("-2048"),
            "the range in words: {v}"
        );
        // Refused before it became a request, and audited all the same.
        super::commands::audited("speed setpoint 5002 rpm").await;
        // An operation MQTT does not take, and an unknown command.
        command(&broker, json!(4), "scan", json!({})).await;
        let v = reply(&mut sub, json!(4)).await;
        assert!(
            problem(&v)["detail"]
                .as_str()
                .unwrap()
                .contains("not an operation MQTT takes"),
            "{v}"
        );
        // Malformed: not JSON (no id to echo), not a command message (the
        // id echoed); each says what is wrong.
        publish(broker.port, &topic("conveyor/command"), "{speed: fast", &[]).await;
        let reply_topic = topic("conveyor/reply");
        let m = sub
            .next(WAIT, "the reply to a message that is not JSON", |m| {
                m.topic == reply_topic && m.json()["id"].is_null()
            })
            .await;
        let v = m.json();
        assert_eq!(problem(&v)["type"], "urn:drivegate:problem:invalid-request");
        assert!(
            problem(&v)["detail"]
                .as_str()
                .unwrap()
                .contains("not a JSON command message"),
            "{v}"
        );
        publish(
            broker.port,
            &topic("conveyor/command"),
            r#"{"type":"command","id":"x","body":{}}"#,
            &[],
        )
        .await;
        let v = reply(&mut sub, json!("x")).await;
        assert!(
            problem(&v)["detail"]
                .as_str()
                .unwrap()
                .contains("missing field `op`"),
            "{v}"
        );
        assert!(counter(&d, "drivegate_mqtt_commands_total{result=\"malformed\"}") >= 3.0);
        // The daemon goes on: the next command is confirmed.
        command(&broker, json!(5), "brake", json!({})).await;
        assert_eq!(reply(&mut sub, json!(5)).await["ok"], true);
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_role_and_no_role_refuse_commands_with_words() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        // A viewer role, then none (the default): refused by the core in
        // its words (the role needed, and where MQTT's comes from), the
        // drive untouched.
        for (id, keys) in [
            (
                1,
                "commands = \"viewer\"\nunauthenticated_commands = true",
            ),
            (2, ""),
        ] {
            let words = "this needs the operator role; commands over MQTT have the viewer role ([mqtt] commands)";
            let d = daemon(&broker, keys).await;
            let mut sub = subscribed(&broker, &[&topic("conveyor/reply")]).await;
            command(&broker, json!(id), "activate", json!({})).await;
            let v = reply(&mut sub, json!(id)).await;
            let p = problem(&v);
            assert_eq!(p["type"], "urn:drivegate:problem:forbidden", "{v}");
            assert!(p["detail"].as_str().unwrap().contains(words), "{v}");
            assert!(!d.sim().drive(1).unwrap().status.active());
            sub.stop().await;
            d.stop().await;
        }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_mqtt5_reply_goes_to_the_response_topic_with_the_correlation_data() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let d = daemon(
            &broker,
            "commands = \"operator\"\nunauthenticated_commands = true",
        )
        .await;
        let mut sub = subscribed(&broker, &["app/replies/#"]).await;
        publish(
            broker.port,
            &topic("conveyor/command"),
            r#"{"type":"command","op":"activate"}"#,
            &[
                ("response-topic", "app/replies/7"),
                ("correlation-data", "req-42"),
            ],
        )
        .await;
        let m = sub
            .next(WAIT, "the reply on the response topic", |m| {
                m.topic == "app/replies/7"
            })
            .await;
        assert_eq!(m.correlation, "req-42", "{m:?}");
        let v = m.json();
        assert_eq!(
            (&v["type"], &v["ok"]),
            (&json!("reply"), &json!(true)),
            "{v}"
        );
        eventually(WAIT, "the conveyor active", || {
            d.sim().drive(1)?.status.active().then_some(())
        })
        .await;
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_leaves_the_state_offline() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        std::fs::write(&path, config(&broker.url(), "format = \"json\"")).unwrap();
        let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .arg("serve")
            .arg("--config")
            .arg(&path)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let state = topic("state");
        let mut sub = Sub::start(broker.port, &[&state]);
        sub.next(WAIT, "the state online", |m| {
            m.topic == state && m.payload == "online"
        })
        .await;
        child.start_kill().unwrap(); // SIGKILL
        child.wait().await.unwrap();
        sub.next(WAIT, "the will: the state offline", |m| {
            m.topic == state && m.payload == "offline"
        })
        .await;
        sub.stop().await;
        // Retained: a client that comes later reads it too.
        let mut late = Sub::start(broker.port, &[&state]);
        let m = late
            .next(WAIT, "the retained state", |m| m.topic == state)
            .await;
        assert_eq!((m.payload.as_str(), m.retained), ("offline", true));
        late.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_tell_of_a_lease_ending_and_of_a_drive_offline_and_back() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let d = daemon(
            &broker,
            "commands = \"operator\"\nunauthenticated_commands = true",
        )
        .await;
        let event_topic = topic("conveyor/event");
        let mut sub = subscribed(&broker, &[&event_topic, &topic("conveyor/reply")]).await;
        command(&broker, json!(1), "activate", json!({})).await;
        reply(&mut sub, json!(1)).await;
        command(&broker, json!(2), "mode", json!({"mode": "speed"})).await;
        reply(&mut sub, json!(2)).await;
        // A setpoint with a lease of its own that nobody renews: its end
        // and its stop are news on the drive's event topic.
        command(
            &broker,
            json!(3),
            "setpoint",
            json!({"speed_rpm": 100, "lease_ms": 300}),
        )
        .await;
        let v = reply(&mut sub, json!(3)).await;
        assert_eq!(v["ok"], true, "{v}");
        // Held by the MQTT session, not a WebSocket, and not its
        // communication-loss lease: the one asked for.
        let lease = &v["result"]["lease"];
        assert_eq!(
            (&lease["lease_ms"], &lease["comm_loss"], &lease["websocket"]),
            (&json!(300), &json!(false), &json!(false)),
            "{v}"
        );
        let m = sub
            .next(WAIT, "the lease's end", |m| {
                m.topic == event_topic && m.json()["type"] == "lease-expired"
            })
            .await;
        let v = m.json();
        assert_eq!(
            (&v["drive"], &v["action"]),
            (&json!("conveyor"), &json!("zero-speed")),
            "{v}"
        );
        // The drive stops answering: offline, with its alarm; then back.
        d.sim().set_silent(1, true);
        // The bus's news and the core's alarm, in either order.
        let (mut offline, mut alarm) = (false, false);
        while !(offline && alarm) {
            let m = sub
                .next(WAIT, "the conveyor offline, and its alarm", |m| {
                    m.topic == event_topic
                        && matches!(m.json()["type"].as_str(), Some("offline" | "alarm-raised"))
                })
                .await;
            let v = m.json();
            if v["type"] == "offline" {
                offline = true;
            } else {
                assert_eq!(v["alarm"]["kind"], "offline", "{v}");
                alarm = true;
            }
        }
        d.sim().set_silent(1, false);
        sub.next(WAIT, "the conveyor online again", |m| {
            m.topic == event_topic && m.json()["type"] == "online"
        })
        .await;
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn losing_the_broker_stops_what_json_commands_started() {
    bounded(Duration::from_secs(90), async {
        let mut broker = Mosquitto::start();
        let d = daemon(
            &broker,
            "commands = \"operator\"\nunauthenticated_commands = true\ncomm_loss_ms = 500",
        )
        .await;
        let mut sub = subscribed(&broker, &[&topic("conveyor/reply")]).await;
        command(&broker, json!(1), "activate", json!({})).await;
        reply(&mut sub, json!(1)).await;
        command(&broker, json!(2), "mode", json!({"mode": "speed"})).await;
        reply(&mut sub, json!(2)).await;
        command(&broker, json!(3), "setpoint", json!({"speed_rpm": 200})).await;
        assert_eq!(reply(&mut sub, json!(3)).await["ok"], true);
        eventually(WAIT, "the conveyor turning", || {
            let s = d.plant.buses()[0].handle.drive(1)?.status?;
            (s.speed_rpm > 100).then_some(())
        })
        .await;
        sub.stop().await;
        broker.stop();
        // The session's communication-loss lease ends after comm_loss_ms.
        eventually(
            WAIT,
            "the conveyor stopped after the broker was lost",
            || {
                let s = d.plant.buses()[0].handle.drive(1)?.status?;
                (s.speed_rpm.abs() <= 2 && d.control().lease(0).is_none()).then_some(())
            },
        )
        .await;
        eventually(WAIT, "the end counted as MQTT's", || {
            (counter(
                &d,
                "drivegate_mqtt_comm_loss_stops_total{bus=\"sim\",reason=\"timeout\"}",
            ) == 1.0)
                .then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}
