//! A face whose task panics is restarted alone, with a growing wait, and
//! said down with why: `/readyz`, the log and
//! `drivegate_face_restarts_total`; the API and Modbus TCP serve on
//! meanwhile. The panic is a real one: the MQTT 5 client's assertion on a
//! keepalive under 5 s, reached by a configuration made in code past the
//! check that now refuses it (`check-config` names the range).

use std::time::Duration;

use drivegate::config::Config;
use drivegate::config::mqtt::Format;

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::metrics::counter;
use crate::support::{TestDaemon, bounded, eventually};

const PANIC: &str = "Keep alives should be >= 5 secs";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_face_is_restarted_alone_and_said_down_with_why() {
    bounded(Duration::from_secs(60), async {
        crate::support::logs::capture_logs();
        // Nothing listens on port 1: the face panics before connecting.
        let toml = ConfigBuilder::four_drives()
            .section(
                "mqtt",
                "broker = \"mqtt://127.0.0.1:1\"\nnode_id = \"crash\"\nkeepalive_s = 2",
            )
            .toml();
        let refused = Config::parse(
            &toml.replace("keepalive_s = 2", "keepalive_s = 2\nformat = \"json\""),
            "drivegate.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(refused.contains("valid 5 to 3600"), "{refused}");
        let mut config = Config::parse(&toml, "test config").unwrap();
        config.mqtt.as_mut().unwrap().format = Format::Json;
        let d = TestDaemon::start_config(config).await;
        let api = Api::new(d.http, None);

        let down = eventually(Duration::from_secs(10), "the MQTT face said down", || {
            d.metrics
                .face_health()
                .states()
                .into_iter()
                .find(|s| s.down.is_some())
        })
        .await;
        assert_eq!(down.face.key(), "mqtt");
        let ready = api.get("/readyz").await.body;
        let face = &ready["faces"][0];
        assert_eq!(face["face"], "mqtt", "{ready:#}");
        assert_eq!(face["name"], "MQTT face", "{ready:#}");
        assert!(
            face["down_why"]
                .as_str()
                .is_some_and(|w| w == format!("it panicked: {PANIC}")),
            "{ready:#}"
        );
        assert!(face["restart_at"].is_string(), "{ready:#}");

        // Started again (and crashing again: the configuration stays).
        eventually(Duration::from_secs(20), "two restarts", || {
            (counter(&d, "drivegate_face_restarts_total{face=\"mqtt\"}") >= 2.0).then_some(())
        })
        .await;
        assert_eq!(
            counter(&d, "drivegate_face_restarts_total{face=\"http\"}"),
            0.0
        );
        // The other faces serve on.
        let status = api.get("/api/v1/drives/conveyor/status").await;
        assert_eq!(status.status, 200, "{:#}", status.body);
        let modbus = d.modbus_tcp.expect("Modbus TCP");
        tokio::net::TcpStream::connect(modbus)
            .await
            .expect("Modbus TCP serves");
        let log = crate::support::logs::log_text();
        assert!(
            log.lines().any(|l| l.contains(&format!(
                "the MQTT face is down: it panicked: {PANIC}; it is started again in"
            ))),
            "no log line of the crash"
        );
        d.stop().await;
    })
    .await;
}
