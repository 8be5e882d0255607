//! A reload that changes `[mqtt]` restarts the MQTT face with the new
//! section (`src/daemon/supervisor.rs`): the old node says goodbye (its NDEATH), its
//! session's leases end with `comm_loss_action` at once, as for a lost
//! broker, and the new node is born under its new name; the HTTP API and
//! the drives run on. `[mqtt]` removed stops the face for good.

use std::time::Duration;

use super::commands::{born, run};
use super::{NODE, config};
use crate::support::api::Api;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{Host, number};
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_changed_mqtt_section_restarts_the_face_and_ends_its_leases_with_their_stop() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "reload-host", None).await;
        // A minute of communication loss: the stop below is the restart's.
        let keys = "commands = \"operator\"\nunauthenticated_commands = true\ncomm_loss_ms = 60000";
        let before = config(&broker.url(), keys);
        let d = TestDaemon::reloadable(&before).await;
        born(&mut host).await;
        run(&host, "conveyor", 200.0).await;
        host.next(WAIT, "the conveyor turning", |m| {
            m.is("DDATA", Some("conveyor"))
                && m.value("status/speed_rpm")
                    .and_then(|v| number(&v))
                    .is_some_and(|s| s > 100.0)
        })
        .await;
        assert!(
            d.control().lease(0).is_some(),
            "MQTT's lease on the conveyor"
        );

        let from = format!("node_id = \"{NODE}\"");
        assert!(before.contains(&from), "{before}");
        d.rewrite(&before.replace(&from, "node_id = \"gw2\""));
        let reply = Api::new(d.http, None)
            .post_empty("/api/v1/config/reload")
            .await
            .expect(200);
        assert_eq!(
            reply["changes"],
            serde_json::json!(["MQTT face restarted with the new [mqtt]"]),
            "{reply}"
        );
        assert_eq!(reply["problems"], serde_json::json!([]), "{reply}");
        let ndeath = host
            .next(WAIT, "the old node's NDEATH", |m| m.is("NDEATH", None))
            .await;
        assert!(
            ndeath.topic.ends_with(&format!("/NDEATH/{NODE}")),
            "{}",
            ndeath.topic
        );
        // Its lease ended with its stop when the old face stopped, not a
        // minute later.
        eventually(WAIT, "the conveyor stopped", || {
            let s = d.plant.buses()[0].handle.drive(1)?.status?;
            (s.speed_rpm.abs() <= 2 && d.control().lease(0).is_none()).then_some(())
        })
        .await;
        let nbirth = host
            .next(WAIT, "the new node's NBIRTH", |m| m.is("NBIRTH", None))
            .await;
        assert!(nbirth.topic.ends_with("/NBIRTH/gw2"), "{}", nbirth.topic);
        // The new node takes commands.
        host.dcmd(
            super::GROUP,
            "gw2",
            "conveyor",
            vec![crate::support::sparkplug::double_metric(
                "setpoint/speed_rpm",
                150.0,
            )],
        )
        .await;
        host.next(WAIT, "the conveyor turning again", |m| {
            m.topic.contains("/gw2/")
                && m.is("DDATA", Some("conveyor"))
                && m.value("status/speed_rpm")
                    .and_then(|v| number(&v))
                    .is_some_and(|s| s > 100.0)
        })
        .await;

        // [mqtt] removed: the face says goodbye and is gone from /readyz.
        let api = Api::new(d.http, None);
        let without = crate::support::config::ConfigBuilder::four_drives()
            .modbus_tcp_off()
            .toml();
        d.rewrite(&without);
        let reply = api.post_empty("/api/v1/config/reload").await.expect(200);
        assert_eq!(
            reply["changes"],
            serde_json::json!(["MQTT face stopped ([mqtt] removed)"]),
            "{reply}"
        );
        let ndeath = host
            .next(WAIT, "the new node's NDEATH", |m| m.is("NDEATH", None))
            .await;
        assert!(ndeath.topic.ends_with("/NDEATH/gw2"), "{}", ndeath.topic);
        let ready = api.get("/readyz").await.expect(200);
        assert!(ready.get("mqtt").is_none(), "{ready}");
        d.stop().await;
    })
    .await;
}
