//! The Grafana dashboard: importable structure (datasource and drive
//! variables, unique ids, a grid without overlaps) and every metric its
//! queries use is one the daemon exports, compared against a real render.

use std::collections::BTreeSet;
use std::time::Duration;

use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{ConfigCommand, DriveRequest, Fault};
use serde_json::Value;

const DASHBOARD: &str = include_str!("../../deploy/grafana/drivegate.json");

/// Every `drivegate_*` name in a PromQL expression.
fn metric_names(expr: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut rest = expr;
    while let Some(i) = rest.find("drivegate_") {
        let tail = &rest[i..];
        let end = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        names.push(tail[..end].to_string());
        rest = &tail[end..];
    }
    names
}

/// Every query of the dashboard: panel targets and variable queries.
fn queries(dashboard: &Value) -> Vec<(String, String)> {
    let mut out = Vec::new();
    for panel in dashboard["panels"].as_array().unwrap() {
        for target in panel["targets"].as_array().into_iter().flatten() {
            let title = panel["title"].as_str().unwrap().to_string();
            out.push((title, target["expr"].as_str().unwrap().to_string()));
        }
    }
    for var in dashboard["templating"]["list"].as_array().unwrap() {
        if var["type"] == "query" {
            let q = var["query"]["query"].as_str().unwrap().to_string();
            out.push((format!("variable {}", var["name"]), q));
        }
    }
    out
}

#[test]
fn dashboard_is_importable() {
    let d: Value = serde_json::from_str(DASHBOARD).expect("valid JSON");
    assert_eq!(d["uid"], "drivegate");
    assert!(d["schemaVersion"].as_u64().unwrap() >= 36);
    let vars = d["templating"]["list"].as_array().unwrap();
    let var = |name: &str| vars.iter().find(|v| v["name"] == name).unwrap();
    assert_eq!(var("datasource")["type"], "datasource");
    assert_eq!(var("datasource")["query"], "prometheus");
    let drive = var("drive");
    assert_eq!(drive["type"], "query");
    assert_eq!(drive["multi"], true);
    assert!(
        drive["query"]["query"]
            .as_str()
            .unwrap()
            .contains("drivegate_drive_up")
    );

    let panels = d["panels"].as_array().unwrap();
    let mut ids = BTreeSet::new();
    let mut cells = BTreeSet::new();
    for p in panels {
        let title = p["title"].as_str().unwrap();
        assert!(
            ids.insert(p["id"].as_u64().unwrap()),
            "duplicate id at {title}"
        );
        let g = &p["gridPos"];
        let (x, y, w, h) = (
            g["x"].as_u64().unwrap(),
            g["y"].as_u64().unwrap(),
            g["w"].as_u64().unwrap(),
            g["h"].as_u64().unwrap(),
        );
        assert!(x + w <= 24 && w > 0 && h > 0, "{title} outside the grid");
        for cx in x..x + w {
            for cy in y..y + h {
                assert!(cells.insert((cx, cy)), "{title} overlaps another panel");
            }
        }
        if p["type"] == "row" {
            continue;
        }
        assert!(
            p["description"].as_str().is_some_and(|s| !s.is_empty()),
            "{title}"
        );
        assert_eq!(p["datasource"]["uid"], "${datasource}", "{title}");
        let targets = p["targets"].as_array().unwrap();
        assert!(!targets.is_empty(), "{title} has no query");
        for t in targets {
            assert_eq!(t["datasource"]["uid"], "${datasource}", "{title}");
            assert!(t["refId"].as_str().is_some(), "{title}");
        }
    }
    // The panels a plant engineer looks for first.
    let titles: Vec<&str> = panels.iter().filter_map(|p| p["title"].as_str()).collect();
    for wanted in [
        "Temperature",
        "Supply voltage",
        "Current",
        "Speed",
        "Angle",
        "Turns",
        "Faults",
        "Flags",
        "Throughput",
        "Transaction time",
        "Utilisation (10 s)",
        "Errors",
        "Wire errors per attempt",
        "Motors stopped on communication loss",
    ] {
        assert!(titles.contains(&wanted), "no {wanted} panel");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_queries_use_only_exported_metrics() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        // Activity, so that every kind of series exists: a command, a fault,
        // and one count on the HTTP counters. The Modbus TCP and per-attempt
        // wire counters exist from start-up, with no request at all.
        let (drive, bus) = d.plant.drive("conveyor").unwrap();
        bus.execute(
            drive.unit,
            &DriveRequest::Config(ConfigCommand::Activate),
            JobOptions::default(),
        )
        .await
        .unwrap();
        d.sim().inject_fault(2, Fault::PowerStage).unwrap();
        d.metrics
            .faces()
            .http_request("/metrics", "GET", 200, Duration::from_millis(1));
        let text = eventually(Duration::from_secs(5), "utilisation exported", || {
            let text = d.metrics.render();
            text.contains("drivegate_bus_utilisation_ratio{")
                .then_some(text)
        })
        .await;
        let exported: BTreeSet<String> = text
            .lines()
            .filter(|l| !l.starts_with('#') && !l.is_empty())
            .map(|l| l.split(['{', ' ']).next().unwrap().to_string())
            .collect();

        let dashboard: Value = serde_json::from_str(DASHBOARD).unwrap();
        let queries = queries(&dashboard);
        assert!(queries.len() > 30, "{} queries", queries.len());
        let mut used = BTreeSet::new();
        for (panel, expr) in &queries {
            let names = metric_names(expr);
            assert!(!names.is_empty(), "{panel}: no drivegate metric in {expr}");
            for name in names {
                assert!(
                    exported.contains(&name),
                    "{panel}: {name} is not exported by the daemon"
                );
                used.insert(name);
            }
        }
        // The dashboard covers the drive values a plant engineer watches.
        for name in [
            "drivegate_drive_temperature_celsius",
            "drivegate_drive_supply_voltage_volts",
            "drivegate_drive_current_amperes",
            "drivegate_drive_speed_rpm",
            "drivegate_drive_angle_degrees",
            "drivegate_drive_fault_code",
            "drivegate_drive_stalled",
            "drivegate_bus_utilisation_ratio",
            "drivegate_bus_transaction_duration_seconds_bucket",
            "drivegate_bus_wire_errors_total",
            "drivegate_bus_wire_attempts_total",
            "drivegate_modbus_tcp_requests_total",
        ] {
            assert!(used.contains(name), "the dashboard does not show {name}");
        }
        d.stop().await;
    })
    .await
    .expect("test did not finish in time");
}

#[test]
fn metric_names_are_found_in_expressions() {
    assert_eq!(
        metric_names(r#"rate(drivegate_bus_busy_seconds_total{bus=~"$bus"}[5m]) / drivegate_x"#),
        ["drivegate_bus_busy_seconds_total", "drivegate_x"]
    );
    assert!(metric_names("up == 0").is_empty());
}
