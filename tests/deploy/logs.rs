//! The binary's logs: JSON on request (one object per line, fields at the
//! top level), plain text without colour codes when not at a terminal, and
//! a clear note when journald or a log filter cannot be used.

use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use crate::support::config::ConfigBuilder;
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::Command;

const LIMIT: Duration = Duration::from_secs(30);
/// What the daemon logs once its buses and listeners are up.
const RUNNING: &str = concat!("drivegate ", env!("CARGO_PKG_VERSION"), " running");

fn config(format: &str) -> String {
    ConfigBuilder::new()
        .section("log", &format!("format = \"{format}\"\nlevel = \"info\""))
        .bus("sim", |b| b.drive(1, "conveyor"))
        .toml()
}

/// Runs `drivegate serve` with `config` until it logs that it is running,
/// stops it with SIGTERM, and returns its exit status and stderr lines.
async fn run_and_stop(config: &str, env: &[(&str, &str)]) -> (ExitStatus, Vec<String>) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("drivegate.toml");
    std::fs::write(&path, config).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_drivegate"));
    cmd.arg("serve")
        .arg("--config")
        .arg(&path)
        .env_remove("RUST_LOG")
        .env_remove("JOURNAL_STREAM")
        .env_remove("NOTIFY_SOCKET")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let mut seen = Vec::new();
    let run = tokio::time::timeout(LIMIT, async {
        while let Some(line) = lines.next_line().await.unwrap() {
            let running = line.contains(RUNNING);
            seen.push(line);
            if running {
                break;
            }
        }
        let pid = Pid::from_raw(i32::try_from(child.id().unwrap()).unwrap());
        kill(pid, Signal::SIGTERM).unwrap();
        while let Some(line) = lines.next_line().await.unwrap() {
            seen.push(line);
        }
        child.wait().await.unwrap()
    })
    .await;
    match run {
        Ok(status) => (status, seen),
        Err(_) => panic!("the daemon did not run and stop in time; stderr so far: {seen:#?}"),
    }
}

#[tokio::test]
async fn json_logs_are_one_object_per_line() {
    let (status, lines) = run_and_stop(&config("json"), &[]).await;
    assert!(status.success(), "{status}: {lines:#?}");
    assert!(lines.len() >= 4, "{lines:#?}");
    let mut messages = Vec::new();
    for line in &lines {
        let v: serde_json::Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("not JSON ({e}): {line}"));
        for key in ["timestamp", "level", "target", "message"] {
            assert!(v.get(key).is_some(), "{key} missing: {line}");
        }
        messages.push(v["message"].as_str().unwrap().to_string());
        // Event fields sit at the top level, not under "fields".
        assert!(v.get("fields").is_none(), "{line}");
    }
    let running = lines
        .iter()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .find(|v| v["message"] == RUNNING)
        .unwrap();
    assert_eq!(running["buses"], 1, "{running}");
    assert_eq!(running["drives"], 1, "{running}");
    assert_eq!(running["level"], "INFO");
    let signal = messages.iter().position(|m| m == "SIGTERM received");
    let stopped = messages.iter().position(|m| m == "stopped");
    assert!(
        matches!((signal, stopped), (Some(a), Some(b)) if a < b),
        "{messages:#?}"
    );
}

#[tokio::test]
async fn text_logs_carry_no_colour_codes_off_a_terminal() {
    let (status, lines) = run_and_stop(&config("text"), &[]).await;
    assert!(status.success(), "{status}: {lines:#?}");
    assert!(
        lines
            .iter()
            .any(|l| l.contains(" INFO ") && l.contains(RUNNING)),
        "{lines:#?}"
    );
    assert!(lines.iter().all(|l| !l.contains('\u{1b}')), "{lines:#?}");
}

#[tokio::test]
async fn missing_journald_and_a_bad_filter_are_reported() {
    // No journald in the test environment: the daemon says so and logs to
    // stderr; a RUST_LOG that does not parse falls back to [log] level.
    let socket_missing = !std::path::Path::new("/run/systemd/journal/socket").exists();
    let (status, lines) =
        run_and_stop(&config("journald"), &[("RUST_LOG", "drivegate=loudest")]).await;
    assert!(status.success(), "{status}: {lines:#?}");
    let text = lines.join("\n");
    assert!(
        text.contains("RUST_LOG=\"drivegate=loudest\" is not a valid filter"),
        "{text}"
    );
    if socket_missing {
        assert!(text.contains("journald is not available"), "{text}");
        assert!(text.contains(RUNNING), "{text}");
    }
}
