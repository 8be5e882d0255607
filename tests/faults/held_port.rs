//! A port that is not the daemon's to take: another program holding the
//! adapter (here `flock(1)` on the pty an external simulator serves) is
//! named with its command line and pid in the bus's state, `/readyz` and
//! the bus-down alarm, never as a missing adapter or group, and the daemon
//! takes the port once it is let go; a link that leads to a login
//! session's terminal (a pty made the controlling terminal of `setsid
//! --ctty`, as a shell's is) is refused unopened, saying why.

use std::os::fd::AsRawFd;
use std::path::Path;
use std::time::Duration;

use drivegate::bus::handle::PortState;

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::sim_process::ExternalSim;
use crate::support::{TestDaemon, bounded, eventually};

const LIMIT: Duration = Duration::from_secs(60);
/// Longest wait for what the design says must come.
const EVENT: Duration = Duration::from_secs(20);

/// Bus `line1` on `port` with the conveyor (1).
fn config(port: &Path) -> String {
    ConfigBuilder::new()
        .bus("line1", |b| {
            b.port(&port.display().to_string()).drive(1, "conveyor")
        })
        .toml()
}

/// The bus's reason for being down, once it is down with one that
/// contains `words`.
async fn down_saying(d: &TestDaemon, words: &str) -> String {
    let bus = d.plant.buses()[0].handle.clone();
    eventually(EVENT, words, || match bus.port_state() {
        PortState::Down { reason, .. } if reason.contains(words) => Some(reason),
        _ => None,
    })
    .await
}

/// True once process `pid` has `path` open.
fn has_open(pid: u32, path: &Path) -> bool {
    let Ok(target) = std::fs::canonicalize(path) else {
        return false;
    };
    std::fs::read_dir(format!("/proc/{pid}/fd")).is_ok_and(|fds| {
        fds.flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|l| l == target))
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_port_another_program_holds_is_named_with_its_pid_and_taken_once_let_go() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-line1");
        let _sim = ExternalSim::start(&link, "1", &[]).await;
        // Another program holds the adapter's lock before the daemon
        // starts.
        // In a process group of its own: its child (the sleep) inherits
        // the locked descriptor, and both go when it is let go.
        let mut flock = tokio::process::Command::new("flock")
            .arg(&link)
            .args(["sleep", "600"])
            .process_group(0)
            .kill_on_drop(true)
            .spawn()
            .expect("flock (util-linux) runs");
        let pid = flock.id().unwrap();
        eventually(EVENT, "flock holding the port", || {
            has_open(pid, &link).then_some(())
        })
        .await;
        let d = TestDaemon::start_no_wait(&config(&link)).await;
        let named = format!(
            "flock {} sleep 600 (pid {pid}, holds its lock)",
            link.display()
        );
        let reason = down_saying(&d, &named).await;
        assert!(
            reason.starts_with(&format!(
                "cannot open serial port {}: in use by another program: ",
                link.display()
            )) && reason.contains("drivegate opens the port once it lets it go")
                && !reason.contains("dialout")
                && !reason.contains("plugged in"),
            "{reason}"
        );
        // /readyz and the bus-down alarm say the same.
        let api = Api::new(d.http, None);
        let ready = api.get("/readyz").await;
        assert_eq!(ready.status, 503);
        let reasons = ready.body["reasons"].to_string();
        assert!(reasons.contains(&named), "{reasons}");
        let alarms = api.get("/api/v1/alarms?active=true").await.expect(200);
        assert!(
            alarms["alarms"].as_array().unwrap().iter().any(|a| {
                a["kind"] == "bus-down" && a["text"].as_str().is_some_and(|t| t.contains(&named))
            }),
            "{alarms:#}"
        );

        // Let go: the daemon takes the port and reads the drive.
        let group = nix::unistd::Pid::from_raw(i32::try_from(pid).unwrap());
        nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGKILL).unwrap();
        flock.wait().await.unwrap();
        let bus = d.plant.buses()[0].handle.clone();
        eventually(EVENT, "the conveyor live once the port is free", || {
            bus.freshness(1)
                .filter(|v| v.freshness.is_live())
                .map(|_| ())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_to_a_login_sessions_terminal_is_refused_unopened() {
    bounded(LIMIT, async {
        // A pty that a session has as its controlling terminal, as a
        // shell's: what a stale adapter link may lead to once the kernel
        // hands its number out again.
        let pty = nix::pty::openpty(None, None).expect("a pty");
        let slave = std::fs::read_link(format!("/proc/self/fd/{}", pty.slave.as_raw_fd())).unwrap();
        let mut session = tokio::process::Command::new("setsid")
            .args(["--ctty", "sleep", "600"])
            .stdin(std::process::Stdio::from(pty.slave))
            .kill_on_drop(true)
            .spawn()
            .expect("setsid (util-linux) runs");
        let pid = session.id().unwrap();
        // Its terminal is the pty once field 7 of its stat (tty_nr) is set.
        eventually(EVENT, "the session's controlling terminal", || {
            let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
            let after_name = stat.rsplit_once(')')?.1;
            let tty: i64 = after_name.split_whitespace().nth(4)?.parse().ok()?;
            (tty != 0).then_some(())
        })
        .await;
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-stale");
        std::os::unix::fs::symlink(&slave, &link).unwrap();

        let d = TestDaemon::start_no_wait(&config(&link)).await;
        let reason = down_saying(&d, "the terminal of a login session").await;
        assert!(
            reason.starts_with(&format!(
                "refusing serial port {}: it leads to {}, the terminal of a login session (sleep 600, pid {pid}), not a serial line",
                link.display(),
                slave.display()
            )) && reason.contains("/dev/serial/by-id/"),
            "{reason}"
        );
        // Nothing was written to the terminal.
        let mut buf = [0u8; 64];
        let _ = nix::fcntl::fcntl(
            &pty.master,
            nix::fcntl::FcntlArg::F_SETFL(nix::fcntl::OFlag::O_NONBLOCK),
        );
        assert!(
            matches!(nix::unistd::read(&pty.master, &mut buf), Err(nix::errno::Errno::EAGAIN)),
            "the daemon wrote to the terminal"
        );
        d.stop().await;
        session.kill().await.unwrap();
    })
    .await;
}
