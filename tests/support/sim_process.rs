//! `drivegate sim` in a process of its own, as an adapter with drives
//! behind it: the daemon opens its link as it would a
//! `/dev/serial/by-id/` path, and killing the process takes the pty away
//! as unplugging the adapter would.

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, BufReader};

/// The simulator's process.
pub struct ExternalSim {
    child: tokio::process::Child,
    link: std::path::PathBuf,
}

impl ExternalSim {
    /// Starts `drivegate sim --units <units> --link <link>` with `args`
    /// and waits for the line that says it serves.
    pub async fn start(link: &Path, units: &str, args: &[&str]) -> ExternalSim {
        let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["sim", "--units", units, "--turnaround-ms", "0.5"])
            .args(args)
            .arg("--link")
            .arg(link)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .expect("drivegate sim starts");
        let mut lines = BufReader::new(child.stdout.take().expect("its output")).lines();
        let first = tokio::time::timeout(Duration::from_secs(10), lines.next_line())
            .await
            .expect("drivegate sim prints its pty within 10 s")
            .expect("its output")
            .expect("a line");
        assert!(first.starts_with("/dev/pts/"), "{first}");
        ExternalSim {
            child,
            link: link.to_path_buf(),
        }
    }

    /// The adapter unplugged: its link goes (as udev removes a by-id
    /// link), then `kill -9` takes the pty with the process. The link goes
    /// first: a pty number the kernel hands out again (to another test's
    /// simulator) must not be reached through it.
    pub async fn kill(mut self) {
        std::fs::remove_file(&self.link).expect("the link removed");
        self.child.start_kill().expect("kill -9");
        let _ = self.child.wait().await;
    }
}
