//! Input that costs the message, not the connection. A 400 kB retained
//! command (Debian's `mosquitto_pub -r`) waiting on the broker: the
//! Sparkplug node takes it cut to nothing, audits it once (and not again
//! when it comes again), and runs the next DCMD on the same connection;
//! the JSON format's MQTT 5 connection has the broker drop it
//! (Maximum Packet Size) and answers the next command. Malformed payloads
//! cost nothing else either. And the broker configuration of
//! `docs/security.md` pins a client id to its user: a stranger connecting
//! with the node's client id does not knock it off, in either format
//! (without it, it does).

use std::process::Stdio;
use std::time::Duration;

use serde_json::json;

use drivegate::mqtt::metric::Value;

use super::commands::{born, run};
use super::{GROUP, NODE, config};
use crate::support::metrics::counter;
use crate::support::mosquitto::{Mosquitto, Sub, publish, publish_as};
use crate::support::sparkplug::{Host, number};
use crate::support::tools;
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);
const LARGE: usize = 400_000;

/// Publishes `bytes` bytes of `x` on `topic`, QoS 1, retained if
/// `retain`, with Debian's `mosquitto_pub` (MQTT 3.1.1), as `login` if
/// given.
async fn publish_large(
    port: u16,
    login: Option<(&str, &str)>,
    topic: &str,
    bytes: usize,
    retain: bool,
) -> std::process::Output {
    publish_bytes(port, login, topic, &vec![b'x'; bytes], retain).await
}

async fn publish_bytes(
    port: u16,
    login: Option<(&str, &str)>,
    topic: &str,
    payload: &[u8],
    retain: bool,
) -> std::process::Output {
    let file = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(file.path(), payload).unwrap();
    let mut cmd = tokio::process::Command::new("mosquitto_pub");
    cmd.args(["-h", "127.0.0.1", "-p", &port.to_string(), "-q", "1"]);
    if let Some((user, password)) = login {
        cmd.args(["-u", user, "-P", password]);
    }
    if retain {
        cmd.arg("-r");
    }
    cmd.args(["-t", topic])
        .arg("-f")
        .arg(file.path())
        .stdin(Stdio::null())
        .output()
        .await
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto_pub", &e)))
}

/// The audit lines of messages dropped for their size on `topic`.
fn audited(topic: &str) -> usize {
    crate::support::logs::log_text()
        .lines()
        .filter(|l| {
            l.contains("drivegate::audit")
                && l.contains("message dropped: larger than the face takes")
                && l.contains(topic)
        })
        .count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_retained_dcmd_costs_the_message_not_the_sparkplug_connection() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let topic = format!("spBv1.0/{GROUP}/DCMD/{NODE}/conveyor");
        let sent = publish_large(broker.port, None, &topic, LARGE, true).await;
        assert!(sent.status.success(), "{sent:?}");
        crate::support::logs::capture_logs();
        let mut host = Host::connect(broker.port, "large-host", None).await;
        let d = TestDaemon::start(&config(
            &broker.url(),
            "commands = \"operator\"\nunauthenticated_commands = true",
        ))
        .await;
        born(&mut host).await;
        eventually(WAIT, "the large DCMD counted", || {
            (counter(&d, "drivegate_mqtt_messages_too_large_total") >= 1.0).then_some(())
        })
        .await;
        assert_eq!(audited(&topic), 1, "audited once");
        // The same connection takes the next DCMD.
        run(&host, "conveyor", 90.0).await;
        host.next(WAIT, "the conveyor turning", |m| {
            m.is("DDATA", Some("conveyor"))
                && m.value("status/speed_rpm")
                    .and_then(|v| number(&v))
                    .is_some_and(|s| s > 45.0)
        })
        .await;
        // The same message again: counted, not audited again.
        let again = publish_large(broker.port, None, &topic, LARGE, false).await;
        assert!(again.status.success());
        eventually(WAIT, "the second large DCMD counted", || {
            (counter(&d, "drivegate_mqtt_messages_too_large_total") >= 2.0).then_some(())
        })
        .await;
        assert_eq!(audited(&topic), 1, "audited once, not at each arrival");
        // A DCMD that is no Sparkplug payload is answered, and costs
        // nothing else.
        // (0xff: a field tag that never ends.)
        let garbage = publish_bytes(broker.port, None, &topic, &[0xff; 100], false).await;
        assert!(garbage.status.success());
        host.next(WAIT, "the garbage DCMD answered", |m| {
            m.is("DDATA", Some("conveyor"))
                && matches!(m.value("command/last_result"),
                    Some(Value::Text(t)) if t.contains("no Sparkplug B payload"))
        })
        .await;
        assert_eq!(counter(&d, "drivegate_mqtt_reconnects_total"), 0.0);
        assert_eq!(counter(&d, "drivegate_mqtt_connection_errors_total"), 0.0);
        assert!(
            !host.seen.iter().any(|m| m.is("NDEATH", None)),
            "the node died on the way"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_retained_command_costs_the_message_not_the_json_connection() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let prefix = format!("drivegate/{NODE}");
        let topic = format!("{prefix}/conveyor/command");
        let sent = publish_large(broker.port, None, &topic, LARGE, true).await;
        assert!(sent.status.success(), "{sent:?}");
        let d = TestDaemon::start(&config(
            &broker.url(),
            "format = \"json\"\ncommands = \"operator\"\nunauthenticated_commands = true",
        ))
        .await;
        let state = format!("{prefix}/state");
        let replies = format!("{prefix}/+/reply");
        let mut sub = Sub::start(broker.port, &[&state, &replies]);
        sub.next(WAIT, "the state online", |m| {
            m.topic == state && m.payload == "online"
        })
        .await;
        // The broker dropped it: MQTT 5's Maximum Packet Size in CONNECT.
        eventually(WAIT, "the broker dropping the large command", || {
            broker
                .log()
                .contains(&format!(
                    "Dropping too large outgoing PUBLISH for drivegate-json-{NODE}"
                ))
                .then_some(())
        })
        .await;
        // The same connection answers the next command, and a malformed one.
        let status = json!({"type": "command", "id": 1, "op": "status"});
        publish(broker.port, &topic, &status.to_string(), &[]).await;
        let reply = sub
            .next(WAIT, "the status reply", |m| m.topic.ends_with("/reply"))
            .await;
        assert_eq!(reply.json()["id"], 1, "{reply:?}");
        assert_eq!(reply.json()["ok"], true, "{reply:?}");
        publish(broker.port, &topic, "{not json", &[]).await;
        let refused = sub
            .next(WAIT, "the malformed command's reply", |m| {
                m.topic.ends_with("/reply") && m.json()["ok"] == false
            })
            .await;
        assert_eq!(refused.json()["problem"]["status"], 400, "{refused:?}");
        assert_eq!(counter(&d, "drivegate_mqtt_reconnects_total"), 0.0);
        assert_eq!(counter(&d, "drivegate_mqtt_connection_errors_total"), 0.0);
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

const GW1: (&str, &str) = ("gw1", "gw1-secret");
const SCADA: (&str, &str) = ("scada", "scada-secret");
const HMI: (&str, &str) = ("hmi", "hmi-secret");
const HISTORIAN: (&str, &str) = ("historian", "historian-secret");

/// The block of `docs/security.md` that starts with `first`, as the page
/// shows it.
fn block_of_the_docs(first: &str) -> String {
    let page =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/security.md")).unwrap();
    let start = page
        .find(first)
        .unwrap_or_else(|| panic!("docs/security.md shows no block {first:?}"));
    let block = &page[start..];
    block[..block.find("```").expect("the block ends")].to_string()
}

/// A client connected as `login` with client id `id` (Debian's
/// `mosquitto_sub`, which reconnects when it is knocked off).
fn stranger(port: u16, login: Option<(&str, &str)>, id: &str) -> tokio::process::Child {
    let mut cmd = tokio::process::Command::new("mosquitto_sub");
    cmd.args(["-h", "127.0.0.1", "-p", &port.to_string(), "-i", id]);
    if let Some((user, password)) = login {
        cmd.args(["-u", user, "-P", password]);
    }
    cmd.args(["-t", "spBv1.0/#"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto_sub", &e)))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_cannot_take_the_nodes_client_id_on_the_documented_broker() {
    bounded(Duration::from_secs(90), async {
        let client_id = format!("drivegate-{GROUP}-{NODE}");
        // The broker of docs/security.md: a user's client id is its name.
        let broker = Mosquitto::start_with_users_and(
            &[GW1, SCADA, HMI],
            &block_of_the_docs("# mosquitto acl_file, Sparkplug"),
            &block_of_the_docs("# mosquitto.conf, drivegate's broker"),
        );
        let mut host = Host::connect_as(broker.port, "scada-host", None, Some(SCADA)).await;
        let dir = tempfile::tempdir().unwrap();
        let password = dir.path().join("mqtt-password");
        std::fs::write(&password, format!("{}\n", GW1.1)).unwrap();
        let d = TestDaemon::start(&config(
            &broker.url(),
            &format!(
                "username = \"{}\"\npassword_file = \"{}\"",
                GW1.0,
                password.display()
            ),
        ))
        .await;
        born(&mut host).await;
        // Another user of the broker connects with the node's client id.
        let mut hmi = stranger(broker.port, Some(HMI), &client_id);
        eventually(WAIT, "the stranger connected", || {
            broker.log().contains("u'hmi'").then_some(())
        })
        .await;
        // The host asks for a rebirth: had the node been knocked off, its
        // NDEATH would have come before the births.
        host.rebirth(GROUP, NODE).await;
        born(&mut host).await;
        assert!(
            !host.seen.iter().any(|m| m.is("NDEATH", None)),
            "the stranger knocked the node off"
        );
        assert_eq!(counter(&d, "drivegate_mqtt_reconnects_total"), 0.0);
        let _ = hmi.kill().await;
        // The broker refuses the large message where it is published.
        let large = publish_large(
            broker.port,
            Some(SCADA),
            &format!("spBv1.0/{GROUP}/DCMD/{NODE}/conveyor"),
            LARGE,
            true,
        )
        .await;
        assert!(!large.status.success(), "the broker took {LARGE} bytes");
        d.stop().await;

        // Without the pinning (any broker of anonymous clients), the same
        // stranger knocks the node off; the node comes back, and the two
        // are not left to fight in a fast loop.
        let open = Mosquitto::start();
        let d = TestDaemon::start(&config(&open.url(), "")).await;
        let mut host = Host::connect(open.port, "open-host", None).await;
        host.rebirth(GROUP, NODE).await;
        born(&mut host).await;
        let mut thief = stranger(open.port, None, &client_id);
        host.next(WAIT, "the node knocked off (its NDEATH)", |m| {
            m.is("NDEATH", None)
        })
        .await;
        let _ = thief.kill().await;
        eventually(WAIT, "the node back", || {
            (counter(&d, "drivegate_mqtt_reconnects_total") >= 1.0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

/// The JSON format's node on the same broker configuration: another
/// broker user connecting with its client id (`drivegate-json-gw1`) does
/// not knock it off, and a command the SCADA user publishes after it is
/// answered on the node's first connection.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_cannot_take_the_json_nodes_client_id_on_the_documented_broker() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start_with_users_and(
            &[GW1, SCADA, HMI, HISTORIAN],
            &block_of_the_docs("# mosquitto acl_file, JSON format"),
            &block_of_the_docs("# mosquitto.conf, drivegate's broker"),
        );
        let dir = tempfile::tempdir().unwrap();
        let password = dir.path().join("mqtt-password");
        std::fs::write(&password, format!("{}\n", GW1.1)).unwrap();
        let d = TestDaemon::start(&config(
            &broker.url(),
            &format!(
                "format = \"json\"\ncommands = \"operator\"\nusername = \"{}\"\npassword_file = \"{}\"",
                GW1.0,
                password.display()
            ),
        ))
        .await;
        let prefix = format!("drivegate/{NODE}");
        let state = format!("{prefix}/state");
        let replies = format!("{prefix}/+/reply");
        // Every user reads; a client id is its user's name, so the reader
        // is a user of its own, apart from the SCADA user who commands.
        let mut sub = Sub::start_as(broker.port, Some(HISTORIAN), &[&state, &replies]);
        sub.next(WAIT, "the state online", |m| {
            m.topic == state && m.payload == "online"
        })
        .await;
        let mut hmi = stranger(broker.port, Some(HMI), &format!("drivegate-json-{NODE}"));
        eventually(WAIT, "the stranger connected", || {
            broker.log().contains("u'hmi'").then_some(())
        })
        .await;
        let status = json!({"type": "command", "id": "after", "op": "status"});
        publish_as(
            broker.port,
            SCADA,
            "scada-client",
            &format!("{prefix}/conveyor/command"),
            status.to_string().as_bytes(),
        )
        .await;
        let reply = sub
            .next(WAIT, "the reply after the stranger came", |m| {
                m.topic.ends_with("/reply")
            })
            .await;
        assert_eq!(
            (&reply.json()["id"], &reply.json()["ok"]),
            (&json!("after"), &json!(true)),
            "{reply:?}"
        );
        assert_eq!(counter(&d, "drivegate_mqtt_reconnects_total"), 0.0);
        assert!(
            !broker.log().contains("already connected, closing old connection"),
            "{}",
            broker.log()
        );
        let _ = hmi.kill().await;
        sub.stop().await;
        d.stop().await;
    })
    .await;
}
