//! The Prometheus side: the scrape config and alert rules pass promtool and
//! their unit tests; and a real Prometheus server on loopback scrapes a
//! daemon running on the simulator, fires DriveFault when a fault is
//! injected into a simulated drive, and answers every dashboard query.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use crate::support::{FOUR_DRIVES, TestDaemon};
use drivegate::drive::Fault;
use serde_json::Value;
use tokio::process::{Child, Command};

const LIMIT: Duration = Duration::from_secs(50);

fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/prometheus")
}

async fn promtool(args: &[&str], dir: &Path) -> (bool, String) {
    let out = tokio::time::timeout(
        Duration::from_secs(30),
        Command::new("promtool")
            .args(args)
            .current_dir(dir)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("promtool in time")
    .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("promtool", &e)));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[tokio::test]
async fn config_and_rules_pass_promtool() {
    let dir = deploy_dir();
    let (ok, out) = promtool(&["check", "config", "prometheus.yml"], &dir).await;
    assert!(ok, "{out}");
    let (ok, out) = promtool(&["check", "rules", "alerts.yml"], &dir).await;
    assert!(ok && out.contains("SUCCESS: 17 rules found"), "{out}");
    let (ok, out) = promtool(&["test", "rules", "alerts_test.yml"], &dir).await;
    assert!(ok && out.contains("SUCCESS"), "{out}");

    // The unit tests can fail: the same tests against a rule file whose
    // threshold moved must not pass.
    let tmp = tempfile::tempdir().unwrap();
    let rules = std::fs::read_to_string(dir.join("alerts.yml")).unwrap();
    let moved = rules.replace(
        "drivegate_drive_temperature_celsius > 75",
        "drivegate_drive_temperature_celsius > 80",
    );
    assert_ne!(moved, rules);
    std::fs::write(tmp.path().join("alerts.yml"), moved).unwrap();
    std::fs::copy(
        dir.join("alerts_test.yml"),
        tmp.path().join("alerts_test.yml"),
    )
    .unwrap();
    let (ok, out) = promtool(&["test", "rules", "alerts_test.yml"], tmp.path()).await;
    assert!(!ok && out.contains("DriveOverTemperature"), "{out}");

    // Without its second half, the broker rule fires for a daemon that has
    // no [mqtt] at all: the unit test sees it.
    let loose = rules.replace(
        "drivegate_mqtt_connected == 0 and drivegate_mqtt_connection_errors_total > 0",
        "drivegate_mqtt_connected == 0",
    );
    assert_ne!(loose, rules);
    std::fs::write(tmp.path().join("alerts.yml"), loose).unwrap();
    let (ok, out) = promtool(&["test", "rules", "alerts_test.yml"], tmp.path()).await;
    assert!(!ok && out.contains("MqttBrokerUnreachable"), "{out}");
}

/// A Prometheus server on loopback with the project's alert rules, scraping
/// `target` every second and evaluating rules every second.
async fn start_prometheus(dir: &Path, target: SocketAddr) -> (Child, String) {
    std::fs::copy(deploy_dir().join("alerts.yml"), dir.join("alerts.yml")).unwrap();
    let config = format!(
        r#"
global:
  scrape_interval: 1s
  evaluation_interval: 1s
rule_files:
  - alerts.yml
scrape_configs:
  - job_name: drivegate
    static_configs:
      - targets: ["{target}"]
"#
    );
    std::fs::write(dir.join("prometheus.yml"), config).unwrap();
    let port = crate::support::ports::free_port();
    let child = Command::new("prometheus")
        .arg(format!(
            "--config.file={}",
            dir.join("prometheus.yml").display()
        ))
        .arg(format!(
            "--storage.tsdb.path={}",
            dir.join("data").display()
        ))
        .arg(format!("--web.listen-address=127.0.0.1:{port}"))
        .arg("--log.level=warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("prometheus", &e)));
    (child, format!("http://127.0.0.1:{port}"))
}

async fn get_json(client: &reqwest::Client, url: &str, query: &[(&str, &str)]) -> Option<Value> {
    let resp = client.get(url).query(query).send().await.ok()?;
    resp.json().await.ok()
}

/// Runs `f` every 250 ms until it gives `Some`, or panics after `limit`.
async fn poll<T, F, Fut>(limit: Duration, what: &str, mut f: F) -> T
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let start = Instant::now();
    loop {
        if let Some(v) = f().await {
            return v;
        }
        assert!(
            start.elapsed() < limit,
            "timed out after {limit:?} waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// Instant query; the result vector when the query succeeded.
async fn query(client: &reqwest::Client, base: &str, expr: &str) -> Option<Vec<Value>> {
    let v = get_json(client, &format!("{base}/api/v1/query"), &[("query", expr)]).await?;
    if v["status"] != "success" {
        panic!("query failed: {expr}: {v}");
    }
    v["data"]["result"].as_array().cloned()
}

/// A dashboard expression with Grafana's variables filled in.
fn fill_variables(expr: &str) -> String {
    expr.replace("$__rate_interval", "15s")
        .replace("$bus", ".*")
        .replace("$drive", ".*")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_prometheus_fires_the_alert_for_a_simulated_fault() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    // The daemon's own HTTP listener serves /metrics.
    let target = d.http;
    let tmp = tempfile::tempdir().unwrap();
    let (mut prometheus, base) = start_prometheus(tmp.path(), target).await;
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(2))
        .build()
        .unwrap();

    let run = tokio::time::timeout(LIMIT, async {
        let started = Instant::now();
        // Prometheus is up and has scraped the daemon.
        poll(Duration::from_secs(20), "the drivegate target up", || async {
            let r = query(&client, &base, r#"up{job="drivegate"} == 1"#).await?;
            (!r.is_empty()).then_some(())
        })
        .await;
        eprintln!("prometheus scraping after {:?}", started.elapsed());

        // Healthy drives: no alert fires.
        let healthy = poll(Duration::from_secs(10), "drive series stored", || async {
            let r = query(&client, &base, "drivegate_drive_fault_code").await?;
            (r.len() == 4).then_some(r)
        })
        .await;
        assert!(healthy.iter().all(|s| s["value"][1] == "0"), "{healthy:?}");
        let alerts = get_json(&client, &format!("{base}/api/v1/alerts"), &[])
            .await
            .unwrap();
        assert_eq!(alerts["data"]["alerts"], Value::Array(vec![]), "{alerts}");

        // Fault injected into the simulated lift (unit 2).
        d.sim().inject_fault(2, Fault::OverTemperature).unwrap();
        let injected = Instant::now();
        let alert = poll(Duration::from_secs(20), "DriveFault firing", || async {
            let v = get_json(&client, &format!("{base}/api/v1/alerts"), &[]).await?;
            v["data"]["alerts"]
                .as_array()?
                .iter()
                .find(|a| a["labels"]["alertname"] == "DriveFault" && a["state"] == "firing")
                .cloned()
        })
        .await;
        let took = injected.elapsed();
        eprintln!("DriveFault firing {took:?} after the injection:\n{alert:#}");
        assert_eq!(alert["labels"]["name"], "lift");
        assert_eq!(alert["labels"]["unit"], "2");
        assert_eq!(alert["labels"]["bus"], "sim");
        assert_eq!(alert["labels"]["fault"], "over_temperature");
        assert_eq!(alert["labels"]["severity"], "critical");
        assert_eq!(
            alert["annotations"]["summary"],
            "Drive lift fault: over_temperature"
        );
        // Only that drive, only that alert.
        let v = get_json(&client, &format!("{base}/api/v1/alerts"), &[])
            .await
            .unwrap();
        let firing: Vec<&Value> = v["data"]["alerts"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["state"] == "firing")
            .collect();
        assert_eq!(firing.len(), 1, "{v}");

        // Every dashboard query parses and, but for the faces' counters
        // (nothing used the faces here), returns series.
        let dashboard: Value =
            serde_json::from_str(include_str!("../../deploy/grafana/drivegate.json")).unwrap();
        let mut exprs = Vec::new();
        for panel in dashboard["panels"].as_array().unwrap() {
            for t in panel["targets"].as_array().into_iter().flatten() {
                exprs.push(fill_variables(t["expr"].as_str().unwrap()));
            }
        }
        for expr in &exprs {
            let faces = ["drivegate_http_", "drivegate_modbus_tcp_requests"]
                .iter()
                .any(|f| expr.contains(f));
            let result = poll(Duration::from_secs(10), expr, || async {
                let r = query(&client, &base, expr).await?;
                (faces || !r.is_empty()).then_some(r)
            })
            .await;
            if !faces {
                assert!(!result.is_empty(), "{expr}");
            }
        }
        eprintln!(
            "{} dashboard queries answered by Prometheus; total run {:?}",
            exprs.len(),
            started.elapsed()
        );
        // The mode query yields one code per drive: the lift is in open loop.
        let mode = query(
            &client,
            &base,
            &fill_variables(
                r#"sum without (mode) (drivegate_drive_mode{name="lift",mode="speed"} or 2 * drivegate_drive_mode{name="lift",mode="position"} or 3 * drivegate_drive_mode{name="lift",mode="torque"})"#,
            ),
        )
        .await
        .unwrap();
        assert_eq!(mode.len(), 1, "{mode:?}");
        assert_eq!(mode[0]["value"][1], "0");
    })
    .await;
    let _ = prometheus.start_kill();
    let _ = prometheus.wait().await;
    d.stop().await;
    run.expect("test did not finish in time");
}
