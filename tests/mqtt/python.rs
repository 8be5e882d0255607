//! A third-party Sparkplug B library, pysparkplug, decodes the births.

use std::path::Path;
use std::time::Duration;

use super::{GROUP, NODE, config};
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::Host;
use crate::support::{TestDaemon, bounded, tools};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pysparkplug_decodes_our_births() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "py-check-host", None).await;
        let d = TestDaemon::start(&config(&broker.url(), "")).await;
        host.next(Duration::from_secs(20), "NBIRTH", |m| m.is("NBIRTH", None))
            .await;
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/sparkplug_host.py");
        let out = tokio::process::Command::new("python3")
            .arg(&script)
            .args([&broker.port.to_string(), GROUP, NODE, "4"])
            .output()
            .await
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run("python3", &e)));
        let stderr = String::from_utf8_lossy(&out.stderr);
        if stderr.contains("No module named 'pysparkplug'") {
            panic!(
                "pysparkplug is missing: {}",
                tools::how_to_get("pysparkplug")
            );
        }
        assert!(out.status.success(), "{stderr}");
        let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        let nbirth = lines
            .iter()
            .find(|l| l["type"] == "NBIRTH")
            .expect("pysparkplug decoded an NBIRTH");
        assert_eq!(nbirth["seq"], 0);
        assert_eq!(nbirth["metrics"]["bdSeq"]["datatype"], "INT64");
        assert_eq!(nbirth["metrics"]["Node Control/Rebirth"]["value"], false);
        let conveyor = lines
            .iter()
            .find(|l| l["type"] == "DBIRTH" && l["device"] == "conveyor")
            .expect("pysparkplug decoded the conveyor's DBIRTH");
        let m = &conveyor["metrics"];
        assert_eq!(m["status/speed_rpm"]["datatype"], "INT32");
        assert_eq!(m["status/mode"]["datatype"], "STRING");
        assert_eq!(m["status/active"]["value"], false);
        assert_eq!(m["setpoint/speed_rpm"]["datatype"], "DOUBLE");
        assert!(m["status/voltage_v"]["value"].as_u64().unwrap() > 0);
        d.stop().await;
    })
    .await;
}
