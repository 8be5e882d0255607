//! The systemd side: the unit file passes `systemd-analyze verify` and keeps
//! a low exposure score, and the real binary speaks sd_notify (READY,
//! WATCHDOG, STOPPING) to a socket as systemd would give it, then exits 0
//! on SIGTERM.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use tokio::io::AsyncReadExt;
use tokio::net::UnixDatagram;
use tokio::process::Command;

const LIMIT: Duration = Duration::from_secs(30);
const UNIT: &str = include_str!("../../deploy/systemd/drivegate.service");
const SYSUSERS: &str = include_str!("../../deploy/sysusers.d/drivegate.conf");

/// The unit with ExecStart pointing at the binary under test: `verify`
/// refuses a unit whose binary does not exist.
fn unit_in(dir: &Path, text: &str) -> PathBuf {
    let path = dir.join("drivegate.service");
    std::fs::write(
        &path,
        text.replace("/usr/bin/drivegate", env!("CARGO_BIN_EXE_drivegate")),
    )
    .unwrap();
    path
}

async fn systemd_analyze(args: &[&str]) -> (bool, String, String) {
    let out = tokio::time::timeout(
        LIMIT,
        Command::new("systemd-analyze")
            .args(args)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("systemd-analyze in time")
    .unwrap_or_else(|e| {
        panic!(
            "{}",
            crate::support::tools::cannot_run("systemd-analyze", &e)
        )
    });
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[tokio::test]
async fn unit_file_passes_systemd_analyze_verify() {
    let dir = tempfile::tempdir().unwrap();
    let unit = unit_in(dir.path(), UNIT);
    let unit = unit.to_str().unwrap();
    let (ok, out, err) = systemd_analyze(&["verify", "--man=no", unit]).await;
    assert!(ok, "verify failed:\n{out}{err}");
    assert!(
        err.trim().is_empty() && out.trim().is_empty(),
        "verify warned:\n{out}{err}"
    );

    // The same check sees a mistake: a misspelt directive is reported.
    let broken = dir.path().join("broken");
    std::fs::create_dir(&broken).unwrap();
    let bad = unit_in(
        &broken,
        &UNIT.replace("ProtectHome=yes", "ProtectHomes=yes"),
    );
    let (_, out, err) = systemd_analyze(&["verify", "--man=no", bad.to_str().unwrap()]).await;
    assert!(
        format!("{out}{err}").contains("ProtectHomes"),
        "no complaint about the typo:\n{out}{err}"
    );
}

#[tokio::test]
async fn unit_file_is_notify_type_with_hardening_and_port_502() {
    // The hardening directives the unit must have, present and not commented out.
    let lines: Vec<&str> = UNIT.lines().map(str::trim).collect();
    for wanted in [
        "Type=notify",
        "WatchdogSec=10s",
        "Restart=on-failure",
        "User=drivegate",
        "SupplementaryGroups=dialout",
        "AmbientCapabilities=CAP_NET_BIND_SERVICE",
        "CapabilityBoundingSet=CAP_NET_BIND_SERVICE",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "PrivateTmp=yes",
        "DevicePolicy=closed",
        "DeviceAllow=char-ttyUSB rw",
        "ExecStart=/usr/bin/drivegate serve --config /etc/drivegate/drivegate.toml",
    ] {
        assert!(lines.contains(&wanted), "{wanted} missing");
    }
    // The user the unit runs as is the one the package creates.
    assert!(SYSUSERS.lines().any(|l| l.starts_with("u drivegate ")));
    assert!(SYSUSERS.lines().any(|l| l == "m drivegate dialout"));

    // systemd's own measure of the sandbox: 0 is a locked box, 10 is root
    // with everything; "OK" is below 4.
    let dir = tempfile::tempdir().unwrap();
    let unit = unit_in(dir.path(), UNIT);
    let (ok, out, err) =
        systemd_analyze(&["security", "--offline=yes", unit.to_str().unwrap()]).await;
    assert!(ok, "{out}{err}");
    let exposure: f64 = out
        .lines()
        .find_map(|l| {
            l.split("Overall exposure level for drivegate.service: ")
                .nth(1)
        })
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no exposure level in:\n{out}{err}"));
    assert!(exposure <= 2.5, "exposure {exposure}:\n{out}");
}

const CONFIG: &str = r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
listen = "127.0.0.1:0"
[log]
format = "text"
[[bus]]
name = "sim"
port = "sim"
response_timeout_ms = 250
guard_ms = 50
[[bus.drive]]
unit = 1
name = "conveyor"
"#;

/// Receives datagrams until one contains `what`; returns every message seen.
async fn until(socket: &UnixDatagram, what: &str, seen: &mut Vec<String>) {
    let mut buf = vec![0u8; 4096];
    loop {
        let n = socket.recv(&mut buf).await.unwrap();
        let msg = String::from_utf8_lossy(&buf[..n]).into_owned();
        let found = msg.lines().any(|l| l == what);
        seen.push(msg);
        if found {
            return;
        }
    }
}

#[tokio::test]
async fn binary_notifies_systemd_and_exits_zero_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("drivegate.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let socket_path = dir.path().join("notify.sock");
    let socket = UnixDatagram::bind(&socket_path).unwrap();

    let mut child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .arg("serve")
        .arg("--config")
        .arg(&config)
        .env("NOTIFY_SOCKET", &socket_path)
        // A 200 ms watchdog: pings every 100 ms.
        .env("WATCHDOG_USEC", "200000")
        .env_remove("WATCHDOG_PID")
        .env_remove("JOURNAL_STREAM")
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let log = tokio::spawn(async move {
        let mut text = String::new();
        let _ = stderr.read_to_string(&mut text).await;
        text
    });

    let mut seen = Vec::new();
    let result = tokio::time::timeout(LIMIT, async {
        until(&socket, "READY=1", &mut seen).await;
        let ready = seen.last().unwrap().clone();
        assert!(
            ready
                .lines()
                .any(|l| l.starts_with("STATUS=serving 1 drive(s) on 1 bus(es)")),
            "{ready}"
        );
        let pings_from = seen.len();
        until(&socket, "WATCHDOG=1", &mut seen).await;
        until(&socket, "WATCHDOG=1", &mut seen).await;
        assert!(
            seen[pings_from..].iter().all(|m| m == "WATCHDOG=1\n"),
            "{seen:?}"
        );

        // A reload that adds a drive: `systemctl status` says so.
        let pid = Pid::from_raw(i32::try_from(child.id().unwrap()).unwrap());
        let more = format!("{CONFIG}[[bus.drive]]\nunit = 2\nname = \"lift\"\n");
        std::fs::write(&config, more).unwrap();
        kill(pid, Signal::SIGHUP).unwrap();
        let mut status = String::new();
        while !status.starts_with("STATUS=serving 2 drive(s) on 1 bus(es); HTTP on 127.0.0.1:") {
            let mut buf = vec![0u8; 4096];
            let n = socket.recv(&mut buf).await.unwrap();
            let msg = String::from_utf8_lossy(&buf[..n]).into_owned();
            if let Some(line) = msg.lines().find(|l| l.starts_with("STATUS=")) {
                status = line.to_string();
            }
            seen.push(msg);
        }

        let asked = Instant::now();
        kill(pid, Signal::SIGTERM).unwrap();
        until(&socket, "STOPPING=1", &mut seen).await;
        let status = child.wait().await.unwrap();
        (status, asked.elapsed())
    })
    .await;
    let (status, took) = match result {
        Ok(r) => r,
        Err(_) => {
            let _ = child.start_kill();
            panic!("timed out; messages so far: {seen:?}");
        }
    };
    let log = log.await.unwrap();
    assert_eq!(status.code(), Some(0), "exit status {status}; log:\n{log}");
    // The order systemd expects: READY first, STOPPING once, last.
    let states: Vec<&str> = seen
        .iter()
        .flat_map(|m| m.lines())
        .filter(|l| !l.starts_with("STATUS=") && *l != "WATCHDOG=1")
        .collect();
    assert_eq!(states, ["READY=1", "STOPPING=1"], "{seen:?}");
    assert!(log.contains("SIGTERM received"), "{log}");
    assert!(log.contains("stopped"), "{log}");
    assert!(
        !log.contains('\u{1b}'),
        "colour codes in a log that is not a terminal:\n{log}"
    );
    eprintln!("stopped {took:?} after SIGTERM");
}
