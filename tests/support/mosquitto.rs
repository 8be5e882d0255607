//! Debian's `mosquitto` as the MQTT tests' broker: on a free loopback
//! port, anonymous, nothing kept on disk; optionally a TLS listener beside
//! it with certificates made by `openssl` (`certs.rs`). Killed when
//! dropped; stopped and started again on the same ports by the tests of a
//! broker outage.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::certs::Pki;
use super::tools;

/// A running broker.
pub struct Mosquitto {
    /// The plain listener's port (127.0.0.1).
    pub port: u16,
    /// The TLS listener's port, if any.
    pub tls_port: Option<u16>,
    dir: tempfile::TempDir,
    child: Option<Child>,
}

fn is_root() -> bool {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata("/proc/self").is_ok_and(|m| m.uid() == 0)
}

impl Mosquitto {
    /// A broker with a plain listener.
    pub fn start() -> Mosquitto {
        Self::with(None)
    }

    /// A broker with a plain listener and a TLS one whose certificate is
    /// `pki`'s `server`, signed by its `ca`.
    pub fn start_tls(pki: &Pki) -> Mosquitto {
        Self::with(Some(pki))
    }

    fn with(pki: Option<&Pki>) -> Mosquitto {
        let dir = tempfile::tempdir().unwrap();
        let port = super::ports::free_port();
        let tls_port = pki.map(|_| super::ports::free_port());
        // As root, mosquitto drops to the user `mosquitto`, which could
        // not read the test's files: it stays who it is.
        let mut conf = String::new();
        if is_root() {
            conf.push_str("user root\n");
        }
        conf.push_str(&format!(
            "persistence false\nper_listener_settings false\nallow_anonymous true\n\
             log_dest file {}\nlog_type all\nlistener {port} 127.0.0.1\n",
            dir.path().join("mosquitto.log").display()
        ));
        if let (Some(pki), Some(tls_port)) = (pki, tls_port) {
            conf.push_str(&format!(
                "listener {tls_port} 127.0.0.1\ncafile {}\ncertfile {}\nkeyfile {}\n",
                pki.path("ca.pem").display(),
                pki.path("server.pem").display(),
                pki.path("server.key").display(),
            ));
        }
        std::fs::write(dir.path().join("mosquitto.conf"), conf).unwrap();
        let mut broker = Mosquitto {
            port,
            tls_port,
            dir,
            child: None,
        };
        broker.resume();
        broker
    }

    /// `mqtt://127.0.0.1:port`.
    pub fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }

    /// `mqtts://127.0.0.1:port` (the TLS listener).
    pub fn tls_url(&self) -> String {
        format!(
            "mqtts://127.0.0.1:{}",
            self.tls_port.expect("a TLS listener")
        )
    }

    /// The broker's log so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("mosquitto.log")).unwrap_or_default()
    }

    fn conf(&self) -> PathBuf {
        self.dir.path().join("mosquitto.conf")
    }

    /// Kills the broker (SIGKILL: its clients see their connection drop).
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Starts the broker (again) on its ports, and waits until the plain
    /// listener accepts connections (10 s at most).
    pub fn resume(&mut self) {
        assert!(self.child.is_none(), "the broker runs already");
        let child = Command::new("mosquitto")
            .arg("-c")
            .arg(self.conf())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto", &e)));
        self.child = Some(child);
        let start = Instant::now();
        let ports: Vec<u16> = std::iter::once(self.port).chain(self.tls_port).collect();
        for port in ports {
            while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
                if let Some(Ok(Some(status))) = self.child.as_mut().map(|c| c.try_wait()) {
                    panic!("mosquitto exited ({status}): {}", self.log());
                }
                assert!(
                    start.elapsed() < Duration::from_secs(10),
                    "mosquitto does not listen on {port} after 10 s: {}",
                    self.log()
                );
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        self.stop();
    }
}
