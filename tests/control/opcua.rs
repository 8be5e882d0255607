//! The OPC UA face with two third-party clients, and what its tests share:
//! the daemon with `[opcua]` on loopback (`Ua`) and the client processes
//! (`Client`, `Table`); the tests, one concept a file, are
//! `opcua_browse.rs`, `opcua_operate.rs`, `opcua_certificates.rs`,
//! `opcua_wire.rs`, `opcua_attacks.rs`, and here a reload of `[opcua]`.
//! The clients: asyncua (PyPI, in the
//! test venv; `tests/python/opcua_client.py`) and node-opcua's client (npm,
//! installed under `target/node-opcua` by `scripts/test`;
//! `tests/node/opcua_client.js`). Each scenario is a client process that
//! prints one JSON line per step; the test reads them and checks the
//! daemon's side too (the simulated motor, the alarm book, the PKI
//! directory, the audit).
//!
//! The server's certificate is made by openssl in the test's PKI directory
//! before the start (the daemon's own RSA key generation costs seconds of
//! CPU in a debug build), but in the certificate test, where the daemon
//! makes it at its first start.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use serde_json::Value;
use tokio::io::{AsyncBufReadExt, BufReader, Lines};
use tokio::process::{Child, ChildStdout, Command};

use crate::support::TestDaemon;
use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::input::{OPERATOR, role_tokens};
use crate::support::opcua::server_pki;
use crate::support::tools;
use crate::support::wait::bounded;

pub(crate) const LIMIT: Duration = Duration::from_secs(150);
/// Longest wait for one client step.
pub(crate) const STEP: Duration = Duration::from_secs(60);
/// The operator's user name: its `[[http.token]]`'s name.
pub(crate) const USER: &str = "scada";

/// What `DriveType` has: its variables, methods and settings object.
/// A drive's children in browse order: the manual's (the status block's
/// registers, its flags, `Online`, the setpoints, the settings, the config
/// commands).
pub(crate) const DRIVE_CHILDREN: [&str; 22] = [
    "Turns",
    "Angle",
    "Speed",
    "Current",
    "Voltage",
    "Temperature",
    "Active",
    "Calibrated",
    "Stalled",
    "Mode",
    "Fault",
    "FaultCode",
    "Online",
    "SpeedSetpoint",
    "PositionSetpoint",
    "TorqueSetpoint",
    "Settings",
    "Activate",
    "Deactivate",
    "Brake",
    "FaultReset",
    "SetMode",
];

/// A daemon with `[opcua]` on loopback (a `none` endpoint beside
/// Basic256Sha256), its PKI directory and where it listens.
pub(crate) struct Ua {
    pub(crate) d: TestDaemon,
    pub(crate) url: String,
    pub(crate) pki: PathBuf,
    _dir: tempfile::TempDir,
}

/// The keys of an `[opcua]` section on loopback (a `none` endpoint beside
/// Basic256Sha256, sessions of at most 3 s) with its PKI directory in
/// `dir/pki`, holding a server certificate made by openssl.
pub(crate) fn section(dir: &Path) -> String {
    section_keys(&server_pki(dir))
}

/// The keys of the `[opcua]` section with `pki` (made by the daemon at its
/// first start if it holds no certificate).
pub(crate) fn section_keys(pki: &Path) -> String {
    format!(
        "listen = \"127.0.0.1:0\"\npki_dir = \"{}\"\nsecurity = [\"none\", \"basic256sha256\"]\nsession_timeout_max_ms = 3000",
        pki.display()
    )
}

impl Ua {
    /// The four drives (or `port`'s bus of two) with `[opcua]`, the role
    /// tokens, and a safety state directory.
    pub(crate) async fn start(port: Option<&Path>) -> Ua {
        let dir = tempfile::tempdir().unwrap();
        let section = section(dir.path());
        Ua::start_with(port, dir, section).await
    }

    /// The same, with `section` and its directory.
    pub(crate) async fn start_with(
        port: Option<&Path>,
        dir: tempfile::TempDir,
        section: String,
    ) -> Ua {
        let builder = match port {
            None => ConfigBuilder::four_drives(),
            Some(link) => ConfigBuilder::new().bus("line1", |b| {
                b.port(&link.display().to_string())
                    .drive(1, "conveyor")
                    .drive(2, "belt")
            }),
        };
        Ua::start_plant(builder, port.is_some(), dir, section).await
    }

    /// The drives of `builder` (on an external simulator's link: the
    /// start does not wait for them), with `section` and its directory.
    pub(crate) async fn start_plant(
        builder: ConfigBuilder,
        external: bool,
        dir: tempfile::TempDir,
        section: String,
    ) -> Ua {
        let pki = dir.path().join("pki");
        let toml = role_tokens(builder)
            .section("opcua", &section)
            .section(
                "safety",
                &format!("state_dir = \"{}\"", dir.path().join("state").display()),
            )
            .toml();
        let d = if external {
            TestDaemon::start_no_wait(&toml).await
        } else {
            TestDaemon::start(&toml).await
        };
        let addr: SocketAddr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        let url = format!("opc.tcp://{addr}/");
        let ua = Ua {
            d,
            url,
            pki,
            _dir: dir,
        };
        ua.wait_serving().await;
        ua
    }

    /// Until `/readyz` says the server serves.
    async fn wait_serving(&self) {
        let api = Api::new(self.d.http, None);
        let t0 = Instant::now();
        loop {
            let r = api.get("/readyz").await;
            if r.body["opcua"]["serving"] == true {
                return;
            }
            assert!(t0.elapsed() < STEP, "OPC UA not serving: {:#}", r.body);
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// A client process: asyncua or node-opcua.
pub(crate) struct Client {
    child: Child,
    lines: Lines<BufReader<ChildStdout>>,
    name: &'static str,
    /// Its standard error, for the failure's message.
    stderr: tempfile::NamedTempFile,
}

/// asyncua answering requests one by one (its `table` scenario): one
/// session per user, kept open.
pub(crate) struct Table {
    client: Client,
    stdin: tokio::process::ChildStdin,
}

impl Table {
    pub(crate) async fn start(url: &str) -> Table {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_client.py");
        let mut cmd = Command::new("python3");
        cmd.arg(script).arg(url).arg("table").stdin(Stdio::piped());
        let mut client = Client::spawn(cmd, "asyncua");
        let stdin = client.child.stdin.take().expect("its input");
        client.until("ready").await;
        Table { client, stdin }
    }

    /// The status code `request` gets (`user`, `password`, `op` ...).
    pub(crate) async fn ask(&mut self, request: Value) -> String {
        use tokio::io::AsyncWriteExt;
        let line = format!("{request}\n");
        self.stdin
            .write_all(line.as_bytes())
            .await
            .expect("a request");
        let v = self.client.until("result").await;
        v["status"].as_str().unwrap_or_default().to_string()
    }
}

/// The operator's credentials as client arguments.
pub(crate) fn operator() -> Vec<String> {
    ["--user", USER, "--password", OPERATOR]
        .map(String::from)
        .to_vec()
}

impl Client {
    /// `tests/python/opcua_client.py URL SCENARIO ARGS`.
    pub(crate) fn asyncua(url: &str, scenario: &str, args: &[String]) -> Client {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_client.py");
        let mut cmd = Command::new("python3");
        cmd.arg(script).arg(url).arg(scenario).args(args);
        Client::spawn(cmd, "asyncua")
    }

    /// `tests/node/opcua_client.js URL SCENARIO ARGS` with node-opcua from
    /// `target/node-opcua` (scripts/test installs it there).
    pub(crate) fn node(url: &str, scenario: &str, pki: &Path, args: &[String]) -> Client {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let modules = root.join("target/node-opcua/node_modules");
        assert!(
            modules.join("node-opcua-client").is_dir(),
            "node-opcua-client is not installed in {}: run scripts/test (it runs \
             `npm ci` there from tests/node/package-lock.json)",
            modules.display()
        );
        let mut cmd = Command::new("node");
        cmd.env("NODE_PATH", modules)
            .arg(root.join("tests/node/opcua_client.js"))
            .arg(url)
            .arg(scenario)
            .arg("--pki")
            .arg(pki)
            .args(args);
        Client::spawn(cmd, "node-opcua")
    }

    fn spawn(mut cmd: Command, name: &'static str) -> Client {
        let stderr = tempfile::NamedTempFile::new().expect("a file for its errors");
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(stderr.reopen().expect("its errors' file"))
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run(name, &e)));
        let stdout = child.stdout.take().expect("its output");
        Client {
            child,
            lines: BufReader::new(stdout).lines(),
            name,
            stderr,
        }
    }

    /// The end of what it wrote to its standard error.
    fn errors(&self) -> String {
        let text = std::fs::read_to_string(self.stderr.path()).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }

    /// The next step the client prints (failing on its `error` step).
    pub(crate) async fn next(&mut self) -> Option<Value> {
        loop {
            let line = tokio::time::timeout(STEP, self.lines.next_line())
                .await
                .unwrap_or_else(|_| panic!("{}: no line within {STEP:?}", self.name))
                .expect("its output")?;
            let Ok(v) = serde_json::from_str::<Value>(&line) else {
                continue;
            };
            assert_ne!(v["step"], "error", "{}: {v}\n{}", self.name, self.errors());
            return Some(v);
        }
    }

    /// Reads steps until one named `step`.
    pub(crate) async fn until(&mut self, step: &str) -> Value {
        loop {
            match self.next().await {
                Some(v) if v["step"] == step => return v,
                Some(_) => {}
                None => panic!("{}: ended before its {step:?} step", self.name),
            }
        }
    }

    /// Every step until the client ends, by name.
    pub(crate) async fn steps(mut self) -> Vec<Value> {
        let mut all = Vec::new();
        while let Some(v) = self.next().await {
            all.push(v);
        }
        let status = self.child.wait().await.expect("it ends");
        assert!(
            status.success(),
            "{} ended with {status}: {all:?}\n{}",
            self.name,
            self.errors()
        );
        all
    }

    /// `kill -9`.
    pub(crate) async fn kill(mut self) {
        self.child.start_kill().expect("kill -9");
        let _ = self.child.wait().await;
    }
}

/// How the audit names `user`'s session of a client whose `step` says its
/// end of the connection (`address`): `scada (127.0.0.1:50412)`.
pub(crate) fn client_named(user: &str, step: &Value) -> String {
    let address = step["address"].as_str().unwrap_or_default();
    let ours: SocketAddr = address
        .parse()
        .unwrap_or_else(|_| panic!("the client's address: {step}"));
    assert!(ours.ip().is_loopback() && ours.port() != 0, "{step}");
    format!("{user} ({ours})")
}

pub(crate) fn step<'a>(steps: &'a [Value], name: &str) -> &'a Value {
    steps
        .iter()
        .find(|s| s["step"] == name)
        .unwrap_or_else(|| panic!("no {name:?} step in {steps:#?}"))
}

/// A reload that changes `[opcua]` restarts the OPC UA server alone, with
/// the new section: anonymous sessions, allowed before, are refused after.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_restarts_the_server_with_the_new_section() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let section = section(dir.path());
        let with = |extra: &str| {
            role_tokens(ConfigBuilder::four_drives())
                .section("opcua", &format!("{section}\n{extra}"))
                .toml()
        };
        let d = TestDaemon::reloadable(&with("")).await;
        let url = |addr: SocketAddr| format!("opc.tcp://{addr}/");
        let addr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        // The drives are polled, and nobody has connected: the server and
        // its address space are not built yet, so no poll's values went in.
        let published = || {
            metric_sum(
                &d.metrics.render(),
                "drivegate_opcua_values_published_total",
            )
        };
        while metric_sum(&d.metrics.render(), "drivegate_bus_polls_total") < 8.0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert_eq!(published(), 0.0);
        let all = Client::asyncua(&url(addr), "brake", &[]).steps().await;
        assert_eq!(
            step(&all, "brake")["status"],
            "BadUserAccessDenied",
            "{all:?}"
        );
        // Built at the first client: each poll's values go in since.
        assert!(published() > 0.0);

        d.rewrite(&with("anonymous = \"none\""));
        let reply = Api::new(d.http, Some(crate::support::input::ADMIN))
            .post_empty("/api/v1/config/reload")
            .await
            .expect(200);
        assert!(reply["changes"].to_string().contains("OPC UA"), "{reply}");
        let addr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        let t0 = Instant::now();
        loop {
            let all = Client::asyncua(&url(addr), "brake", &[]).steps().await;
            if all.iter().any(|s| s["step"] == "session") {
                break;
            }
            assert!(t0.elapsed() < STEP, "anonymous still served: {all:?}");
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let all = Client::asyncua(&url(addr), "brake", &operator())
            .steps()
            .await;
        assert_eq!(step(&all, "brake")["status"], "Good", "{all:?}");
    })
    .await;
}

/// The sum of the samples of `name` (every label set) in `text`.
fn metric_sum(text: &str, name: &str) -> f64 {
    text.lines()
        .filter_map(|l| {
            let (head, value) = l.rsplit_once(' ')?;
            let metric = head.split('{').next()?;
            (metric == name).then(|| value.parse::<f64>().ok())?
        })
        .sum()
}
