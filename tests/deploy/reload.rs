//! A configuration change without a restart: `POST /api/v1/config/reload`
//! on the daemon in-process (two simulated buses), and `systemctl reload`'s
//! SIGHUP on a real `drivegate serve` process. A drive that did not change
//! keeps turning through every reload, with its lease and its stream; a
//! bad file changes nothing and says where it is wrong; a removed drive
//! that moves is stopped, audited.

use std::net::SocketAddr;
use std::process::Stdio;
use std::time::Duration;

use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::Command;

use crate::support::api::{Api, Reply, Ws, connect, wait_for};
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::exported;
use crate::support::{TestDaemon, bounded, eventually};
use drivegate::plant::SimRef;

const LIMIT: Duration = Duration::from_secs(90);
/// Longest wait for an event the design says must come.
const EVENT: Duration = Duration::from_secs(20);
const ADMIN: &str = "reload-admin-token";
const VIEWER: &str = "reload-viewer-token";
const SCADA: &str = "reload-scada-token";

/// Two buses: the kiln's belt alone on line1, its press and saw on line2
/// (names no other test of this binary uses: the log is shared).
fn plant() -> ConfigBuilder {
    ConfigBuilder::new()
        .bus("line1", |b| b.drive(1, "kiln_belt"))
        .bus("line2", |b| b.drive(1, "kiln_press").drive(2, "kiln_saw"))
        .http_token("admin", "admin", ADMIN)
        .http_token("panel", "viewer", VIEWER)
        .section(
            "safety",
            "lease_max_ms = 600000\non_shutdown = \"zero-speed\"",
        )
}

/// Turns `drive` at 100 rpm with a lease of ten minutes (or none).
async fn turn(api: &Api, drive: &str, lease: bool) {
    api.activate_in(drive, "speed").await;
    let body = if lease {
        json!({"speed_rpm": 100, "lease_ms": 600000})
    } else {
        json!({"speed_rpm": 100})
    };
    api.put(&format!("/api/v1/drives/{drive}/setpoint"), body)
        .await
        .expect(200);
}

/// The simulated drive at `unit` behind `bus`, turning at `rpm` (at the
/// output, as the simulator reports it).
async fn until_turning(sim: &SimRef, unit: u8, rpm: f64, what: &str) {
    eventually(EVENT, what, || {
        ((sim.drive(unit)?.speed_rpm - rpm).abs() <= 2.0).then_some(())
    })
    .await;
}

async fn reload(api: &Api) -> Reply {
    api.post_empty("/api/v1/config/reload").await
}

/// Reads the stream until the kiln_belt's status, and checks its speed.
async fn kiln_belt_still_streams(ws: &mut Ws) {
    let v = wait_for(ws, EVENT, "a status of the kiln_belt", |v| {
        v["type"] == "status" && v["drive"] == "kiln_belt"
    })
    .await;
    let rpm = v["status"]["speed_rpm"].as_i64().unwrap();
    assert!((98..=102).contains(&rpm), "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_turning_drive_keeps_turning_while_a_drive_and_a_token_are_added_and_a_bad_file_is_refused()
 {
    capture_logs();
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant().toml()).await;
        let api = Api::new(d.http, Some(ADMIN));
        let line1 = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        turn(&api, "kiln_belt", true).await;
        until_turning(&line1, 1, 100.0, "the kiln_belt at 100 rpm").await;
        let lease = api.get("/api/v1/drives/kiln_belt").await.expect(200)["lease"].clone();
        assert_eq!(lease["lease_ms"], 600000, "{lease}");
        let mut ws = connect(d.http, "?drives=all", Some(ADMIN)).await;
        // The first statuses may be polls from before the motor got there
        // (a loaded machine runs the bus late): until one at speed.
        wait_for(&mut ws, EVENT, "a status of the kiln_belt at speed", |v| {
            v["type"] == "status"
                && v["drive"] == "kiln_belt"
                && v["status"]["speed_rpm"]
                    .as_i64()
                    .is_some_and(|r| (98..=102).contains(&r))
        })
        .await;

        // A drive on line2 and a token: line2 takes it in place, line1 is
        // not touched.
        let added = plant()
            .with_bus("line2", |b| b.drive(3, "kiln_mixer"))
            .http_token("scada", "viewer", SCADA)
            .toml();
        d.rewrite(&added);
        let reply = reload(&api).await.expect(200);
        let changes: Vec<&str> = reply["changes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_str().unwrap())
            .collect();
        assert_eq!(
            changes,
            vec![
                "drives added: kiln_mixer",
                "bus line2 changed in place (drives), its port kept open",
                "tokens changed: 1"
            ],
            "{reply}"
        );
        assert_eq!(reply["stopped"], json!([]), "{reply}");
        assert_eq!(reply["problems"], json!([]), "{reply}");
        // The new token works at once, the new drive is listed and streamed.
        let scada = Api::new(d.http, Some(SCADA));
        let me = scada.get("/api/v1/whoami").await.expect(200);
        assert_eq!(
            (me["who"].as_str(), me["role"].as_str()),
            (Some("scada"), Some("viewer"))
        );
        let drives = api.get("/api/v1/drives").await.expect(200);
        let names: Vec<&str> = drives
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            names,
            vec!["kiln_belt", "kiln_press", "kiln_saw", "kiln_mixer"]
        );
        wait_for(&mut ws, EVENT, "a status of the added drive", |v| {
            v["type"] == "status" && v["drive"] == "kiln_mixer"
        })
        .await;

        // A file that does not pass the check: nothing changes, and the
        // answer, /readyz and the metrics say where it is wrong.
        let bad = format!("{added}\n[bogus]\nkey = 1\n");
        let line = bad.lines().count() - 1;
        d.rewrite(&bad);
        let refused = reload(&api).await.expect_problem(422, "config-invalid");
        let place = format!("{}:{line}:", d.config_path().display());
        let detail = refused["detail"].as_str().unwrap();
        assert!(detail.contains(&place), "{detail} does not say {place}");
        let ready = api.get("/readyz").await.expect(200);
        let config = &ready["configuration"];
        assert_eq!(config["last_reload_ok"], false, "{ready}");
        assert!(
            config["last_reload_error"]
                .as_str()
                .unwrap()
                .contains(&place),
            "{ready}"
        );
        assert_eq!(config["reloads"], 1, "{ready}");
        let text = d.metrics.render();
        assert_eq!(exported(&text, "drivegate_config_last_reload_ok "), 0.0);
        assert_eq!(
            exported(&text, "drivegate_config_reload_total{result=\"invalid\"}"),
            1.0
        );
        assert_eq!(
            exported(&text, "drivegate_config_reload_total{result=\"applied\"}"),
            1.0
        );
        assert!(
            log_text()
                .lines()
                .any(|l| l.contains("configuration reload refused") && l.contains(&place)),
            "no log line says where the file is wrong"
        );
        // The running configuration stayed: the new token still works.
        scada.get("/api/v1/whoami").await.expect(200);

        // A viewer may not reload, and is told so.
        let viewer = Api::new(d.http, Some(VIEWER));
        reload(&viewer).await.expect_problem(403, "forbidden");

        // Through it all the kiln_belt kept its lease (never renewed nor
        // replaced: less time left), its speed and its stream.
        let now = api.get("/api/v1/drives/kiln_belt").await.expect(200)["lease"].clone();
        assert_eq!(
            (&now["owner"], &now["lease_ms"]),
            (&lease["owner"], &lease["lease_ms"]),
            "{now}"
        );
        assert!(now["expires_in_ms"].as_u64() < lease["expires_in_ms"].as_u64());
        assert_eq!(line1.drive(1).unwrap().setpoints.speed_rpm, 100);
        kiln_belt_still_streams(&mut ws).await;
        assert!(
            !log_text()
                .lines()
                .any(|l| l.contains("lease ended") && l.contains("drive=kiln_belt")),
            "the kiln_belt's lease ended"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_removed_moving_drive_gets_its_stop_audited() {
    capture_logs();
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant().toml()).await;
        let api = Api::new(d.http, Some(ADMIN));
        // Kept by the test: the bus goes on without them.
        let line1 = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        let line2 = SimRef::of(d.plant.bus("line2").unwrap()).unwrap();
        turn(&api, "kiln_belt", true).await;
        turn(&api, "kiln_press", true).await;
        turn(&api, "kiln_saw", false).await;
        until_turning(&line2, 1, 100.0, "the kiln_press at 100 rpm").await;
        until_turning(&line2, 2, 100.0, "the kiln_saw at 100 rpm").await;

        let without = ConfigBuilder::new()
            .bus("line1", |b| b.drive(1, "kiln_belt"))
            .bus("line2", |b| b)
            .http_token("admin", "admin", ADMIN)
            .http_token("panel", "viewer", VIEWER)
            .section(
                "safety",
                "lease_max_ms = 600000\non_shutdown = \"zero-speed\"",
            )
            .toml();
        d.rewrite(&without);
        let reply = reload(&api).await.expect(200);
        assert_eq!(
            reply["changes"][0], "drives removed: kiln_press, kiln_saw",
            "{reply}"
        );
        let stopped: Vec<&str> = reply["stopped"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s.as_str().unwrap())
            .collect();
        assert_eq!(stopped.len(), 2, "{reply}");
        assert!(
            stopped
                .iter()
                .any(|s| s.starts_with("drive kiln_saw was moving: zero-speed applied")),
            "{reply}"
        );
        assert!(
            stopped
                .iter()
                .any(|s| s.starts_with("drive kiln_press's lease ended with its stop")),
            "{reply}"
        );
        // The stops reached the drives before their bus let them go.
        assert_eq!(line2.drive(1).unwrap().setpoints.speed_rpm, 0);
        assert_eq!(line2.drive(2).unwrap().setpoints.speed_rpm, 0);
        let log = log_text();
        assert!(
            log.lines().any(|l| l.contains("lease ended with its stop")
                && l.contains("drive=\"kiln_press\"")
                && l.contains("removed from the configuration by a reload")),
            "no audit line of the kiln_press's stop:\n{}",
            log.lines()
                .filter(|l| l.contains("kiln_press"))
                .collect::<Vec<_>>()
                .join("\n")
        );
        assert!(
            log.lines()
                .any(|l| l.contains("who=\"reload\"") || l.contains("who=reload")),
            "no audit line of the kiln_saw's stop"
        );
        assert!(
            log.lines()
                .any(|l| l.contains("configuration reloaded") && l.contains("drives removed")),
            "no audit line of the reload"
        );
        api.get("/api/v1/drives/kiln_press")
            .await
            .expect_problem(404, "unknown-drive");
        // The kiln_belt on line1 went on.
        assert_eq!(line1.drive(1).unwrap().setpoints.speed_rpm, 100);
        assert!(!api.get("/api/v1/drives/kiln_belt").await.expect(200)["lease"].is_null());
        d.stop().await;
    })
    .await;
}

/// A real `drivegate serve --config FILE`, its HTTP address from its log,
/// and its log lines as they come.
async fn serve(
    file: &std::path::Path,
) -> (
    tokio::process::Child,
    SocketAddr,
    tokio::sync::mpsc::UnboundedReceiver<Value>,
) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .arg("serve")
        .arg("--config")
        .arg(file)
        .env_remove("RUST_LOG")
        .env_remove("JOURNAL_STREAM")
        .env_remove("NOTIFY_SOCKET")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        while let Ok(Some(line)) = lines.next_line().await {
            let v: Value = serde_json::from_str(&line).unwrap_or(json!({"message": line}));
            if tx.send(v).is_err() {
                return;
            }
        }
    });
    let addr = loop {
        let v = tokio::time::timeout(EVENT, rx.recv())
            .await
            .expect("the daemon started in time")
            .expect("the daemon's log");
        if v["message"] == "HTTP API listening" {
            break v["addr"].as_str().unwrap().parse().unwrap();
        }
    };
    (child, addr, rx)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_reloads_the_file_and_a_new_token_works_at_once() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("drivegate.toml");
        let base = ConfigBuilder::new()
            .bus("line1", |b| b.drive(1, "kiln_belt"))
            .http_token("admin", "admin", ADMIN)
            .modbus_tcp_off()
            .section("log", "format = \"json\"");
        std::fs::write(&file, base.toml()).unwrap();
        let (child, addr, mut log) = serve(&file).await;
        let scada = Api::new(addr, Some(SCADA));
        scada
            .get("/api/v1/whoami")
            .await
            .expect_problem(401, "unauthorized");

        std::fs::write(
            &file,
            base.clone().http_token("scada", "operator", SCADA).toml(),
        )
        .unwrap();
        let pid = nix::unistd::Pid::from_raw(i32::try_from(child.id().unwrap()).unwrap());
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGHUP).unwrap();
        let reloaded = loop {
            let v = tokio::time::timeout(EVENT, log.recv())
                .await
                .expect("the reload in time")
                .expect("the daemon's log");
            if v["message"]
                .as_str()
                .is_some_and(|m| m.starts_with("configuration reloaded from"))
            {
                break v;
            }
        };
        assert!(
            reloaded["message"]
                .as_str()
                .unwrap()
                .ends_with("tokens changed: 1"),
            "{reloaded}"
        );
        assert_eq!(reloaded["by"], "SIGHUP", "{reloaded}");
        let me = scada.get("/api/v1/whoami").await.expect(200);
        assert_eq!(me["role"], "operator");
        // The daemon runs on: SIGHUP is never a stop.
        Api::new(addr, Some(ADMIN))
            .get("/api/v1/drives/kiln_belt")
            .await
            .expect(200);
        drop(child);
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drives_are_added_to_the_file_keeping_its_comments_and_a_stale_or_bad_write_is_refused() {
    bounded(LIMIT, async {
        let toml = format!("# Kiln line: written by hand.\n{}", plant().toml());
        let d = TestDaemon::reloadable(&toml).await;
        let api = Api::new(d.http, Some(ADMIN));
        let extra = json!({"bus": "line2", "drives": [{"unit": 3, "name": "kiln_extra"}]});
        let mut dry = extra.clone();
        dry["dry_run"] = json!(true);
        let preview = api
            .post("/api/v1/config/drives", dry.clone())
            .await
            .expect(200);
        assert_eq!(
            preview["tables"],
            "[[bus.drive]]\nunit = 3\nname = \"kiln_extra\"\n"
        );
        assert!(preview["reload"].is_null());
        assert_eq!(std::fs::read_to_string(d.config_path()).unwrap(), toml);

        // The file changed on disk since the preview: refused, untouched.
        let edited = format!("{toml}# a note added by hand\n");
        d.rewrite(&edited);
        let mut write = extra.clone();
        write["base_sha256"] = preview["sha256"].clone();
        api.post("/api/v1/config/drives", write)
            .await
            .expect_problem(409, "config-changed");
        assert_eq!(std::fs::read_to_string(d.config_path()).unwrap(), edited);

        // A result that would not pass the check (a name taken on another
        // bus): nothing written.
        let taken =
            json!({"bus": "line2", "drives": [{"unit": 4, "name": "kiln_belt"}], "dry_run": true});
        let refused = api
            .post("/api/v1/config/drives", taken)
            .await
            .expect_problem(422, "config-invalid");
        assert!(
            refused["detail"].as_str().unwrap().contains("kiln_belt"),
            "{refused}"
        );
        // Only an admin.
        Api::new(d.http, Some(VIEWER))
            .post("/api/v1/config/drives", dry.clone())
            .await
            .expect_problem(403, "forbidden");

        // Read again, written, reloaded: the drive answers.
        let preview = api.post("/api/v1/config/drives", dry).await.expect(200);
        let mut write = extra.clone();
        write["base_sha256"] = preview["sha256"].clone();
        let done = api.post("/api/v1/config/drives", write).await.expect(200);
        assert_eq!(
            done["reload"]["changes"],
            json!([
                "drives added: kiln_extra",
                "bus line2 changed in place (drives), its port kept open"
            ]),
            "{done}"
        );
        let written = std::fs::read_to_string(d.config_path()).unwrap();
        assert!(written.starts_with("# Kiln line: written by hand.\n"));
        assert!(
            written.ends_with("# a note added by hand\n")
                || written.contains("# a note added by hand\n")
        );
        assert!(written.contains("[[bus.drive]]\nunit = 3\nname = \"kiln_extra\"\n"));
        let line2 = SimRef::of(d.plant.bus("line2").unwrap()).unwrap();
        eventually(EVENT, "the added drive polled", || {
            line2.drive(3).map(|_| ())
        })
        .await;
        eventually(EVENT, "the added drive online", || {
            let (_, bus) = d.plant.drive("kiln_extra").ok()?;
            bus.drive(3)?.status.map(|_| ())
        })
        .await;
        d.stop().await;
    })
    .await;
}
