//! `drivegate probe` as a user runs it, on the simulator's pty: drives found
//! with their figures, a silent line, drives at another baud rate (the
//! simulator reads the master's rate off the pty and garbles the bits as a
//! UART at the other rate would), an adapter that echoes, and a line that
//! corrupts some replies; a serial device server's `tcp://` line; and a
//! port another program holds (a running `drivegate serve`, `flock`),
//! named with that program and its pid.

use std::time::Duration;

use drivegate::sim::SimConfig;
use drivegate::sim::Simulator;

use crate::support::eventually;

/// Runs the probe on `sim`'s pty with `args`; its stdout.
async fn probe(sim: &SimConfig, args: &[&str]) -> String {
    let handle = Simulator::start(sim.clone()).unwrap();
    let out = tokio::time::timeout(
        Duration::from_secs(120),
        tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .arg("probe")
            .arg("--port")
            .arg(handle.port_path())
            // A drive answers within milliseconds; the simulator is a
            // thread of a machine that may be loaded (tests/README), and a
            // unit whose first read goes unanswered is taken for absent.
            .args(["--timeout-ms", "1000"])
            .args(args)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("the probe ends within 120 s")
    .unwrap();
    handle.stop();
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

fn has(out: &str, text: &str) {
    assert!(out.contains(text), "no {text:?} in:\n{out}");
}

#[tokio::test]
async fn lists_the_drives_that_answer_with_their_figures() {
    let out = probe(
        &SimConfig::for_units([1, 3]),
        &["--units", "1-4", "--reads", "3"],
    )
    .await;
    has(&out, "Probing ");
    has(&out, "at 115200 baud 8N1, units 1-4, 1000 ms timeout");
    has(&out, "Found at 115200 baud:");
    has(
        &out,
        "  unit   1: mode open_loop, inactive, 24 V, 25 °C, fault none",
    );
    has(
        &out,
        "  unit   3: mode open_loop, inactive, 24 V, 25 °C, fault none",
    );
    assert!(
        !out.contains("unit   2:") && !out.contains("unit   4:"),
        "{out}"
    );
    has(&out, "[[bus]]\nname = \"line1\"\n");
    has(
        &out,
        "baud = 115200\n\n[[bus.drive]]\nunit = 1\nname = \"drive1\"\n\n[[bus.drive]]\nunit = 3\n",
    );
}

#[tokio::test]
async fn a_silent_line_is_explained() {
    let out = probe(&SimConfig::for_units([]), &["--units", "1-3"]).await;
    has(&out, "No drive found.");
    has(&out, "Silence: not one byte came back (baud 115200).");
    has(&out, "A and B are swapped");
    has(&out, "--try-bauds scans the common rates");
    assert!(!out.contains("[[bus]]"), "{out}");
}

#[tokio::test]
async fn drives_at_another_rate_are_found_at_theirs() {
    let mut sim = SimConfig::for_units([2]);
    sim.baud = 19_200;
    sim.check_master_baud = true;
    // At 115200 the drive reads garbage and stays silent, as a real one.
    let out = probe(&sim, &["--units", "1-3", "--reads", "2"]).await;
    has(&out, "Silence: not one byte came back (baud 115200).");
    let out = probe(&sim, &["--units", "1-3", "--reads", "2", "--try-bauds"]).await;
    has(&out, "Trying 9600 baud");
    has(&out, "Found at 19200 baud:\n  unit   2: mode open_loop");
    has(
        &out,
        "Wrong baud rate: nothing answered at 115200 baud, the drives answered at 19200 baud. \
         Set baud = 19200 for this bus",
    );
    has(&out, "baud = 19200\n");
    // The rates after the one that answered are not tried.
    assert!(!out.contains("Trying 38400"), "{out}");
}

#[tokio::test]
async fn an_adapter_that_echoes_is_named_with_its_fix() {
    let mut sim = SimConfig::for_units([1]);
    sim.echo = true;
    let out = probe(&sim, &["--units", "1-2"]).await;
    has(&out, "No drive found.");
    has(
        &out,
        "Echo: every request came back byte for byte before any answer.",
    );
    has(&out, "automatic send/receive switching");
    // An echo is no reason to try other rates.
    assert!(!out.contains("Trying"), "{out}");
}

#[tokio::test]
async fn corrupted_replies_from_a_drive_that_answers_point_at_termination() {
    let mut sim = SimConfig::for_units([1]);
    sim.faults.crc_error_rate = 0.3;
    sim.seed = 11;
    let out = probe(&sim, &["--units", "1", "--reads", "20"]).await;
    has(&out, "Found at 115200 baud:\n  unit   1: mode open_loop");
    has(&out, "Unit 1: ");
    has(&out, " of 20 reads failed (corrupted or lost).");
    has(&out, "120 ohm across A and B at both ends");
}

#[tokio::test]
async fn probes_a_serial_device_server_over_tcp() {
    let mut sim = SimConfig::for_units([2]);
    sim.listen = Some("127.0.0.1:0".parse().unwrap());
    let out = probe(&sim, &["--units", "1-2", "--reads", "2"]).await;
    has(&out, "Probing tcp://127.0.0.1:");
    has(&out, "Found at 115200 baud:\n  unit   2: mode open_loop");
    has(&out, "port = \"tcp://127.0.0.1:");
}

/// True when process `pid` has `path` open.
fn has_open(pid: u32, path: &std::path::Path) -> bool {
    std::fs::read_dir(format!("/proc/{pid}/fd")).is_ok_and(|fds| {
        fds.flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|l| l == path))
    })
}

/// The probe on `port`, expected to fail: its stderr.
async fn probe_refused(port: &std::path::Path) -> String {
    let out = tokio::time::timeout(
        Duration::from_secs(60),
        tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["probe", "--units", "1-2", "--port"])
            .arg(port)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("the probe ends within 60 s")
    .unwrap();
    assert_eq!(out.status.code(), Some(1));
    String::from_utf8(out.stderr).unwrap()
}

#[tokio::test]
async fn a_port_another_program_holds_is_named_with_that_program_and_its_pid() {
    let sim = Simulator::start(SimConfig::for_units([1])).unwrap();
    let port = sim.port_path().to_path_buf();
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("plant.toml");
    std::fs::write(
        &config,
        format!(
            "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
             [[bus]]\nname = \"line1\"\nport = \"{}\"\nresponse_timeout_ms = 250\n\
             [[bus.drive]]\nunit = 1\nname = \"conveyor\"\n",
            port.display()
        ),
    )
    .unwrap();
    // The daemon on the line, as on a plant box: it holds the port.
    let mut daemon = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .arg("serve")
        .arg("--config")
        .arg(&config)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let pid = daemon.id().unwrap();
    eventually(
        Duration::from_secs(30),
        "the daemon holding the port",
        || has_open(pid, &port).then_some(()),
    )
    .await;
    let said = probe_refused(&port).await;
    assert!(
        said.contains(&format!("{} is in use by", port.display()))
            && said.contains(&format!(
                "drivegate serve --config {} (pid {pid}, holds its lock)",
                config.display()
            ))
            && said.contains("sudo systemctl stop drivegate"),
        "{said}"
    );
    assert!(!said.contains("dialout"), "{said}");
    daemon.kill().await.unwrap();

    // Another program: flock(1) holding the port's lock.
    let mut flock = tokio::process::Command::new("flock")
        .arg(&port)
        .args(["sleep", "600"])
        .kill_on_drop(true)
        .spawn()
        .expect("flock (util-linux) runs");
    let pid = flock.id().unwrap();
    eventually(Duration::from_secs(30), "flock holding the port", || {
        has_open(pid, &port).then_some(())
    })
    .await;
    let said = probe_refused(&port).await;
    assert!(
        said.contains(&format!(
            "flock {} sleep 600 (pid {pid}, holds its lock)",
            port.display()
        )) && said.contains("Stop it first, then probe again"),
        "{said}"
    );
    flock.kill().await.unwrap();
    sim.stop();
}
