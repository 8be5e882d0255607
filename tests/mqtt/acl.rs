//! Who may command over MQTT is the broker's to decide: MQTT carries no
//! publisher identity. With the `acl_file` of `docs/security.md` (read
//! from the page itself) and users in a password file made by
//! `mosquitto_passwd`, a DCMD from a user other than the SCADA host's is
//! not delivered and moves no motor, the SCADA user's does; the audit log,
//! the lease and the bus monitor say only what is known of the sender. The
//! same for the JSON format's commands, with its `acl_file`.
//! Without a login the broker authenticates, `check-config` and `serve`
//! refuse commands, naming both ways (and `unauthenticated_commands`).

use std::process::Stdio;
use std::time::Duration;

use drivegate::mqtt::metric::Value;
use drivegate::mqtt::sparkplug_b::Payload;
use prost::Message;
use serde_json::json;
use tokio::io::AsyncBufReadExt;

use super::commands::{born, run};
use super::{GROUP, NODE, config};
use crate::support::api::Api;
use crate::support::mosquitto::{Mosquitto, Sub, publish_as};
use crate::support::sparkplug::{Host, bool_metric, double_metric, number, string_metric};
use crate::support::{TestDaemon, bounded};

const WAIT: Duration = Duration::from_secs(20);
const GW1: (&str, &str) = ("gw1", "gw1-secret");
const SCADA: (&str, &str) = ("scada", "scada-secret");
const HMI: (&str, &str) = ("hmi", "hmi-secret");

/// The mosquitto `acl_file` of `docs/security.md` whose first line
/// starts with `first`, as the page shows it.
fn acl_from_the_docs(first: &str) -> String {
    let page =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/security.md")).unwrap();
    let start = page
        .find(first)
        .unwrap_or_else(|| panic!("docs/security.md shows no acl_file {first:?}"));
    let block = &page[start..];
    block[..block.find("```").expect("the block ends")].to_string()
}

/// `keys` of `[mqtt]` logging in as `gw1`, its password in a file of `dir`.
fn logged_in(dir: &std::path::Path, keys: &str) -> String {
    let password = dir.join("mqtt-password");
    std::fs::write(&password, format!("{}\n", GW1.1)).unwrap();
    format!(
        "username = \"{}\"\npassword_file = \"{}\"\n{keys}",
        GW1.0,
        password.display()
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dcmd_from_another_broker_user_moves_no_motor() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start_with_users(
            &[GW1, SCADA, HMI],
            &acl_from_the_docs("# mosquitto acl_file, Sparkplug"),
        );
        let mut host =
            Host::connect_as(broker.port, "scada-host", Some("scada"), Some(SCADA)).await;
        host.announce(true).await;
        crate::support::logs::capture_logs();
        let dir = tempfile::tempdir().unwrap();
        let keys = logged_in(
            dir.path(),
            "primary_host_id = \"scada\"\ncommands = \"operator\"\ncomm_loss_ms = 60000",
        );
        let d = TestDaemon::start(&config(&broker.url(), &keys)).await;
        born(&mut host).await;

        // Another user of the broker (an HMI, a laptop) sends the DCMD
        // that would run the conveyor: the broker's ACL drops it.
        let dcmd = Payload {
            timestamp: Some(1),
            metrics: vec![
                bool_metric("command/activate", true),
                string_metric("mode", "speed"),
                double_metric("setpoint/speed_rpm", 300.0),
            ],
            ..Default::default()
        };
        let topic = format!("spBv1.0/{GROUP}/DCMD/{NODE}/conveyor");
        publish_as(
            broker.port,
            HMI,
            "hmi-console",
            &topic,
            &dcmd.encode_to_vec(),
        )
        .await;
        assert!(
            broker.log().contains(&format!(
                "Denied PUBLISH from hmi-console (d0, q1, r0, m1, '{topic}'"
            )),
            "the broker did not deny the HMI's DCMD: {}",
            broker.log()
        );
        // Nor may it speak as the primary host.
        publish_as(
            broker.port,
            HMI,
            "hmi-console",
            "spBv1.0/STATE/scada",
            br#"{"online":false,"timestamp":1}"#,
        )
        .await;
        assert!(
            broker
                .log()
                .contains("Denied PUBLISH from hmi-console (d0, q1, r0, m1, 'spBv1.0/STATE/scada'")
        );

        // The SCADA user's DCMD runs the lift (sent after the HMI's was
        // acknowledged by the broker: had the HMI's been delivered, it
        // would have reached the daemon first).
        run(&host, "lift", 120.0).await;
        host.next(WAIT, "the lift turning", |m| {
            m.is("DDATA", Some("lift"))
                && m.value("status/speed_rpm")
                    .and_then(|v| number(&v))
                    .is_some_and(|s| s > 60.0)
        })
        .await;
        let conveyor = host
            .seen
            .iter()
            .filter(|m| m.device.as_deref() == Some("conveyor"))
            .filter_map(|m| m.value("setpoint/speed_rpm"))
            .collect::<Vec<_>>();
        assert!(
            !conveyor.contains(&Value::Double(300.0)),
            "the HMI's setpoint was taken: {conveyor:?}"
        );
        // The conveyor never moved: only the SCADA user's three commands
        // were taken, the conveyor holds no lease and stands still.
        assert_eq!(
            crate::support::metrics::counter(
                &d,
                "drivegate_mqtt_commands_total{result=\"confirmed\"}"
            ),
            3.0
        );
        let index = |name: &str| {
            d.plant
                .drives()
                .iter()
                .position(|x| x.name == name)
                .unwrap()
        };
        assert!(d.control().lease(index("conveyor")).is_none());
        let api = Api::new(d.http, None);
        let status = api.get("/api/v1/drives/conveyor/status").await.expect(200);
        assert_eq!(status["speed_rpm"], 0, "{status:#}");
        assert_eq!(status["active"], false, "{status:#}");

        // Said as it is known: the broker's user, the host only claimed.
        let who = "broker user gw1; primary host \"scada\" claimed";
        let lease = d.control().lease(index("lift")).expect("the lift's lease");
        assert_eq!(&*lease.owner, format!("mqtt {who}"));
        let log = crate::support::logs::log_text();
        assert!(
            log.lines().any(|l| l.contains("drivegate::audit")
                && l.contains("write confirmed")
                && l.contains("face=\"mqtt\"")
                && l.contains(r#"broker user gw1; primary host \"scada\" claimed"#)),
            "no audit line naming the broker's user and the claimed host"
        );
        let frames = api
            .get("/api/v1/buses/sim/monitor/frames?source=mqtt")
            .await
            .expect(200);
        let frames = frames["frames"].as_array().unwrap();
        assert!(!frames.is_empty());
        assert!(frames.iter().all(|f| f["source_who"] == who), "{frames:#?}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_json_formats_commands_from_another_broker_user_move_no_motor() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start_with_users(
            &[GW1, SCADA, HMI],
            &acl_from_the_docs("# mosquitto acl_file, JSON format"),
        );
        crate::support::logs::capture_logs();
        let dir = tempfile::tempdir().unwrap();
        let keys = logged_in(dir.path(), "format = \"json\"\ncommands = \"operator\"");
        let d = TestDaemon::start(&config(&broker.url(), &keys)).await;
        let prefix = format!("drivegate/{NODE}");
        let state = format!("{prefix}/state");
        let replies = format!("{prefix}/+/reply");
        let mut sub = Sub::start_as(broker.port, Some(SCADA), &[&state, &replies]);
        sub.next(WAIT, "the state online", |m| {
            m.topic == state && m.payload == "online"
        })
        .await;
        let command =
            |id: &str| format!(r#"{{"type":"command","id":"{id}","op":"activate","body":{{}}}}"#);
        // Another user's command: dropped by the broker.
        let conveyor = format!("{prefix}/conveyor/command");
        publish_as(
            broker.port,
            HMI,
            "hmi-console",
            &conveyor,
            command("hmi").as_bytes(),
        )
        .await;
        assert!(
            broker.log().contains(&format!(
                "Denied PUBLISH from hmi-console (d0, q1, r0, m1, '{conveyor}'"
            )),
            "{}",
            broker.log()
        );
        // The SCADA user's, sent after it: taken and confirmed.
        let lift = format!("{prefix}/lift/command");
        publish_as(
            broker.port,
            SCADA,
            "scada-client",
            &lift,
            command("scada").as_bytes(),
        )
        .await;
        let reply = sub
            .next(WAIT, "the reply to the SCADA user's command", |m| {
                m.json()["id"] == "scada" || m.json()["id"] == "hmi"
            })
            .await
            .json();
        assert_eq!(
            (&reply["id"], &reply["ok"]),
            (&json!("scada"), &json!(true)),
            "{reply}"
        );
        assert_eq!(
            crate::support::metrics::counter(
                &d,
                "drivegate_mqtt_commands_total{result=\"confirmed\"}"
            ),
            1.0
        );
        let api = Api::new(d.http, None);
        let status = api.get("/api/v1/drives/conveyor/status").await.expect(200);
        assert_eq!(status["active"], false, "{status:#}");
        let log = crate::support::logs::log_text();
        assert!(
            log.lines().any(|l| l.contains("drivegate::audit")
                && l.contains("face=\"mqtt\"")
                && l.contains("who=\"broker user gw1\"")),
            "no audit line naming the broker's user"
        );
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

/// `drivegate` with `args`, its exit status and its output (both streams).
async fn drivegate(args: &[&str]) -> (bool, String) {
    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .await
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_without_a_broker_login_are_refused_naming_both_ways() {
    bounded(Duration::from_secs(60), async {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        let path_text = path.to_str().unwrap();
        std::fs::write(
            &path,
            config("mqtt://127.0.0.1:1", "commands = \"operator\""),
        )
        .unwrap();
        for args in [
            vec!["check-config", path_text],
            vec!["serve", "--config", path_text],
        ] {
            let (ok, text) = drivegate(&args).await;
            assert!(!ok, "{args:?} took commands without a login: {text}");
            for words in [
                "commands = \"operator\"",
                "not authenticated",
                "username and password_file",
                "client certificate (client_cert and client_key) over mqtts://",
                "unauthenticated_commands = true",
            ] {
                assert!(text.contains(words), "{args:?}: no {words:?} in {text}");
            }
        }
        // With a login, the file is valid.
        std::fs::write(
            &path,
            config(
                "mqtt://127.0.0.1:1",
                &logged_in(dir.path(), "commands = \"operator\""),
            ),
        )
        .unwrap();
        let (ok, text) = drivegate(&["check-config", path_text]).await;
        assert!(ok, "{text}");

        // Said on purpose: it starts, and says so at every start.
        std::fs::write(
            &path,
            format!(
                "{}[safety]\nstate_dir = \"{}\"\n",
                config(
                    "mqtt://127.0.0.1:1",
                    "commands = \"operator\"\nunauthenticated_commands = true"
                ),
                dir.path().join("state").display()
            ),
        )
        .unwrap();
        let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["serve", "--config", path_text])
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let mut lines = tokio::io::BufReader::new(child.stderr.take().unwrap()).lines();
        let mut seen = Vec::new();
        let warned = tokio::time::timeout(WAIT, async {
            while let Ok(Some(line)) = lines.next_line().await {
                let found = line.contains("unauthenticated_commands = true")
                    && line.contains("unauthenticated broker 127.0.0.1:1");
                seen.push(line);
                if found {
                    return true;
                }
            }
            false
        })
        .await;
        assert!(
            matches!(warned, Ok(true)),
            "no warning at the start: {seen:#?}"
        );
        child.start_kill().unwrap();
        child.wait().await.unwrap();
    })
    .await;
}
