//! What the OPC UA tests of several binaries share: a PKI directory with
//! the server's certificate made by openssl (the daemon's own RSA key
//! generation costs seconds of CPU in a debug build), and asyncua (PyPI,
//! `tests/python/opcua_client.py`) holding a session open, or a lease.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use serde_json::Value;
use tokio::io::{AsyncBufReadExt, BufReader, Lines};
use tokio::process::{Child, ChildStdout, Command};

use super::certs::openssl;
use super::tools;

/// A self-signed application certificate `name.der` / `name-key.pem` in
/// `dir`, for application URI `uri`, valid 30 days.
pub fn application_cert(dir: &Path, name: &str, uri: &str) {
    application_cert_for(dir, name, uri, 30);
}

/// The same, valid `days` days.
pub fn application_cert_for(dir: &Path, name: &str, uri: &str, days: u32) {
    let days = days.to_string();
    openssl(
        dir,
        &[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            &format!("{name}-key.pem"),
            "-out",
            &format!("{name}.pem"),
            "-days",
            &days,
            "-subj",
            &format!("/CN={name}"),
            "-addext",
            &format!("subjectAltName=URI:{uri},DNS:localhost,IP:127.0.0.1"),
            "-addext",
            "keyUsage=critical,digitalSignature,nonRepudiation,keyEncipherment,dataEncipherment",
            "-addext",
            "extendedKeyUsage=clientAuth,serverAuth",
        ],
    );
    openssl(
        dir,
        &[
            "x509",
            "-in",
            &format!("{name}.pem"),
            "-outform",
            "der",
            "-out",
            &format!("{name}.der"),
        ],
    );
}

/// The host's name, as the daemon reads it (its application URI is
/// `urn:<host name>:drivegate`).
pub fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "localhost".into())
}

/// `dir/pki`, an `[opcua] pki_dir` holding a server certificate made by
/// openssl for the daemon's application URI.
pub fn server_pki(dir: &Path) -> PathBuf {
    let pki = dir.join("pki");
    for sub in ["own", "private"] {
        std::fs::create_dir_all(pki.join(sub)).unwrap();
    }
    application_cert(dir, "server", &format!("urn:{}:drivegate", host_name()));
    std::fs::rename(dir.join("server.der"), pki.join("own/cert.der")).unwrap();
    std::fs::rename(dir.join("server-key.pem"), pki.join("private/private.pem")).unwrap();
    pki
}

/// An asyncua session held open: anonymous until [`Held::close`] or the
/// drop (its `hold` scenario), or an operator's that took a lease (its
/// `lease` scenario) until it is killed. The drop kills the client.
pub struct Held {
    child: Child,
    lines: Lines<BufReader<ChildStdout>>,
    /// The client's end of its connection (`127.0.0.1:50412`).
    pub address: String,
}

impl Held {
    /// Opens the session at `url` and waits until it is activated.
    pub async fn open(url: String, limit: Duration) -> Held {
        let mut held = Held::spawn(&url, "hold", &[]);
        let connected = held.until("connected", limit).await;
        held.address = connected["address"]
            .as_str()
            .unwrap_or_default()
            .to_string();
        held
    }

    /// Signs in at `url` as `user` with `password` and takes a lease on
    /// `drive`: SetMode("speed"), Activate(), SpeedSetpoint = `rpm`, each
    /// answered `Good` (else the test fails); the session is kept open.
    pub async fn lease(
        url: &str,
        (user, password): (&str, &str),
        (drive, rpm): (&str, f64),
        limit: Duration,
    ) -> Held {
        let rpm = rpm.to_string();
        let args = [
            "--user",
            user,
            "--password",
            password,
            "--drive",
            drive,
            "--value",
            &rpm,
        ];
        let mut held = Held::spawn(url, "lease", &args);
        let session = held.until("session", limit).await;
        held.address = session["address"].as_str().unwrap_or_default().to_string();
        let leased = held.until("leased", limit).await;
        assert_eq!(leased["status"], "Good", "asyncua: {leased}");
        held
    }

    /// `opcua_client.py URL SCENARIO ARGS`, its input a pipe.
    fn spawn(url: &str, scenario: &str, args: &[&str]) -> Held {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_client.py");
        let mut child = Command::new("python3")
            .arg(script)
            .arg(url)
            .arg(scenario)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run("asyncua", &e)));
        let stdout = child.stdout.take().expect("its output");
        Held {
            child,
            lines: BufReader::new(stdout).lines(),
            address: String::new(),
        }
    }

    async fn until(&mut self, step: &str, limit: Duration) -> Value {
        loop {
            let line = tokio::time::timeout(limit, self.lines.next_line())
                .await
                .unwrap_or_else(|_| panic!("asyncua: no {step:?} step within {limit:?}"))
                .expect("its output")
                .unwrap_or_else(|| panic!("asyncua ended before its {step:?} step"));
            let Ok(v) = serde_json::from_str::<Value>(&line) else {
                continue;
            };
            assert_ne!(v["step"], "error", "asyncua: {v}");
            if v["step"] == step {
                return v;
            }
        }
    }

    /// Closes the session (CloseSession, then the connection) and waits
    /// for the client to end.
    pub async fn close(mut self, limit: Duration) {
        drop(self.child.stdin.take());
        self.until("closed", limit).await;
        let status = tokio::time::timeout(limit, self.child.wait())
            .await
            .expect("asyncua ends")
            .expect("its status");
        assert!(status.success(), "asyncua ended with {status}");
    }

    /// `kill -9`: the client vanishes without closing its session.
    pub async fn kill(mut self) {
        self.child.start_kill().expect("kill -9");
        let _ = self.child.wait().await;
    }
}
