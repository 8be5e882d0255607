//! The OPC UA face as both third-party clients browse and read it:
//! endpoints, the drives' nodes, values with their units, HistoryRead, an
//! anonymous write refused (the clients and the daemon: `opcua.rs`).

use serde_json::Value;

use super::opcua::{Client, DRIVE_CHILDREN, LIMIT, Ua, step};
use crate::support::wait::bounded;

/// Endpoints, browse, read with units, the anonymous write and HistoryRead,
/// as both clients see them, each client running its scenarios in one
/// process, both at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_clients_browse_read_with_units_and_read_history() {
    bounded(LIMIT, async {
        let ua = Ua::start(None).await;
        let pki = ua.pki.parent().unwrap().join("node-pki");
        let (all, node) = tokio::join!(
            Client::asyncua(
                &ua.url,
                "endpoints,browse,read,described,anonymous-write,history",
                &["--drive".into(), "lift".into()],
            )
            .steps(),
            Client::node(
                &ua.url,
                "endpoints,browse,read,described,history",
                &pki,
                &[]
            )
            .steps(),
        );
        let endpoints = step(&all, "endpoints")["endpoints"]
            .as_array()
            .unwrap()
            .clone();
        let policies: Vec<_> = endpoints
            .iter()
            .map(|e| e["policy"].as_str().unwrap())
            .collect();
        assert!(
            policies.contains(&"None") && policies.contains(&"Basic256Sha256"),
            "{endpoints:?}"
        );
        for e in &endpoints {
            assert_eq!(
                e["tokens"],
                serde_json::json!(["Anonymous", "Certificate", "UserName"]),
                "{e}"
            );
            if e["policy"] == "Basic256Sha256" {
                assert_eq!(e["mode"], "SignAndEncrypt");
            }
        }

        let browse = step(&all, "browse");
        assert_eq!(
            browse["drives"],
            serde_json::json!(["conveyor", "feeder", "lift", "turntable"])
        );
        assert_eq!(browse["type"], "DriveType");
        assert_eq!(browse["buses"], serde_json::json!(["sim"]));
        for child in DRIVE_CHILDREN {
            assert!(
                browse["children"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|c| c == child),
                "{child}: {browse}"
            );
        }

        let read = step(&all, "read");
        let speed = &read["values"]["Speed"];
        assert_eq!(
            (speed["status"].as_str(), speed["type"].as_str()),
            (Some("Good"), Some("Double"))
        );
        // UNECE codes: RPM, CEL, VLT.
        assert_eq!(
            (speed["unit"].as_str(), speed["unit_id"].as_u64()),
            (Some("r/min"), Some(5_394_509))
        );
        assert_eq!(read["values"]["Temperature"]["unit_id"], 4_408_652);
        assert_eq!(read["values"]["Voltage"]["unit_id"], 5_655_636);
        assert!(
            speed["low"].as_f64().unwrap() < 0.0 && speed["high"].as_f64().unwrap() > 0.0,
            "{speed}"
        );
        assert!(
            speed["source_timestamp"]
                .as_str()
                .is_some_and(|t| !t.is_empty()),
            "{speed}"
        );
        assert_eq!(read["values"]["Turns"]["type"], "Int32");
        assert_eq!(read["values"]["FaultCode"]["type"], "UInt16");
        assert_eq!(read["values"]["Online"]["value"], true);
        // The poll's period is the fastest sampling.
        assert!(read["min_sampling_ms"].as_f64().unwrap() > 0.0, "{read}");

        // Every node under a drive says what it is; the drive's children
        // come in the manual's order; Mode is a DriveMode, an enumeration
        // with its names; SetMode's argument says what it takes.
        let described = step(&all, "described");
        assert_eq!(
            described["order"],
            serde_json::json!(DRIVE_CHILDREN),
            "{described}"
        );
        assert_eq!(described["missing"], serde_json::json!([]), "{described}");
        assert!(described["nodes"].as_u64().unwrap() > 40, "{described}");
        assert_eq!(described["mode_type"], "DriveMode");
        assert_eq!(
            described["enum_strings"],
            serde_json::json!(["OpenLoop", "Speed", "Position", "Torque"])
        );
        assert!(described["mode_value"].is_i64(), "{described}");
        assert_eq!(described["argument"]["name"], "Mode");
        assert!(
            described["argument"]["description"]
                .as_str()
                .unwrap()
                .contains("speed, position or torque"),
            "{described}"
        );
        assert_eq!(read["values"]["Mode"]["type"], "Int32", "{read}");

        let refused = step(&all, "anonymous-write");
        assert_eq!(refused["status"], "BadUserAccessDenied", "{refused}");
        // Its UserAccessLevel shows no write (CurrentRead only).
        assert_eq!(refused["user_access_level"], 1, "{refused}");

        let history = step(&all, "history");
        assert!(history["count"].as_u64().unwrap() > 5, "{history}");
        assert_eq!(history["five"], 5, "{history}");

        // node-opcua: the same server through a second implementation.
        node_sees_the_same(&node, endpoints.len(), &browse["drives"]);
    })
    .await;
}

/// node-opcua's view (its steps `node`): as many endpoints, the same
/// drives, Speed read with its unit, HistoryRead.
fn node_sees_the_same(node: &[Value], endpoints: usize, drives: &Value) {
    assert_eq!(
        step(node, "endpoints")["endpoints"]
            .as_array()
            .unwrap()
            .len(),
        endpoints
    );
    assert_eq!(step(node, "browse")["drives"], *drives);
    let described = step(node, "described");
    assert_eq!(
        described["order"],
        serde_json::json!(DRIVE_CHILDREN),
        "{described}"
    );
    assert_eq!(described["missing"], serde_json::json!([]), "{described}");
    assert_eq!(described["mode_type"], "DriveMode");
    assert_eq!(
        described["enum_strings"],
        serde_json::json!(["OpenLoop", "Speed", "Position", "Torque"])
    );
    let speed = &step(node, "read")["values"]["Speed"];
    assert_eq!(
        (speed["status"].as_str(), speed["unit_id"].as_u64()),
        (Some("Good"), Some(5_394_509))
    );
    let history = step(node, "history");
    assert_eq!(history["status"], "Good");
    assert!(history["count"].as_u64().unwrap() > 5, "{history}");
}
