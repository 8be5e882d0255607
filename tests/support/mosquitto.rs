//! Debian's `mosquitto` as the MQTT tests' broker: on a free loopback
//! port, anonymous, nothing kept on disk; optionally a TLS listener beside
//! it with certificates made by `openssl` (`certs.rs`), or users in a
//! password file made by `mosquitto_passwd` and an `acl_file`. Killed when
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
        Self::with(None, None)
    }

    /// A broker with a plain listener and a TLS one whose certificate is
    /// `pki`'s `server`, signed by its `ca`.
    pub fn start_tls(pki: &Pki) -> Mosquitto {
        Self::with(Some(pki), None)
    }

    /// A broker that lets in only `users` (name, password: a password
    /// file made by Debian's `mosquitto_passwd`, no anonymous client) and
    /// gives each the topics of `acl` (mosquitto's `acl_file` format).
    pub fn start_with_users(users: &[(&str, &str)], acl: &str) -> Mosquitto {
        Self::with(None, Some((users, acl)))
    }

    /// [`Mosquitto::start_with_users`], with `conf`'s lines added to its
    /// configuration (a block of `docs/security.md`).
    pub fn start_with_users_and(users: &[(&str, &str)], acl: &str, conf: &str) -> Mosquitto {
        Self::configured(None, Some((users, acl)), conf)
    }

    fn with(pki: Option<&Pki>, auth: Option<(&[(&str, &str)], &str)>) -> Mosquitto {
        Self::configured(pki, auth, "")
    }

    fn configured(
        pki: Option<&Pki>,
        auth: Option<(&[(&str, &str)], &str)>,
        extra: &str,
    ) -> Mosquitto {
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
            "persistence false\nper_listener_settings false\n\
             log_dest file {}\nlog_type all\nlistener {port} 127.0.0.1\n",
            dir.path().join("mosquitto.log").display()
        ));
        match auth {
            None => conf.push_str("allow_anonymous true\n"),
            Some((users, acl)) => {
                let passwords = dir.path().join("passwords");
                for (i, (user, password)) in users.iter().enumerate() {
                    let mut cmd = Command::new("mosquitto_passwd");
                    cmd.arg("-b");
                    if i == 0 {
                        cmd.arg("-c");
                    }
                    let out = cmd
                        .arg(&passwords)
                        .args([user, password])
                        .output()
                        .unwrap_or_else(|e| {
                            panic!("{}", tools::cannot_run("mosquitto_passwd", &e))
                        });
                    assert!(
                        out.status.success(),
                        "mosquitto_passwd: {}",
                        String::from_utf8_lossy(&out.stderr)
                    );
                }
                let acl_file = dir.path().join("acl");
                std::fs::write(&acl_file, acl).unwrap();
                conf.push_str(&format!(
                    "allow_anonymous false\npassword_file {}\nacl_file {}\n",
                    passwords.display(),
                    acl_file.display()
                ));
            }
        }
        conf.push_str(extra);
        conf.push('\n');
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

/// One message as `mosquitto_sub` printed it.
#[derive(Debug, Clone)]
pub struct Received {
    /// Its topic.
    pub topic: String,
    /// The retained flag.
    pub retained: bool,
    /// The MQTT 5 correlation data, as text (empty: none).
    pub correlation: String,
    /// The payload, as text.
    pub payload: String,
}

impl Received {
    /// The payload as JSON (`Null` when it is not JSON).
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.payload).unwrap_or(serde_json::Value::Null)
    }
}

/// Debian's `mosquitto_sub`, an MQTT 5 client of the broker on `port`,
/// subscribed to some topics, each message read as it comes. Killed when
/// dropped.
pub struct Sub {
    child: tokio::process::Child,
    lines: tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
    /// Every message read so far.
    pub seen: Vec<Received>,
}

impl Sub {
    /// Subscribes to `topics` on the broker on `port` (MQTT 5, QoS 1).
    pub fn start(port: u16, topics: &[&str]) -> Sub {
        Self::start_as(port, None, topics)
    }

    /// [`Sub::start`], logged in as `login` (user, password).
    pub fn start_as(port: u16, login: Option<(&str, &str)>, topics: &[&str]) -> Sub {
        use tokio::io::AsyncBufReadExt;
        let mut cmd = tokio::process::Command::new("mosquitto_sub");
        if let Some((user, password)) = login {
            cmd.args(["-u", user, "-P", password]);
        }
        cmd.args([
            "-h",
            "127.0.0.1",
            "-p",
            &port.to_string(),
            "-V",
            "mqttv5",
            "-q",
            "1",
        ])
        // One line per message: topic, retained flag, correlation
        // data, payload (the payloads here are one-line JSON).
        .args(["-F", "%t\t%r\t%D\t%p"]);
        for t in topics {
            cmd.args(["-t", t]);
        }
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto_sub", &e)));
        let stdout = child.stdout.take().expect("mosquitto_sub's output");
        Sub {
            child,
            lines: tokio::io::BufReader::new(stdout).lines(),
            seen: Vec::new(),
        }
    }

    /// The next message that `pred` accepts, within `limit`; fails the
    /// test naming `what` and the messages seen.
    pub async fn next(
        &mut self,
        limit: Duration,
        what: &str,
        pred: impl Fn(&Received) -> bool,
    ) -> Received {
        let deadline = tokio::time::Instant::now() + limit;
        loop {
            let line = tokio::time::timeout_at(deadline, self.lines.next_line())
                .await
                .unwrap_or_else(|_| {
                    let last = &self.seen[self.seen.len().saturating_sub(5)..];
                    panic!(
                        "no {what} within {limit:?}; {} messages seen, the last: {:?}",
                        self.seen.len(),
                        last.iter()
                            .map(|m| (&m.topic, m.retained, &m.payload))
                            .collect::<Vec<_>>()
                    )
                })
                .expect("mosquitto_sub's output")
                .unwrap_or_else(|| panic!("mosquitto_sub ended before {what}"));
            let mut parts = line.splitn(4, '\t');
            let mut part = || parts.next().unwrap_or("").to_string();
            let m = Received {
                topic: part(),
                retained: part() == "1",
                correlation: part(),
                payload: part(),
            };
            self.seen.push(m.clone());
            if pred(&m) {
                return m;
            }
        }
    }

    /// Stops the client.
    pub async fn stop(mut self) {
        let _ = self.child.start_kill();
        let _ = self.child.wait().await;
    }
}

/// Publishes `payload` on `topic` with Debian's `mosquitto_pub` (MQTT 5,
/// QoS 1) and `properties` (`["response-topic", "t", "correlation-data",
/// "c"]` pairs for `-D publish`); waits until it is delivered to the
/// broker.
pub async fn publish(port: u16, topic: &str, payload: &str, properties: &[(&str, &str)]) {
    mosquitto_pub(port, topic, payload.as_bytes(), properties, false).await;
}

/// [`publish`] with the retain flag: the broker keeps it and hands it to
/// every later subscriber (with its properties).
pub async fn publish_retained(port: u16, topic: &str, payload: &[u8], properties: &[(&str, &str)]) {
    mosquitto_pub(port, topic, payload, properties, true).await;
}

async fn mosquitto_pub(
    port: u16,
    topic: &str,
    payload: &[u8],
    properties: &[(&str, &str)],
    retain: bool,
) {
    // Any bytes (a Sparkplug payload), from a file.
    let file = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(file.path(), payload).unwrap();
    let mut cmd = tokio::process::Command::new("mosquitto_pub");
    cmd.args([
        "-h",
        "127.0.0.1",
        "-p",
        &port.to_string(),
        "-V",
        "mqttv5",
        "-q",
        "1",
    ])
    .args(["-t", topic])
    .arg("-f")
    .arg(file.path());
    if retain {
        cmd.arg("-r");
    }
    for (name, value) in properties {
        cmd.args(["-D", "publish", name, value]);
    }
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .await
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto_pub", &e)));
    assert!(
        out.status.success(),
        "mosquitto_pub failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Publishes `payload` (any bytes) on `topic` with Debian's `mosquitto_pub`
/// logged in as `user` with `password` (MQTT 3.1.1, QoS 1): returns once
/// the broker acknowledged it, whether its ACL let it through or not.
pub async fn publish_as(
    port: u16,
    login: (&str, &str),
    client_id: &str,
    topic: &str,
    payload: &[u8],
) {
    let file = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(file.path(), payload).unwrap();
    let out = tokio::process::Command::new("mosquitto_pub")
        .args(["-h", "127.0.0.1", "-p", &port.to_string(), "-q", "1"])
        .args(["-u", login.0, "-P", login.1, "-i", client_id, "-t", topic])
        .arg("-f")
        .arg(file.path())
        .stdin(Stdio::null())
        .output()
        .await
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("mosquitto_pub", &e)));
    assert!(
        out.status.success(),
        "mosquitto_pub failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}
