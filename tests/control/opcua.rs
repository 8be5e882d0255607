//! The OPC UA face with two third-party clients: asyncua (PyPI, in the
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
use crate::support::api::{Api, connect, wait_for};
use crate::support::certs::openssl;
use crate::support::config::ConfigBuilder;
use crate::support::input::{OPERATOR, VIEWER, role_tokens};
use crate::support::metrics::metric;
use crate::support::opcua::{application_cert, host_name, server_pki};
use crate::support::sim_process::ExternalSim;
use crate::support::tools;
use crate::support::wait::{bounded, eventually};

pub(crate) const LIMIT: Duration = Duration::from_secs(150);
/// Longest wait for one client step.
pub(crate) const STEP: Duration = Duration::from_secs(60);
/// The operator's user name: its `[[http.token]]`'s name.
pub(crate) const USER: &str = "scada";

/// What `DriveType` has: its variables, methods and settings object.
/// A drive's children in browse order: the manual's (the status block's
/// registers, its flags, `Online`, the setpoints, the settings, the config
/// commands).
const DRIVE_CHILDREN: [&str; 22] = [
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
    fn node(url: &str, scenario: &str, pki: &Path, args: &[String]) -> Client {
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
fn client_named(user: &str, step: &Value) -> String {
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

/// Endpoints, browse, read with units, the anonymous write and HistoryRead,
/// as both clients see them, each client running its scenarios in one
/// process, both at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_clients_browse_read_with_units_and_read_history() {
    bounded(LIMIT, async {
        let ua = Ua::start(None).await;
        let pki = ua.pki.parent().unwrap().join("node-pki");
        let (all, node) = tokio::join!(
            Client::asyncua(
                &ua.url,
                "endpoints,browse,read,described,anonymous-write,history",
                &["--drive".into(), "lift".into()],
            )
            .steps(),
            Client::node(
                &ua.url,
                "endpoints,browse,read,described,history",
                &pki,
                &[]
            )
            .steps(),
        );
        let endpoints = step(&all, "endpoints")["endpoints"]
            .as_array()
            .unwrap()
            .clone();
        let policies: Vec<_> = endpoints
            .iter()
            .map(|e| e["policy"].as_str().unwrap())
            .collect();
        assert!(
            policies.contains(&"None") && policies.contains(&"Basic256Sha256"),
            "{endpoints:?}"
        );
        for e in &endpoints {
            assert_eq!(
                e["tokens"],
                serde_json::json!(["Anonymous", "Certificate", "UserName"]),
                "{e}"
            );
            if e["policy"] == "Basic256Sha256" {
                assert_eq!(e["mode"], "SignAndEncrypt");
            }
        }

        let browse = step(&all, "browse");
        assert_eq!(
            browse["drives"],
            serde_json::json!(["conveyor", "feeder", "lift", "turntable"])
        );
        assert_eq!(browse["type"], "DriveType");
        assert_eq!(browse["buses"], serde_json::json!(["sim"]));
        for child in DRIVE_CHILDREN {
            assert!(
                browse["children"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|c| c == child),
                "{child}: {browse}"
            );
        }

        let read = step(&all, "read");
        let speed = &read["values"]["Speed"];
        assert_eq!(
            (speed["status"].as_str(), speed["type"].as_str()),
            (Some("Good"), Some("Double"))
        );
        // UNECE codes: RPM, CEL, VLT.
        assert_eq!(
            (speed["unit"].as_str(), speed["unit_id"].as_u64()),
            (Some("r/min"), Some(5_394_509))
        );
        assert_eq!(read["values"]["Temperature"]["unit_id"], 4_408_652);
        assert_eq!(read["values"]["Voltage"]["unit_id"], 5_655_636);
        assert!(
            speed["low"].as_f64().unwrap() < 0.0 && speed["high"].as_f64().unwrap() > 0.0,
            "{speed}"
        );
        assert!(
            speed["source_timestamp"]
                .as_str()
                .is_some_and(|t| !t.is_empty()),
            "{speed}"
        );
        assert_eq!(read["values"]["Turns"]["type"], "Int32");
        assert_eq!(read["values"]["FaultCode"]["type"], "UInt16");
        assert_eq!(read["values"]["Online"]["value"], true);
        // The poll's period is the fastest sampling.
        assert!(read["min_sampling_ms"].as_f64().unwrap() > 0.0, "{read}");

        // Every node under a drive says what it is; the drive's children
        // come in the manual's order; Mode is a DriveMode, an enumeration
        // with its names; SetMode's argument says what it takes.
        let described = step(&all, "described");
        assert_eq!(
            described["order"],
            serde_json::json!(DRIVE_CHILDREN),
            "{described}"
        );
        assert_eq!(described["missing"], serde_json::json!([]), "{described}");
        assert!(described["nodes"].as_u64().unwrap() > 40, "{described}");
        assert_eq!(described["mode_type"], "DriveMode");
        assert_eq!(
            described["enum_strings"],
            serde_json::json!(["OpenLoop", "Speed", "Position", "Torque"])
        );
        assert!(described["mode_value"].is_i64(), "{described}");
        assert_eq!(described["argument"]["name"], "Mode");
        assert!(
            described["argument"]["description"]
                .as_str()
                .unwrap()
                .contains("speed, position or torque"),
            "{described}"
        );
        assert_eq!(read["values"]["Mode"]["type"], "Int32", "{read}");

        let refused = step(&all, "anonymous-write");
        assert_eq!(refused["status"], "BadUserAccessDenied", "{refused}");
        // Its UserAccessLevel shows no write (CurrentRead only).
        assert_eq!(refused["user_access_level"], 1, "{refused}");

        let history = step(&all, "history");
        assert!(history["count"].as_u64().unwrap() > 5, "{history}");
        assert_eq!(history["five"], 5, "{history}");

        // node-opcua: the same server through a second implementation.
        node_sees_the_same(&node, endpoints.len(), &browse["drives"]);
    })
    .await;
}

/// node-opcua's view (its steps `node`): as many endpoints, the same
/// drives, Speed read with its unit, HistoryRead.
fn node_sees_the_same(node: &[Value], endpoints: usize, drives: &Value) {
    assert_eq!(
        step(node, "endpoints")["endpoints"]
            .as_array()
            .unwrap()
            .len(),
        endpoints
    );
    assert_eq!(step(node, "browse")["drives"], *drives);
    let described = step(node, "described");
    assert_eq!(
        described["order"],
        serde_json::json!(DRIVE_CHILDREN),
        "{described}"
    );
    assert_eq!(described["missing"], serde_json::json!([]), "{described}");
    assert_eq!(described["mode_type"], "DriveMode");
    assert_eq!(
        described["enum_strings"],
        serde_json::json!(["OpenLoop", "Speed", "Position", "Torque"])
    );
    let speed = &step(node, "read")["values"]["Speed"];
    assert_eq!(
        (speed["status"].as_str(), speed["unit_id"].as_u64()),
        (Some("Good"), Some(5_394_509))
    );
    let history = step(node, "history");
    assert_eq!(history["status"], "Good");
    assert!(history["count"].as_u64().unwrap() > 5, "{history}");
}

/// An operator (user name = the token's name, password = the token) sets
/// the mode, activates and writes SpeedSetpoint; the motor turns, the
/// subscription is notified at the poll rate (and through absolute and
/// percent deadbands as wide as they say), an out-of-range setpoint is
/// refused with the range in the diagnostics, and so is a mode the drive
/// does not have. The operator's writes, its refused ones included, and an
/// anonymous session's refused one are audited by user and the client's
/// address, `<user> (127.0.0.1:<port>)` (face `opcua`). node-opcua does the
/// same on another drive at the same time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_sets_the_mode_activates_and_writes_the_speed_setpoint() {
    bounded(LIMIT, async {
        let ua = Ua::start(None).await;
        // The audit's lines, as the stream's `write` messages carry them.
        let mut ws = connect(ua.d.http, "?drives=all", Some(VIEWER)).await;
        let mut args = operator();
        args.extend([
            "--value".into(),
            "600".into(),
            "--metrics".into(),
            format!("http://{}/metrics", ua.d.http),
        ]);
        // node-opcua at the same time, on the feeder.
        let pki = ua.pki.parent().unwrap().join("node-pki");
        let mut node_args = operator();
        node_args.extend([
            "--drive".into(),
            "feeder".into(),
            "--value".into(),
            "450".into(),
        ]);
        let (all, node) = tokio::join!(
            Client::asyncua(&ua.url, "operate", &args).steps(),
            Client::node(&ua.url, "operate", &pki, &node_args).steps(),
        );
        assert_eq!(step(&all, "written")["status"], "Good", "{all:?}");
        assert_eq!(step(&all, "turned")["reached"], 600.0, "{all:?}");
        // The simulated motor turned (the conveyor's gear: 3.75): its
        // angle changes at every poll.
        let angle = step(&all, "angle");
        subscribed_at_the_poll_rate(angle);
        // Deadband filters on the same angle: a narrow one lets every step
        // through, one no change can exceed only the first value.
        let deadbands = &angle["deadbands"];
        for narrow in ["absolute-narrow", "percent-narrow"] {
            assert!(deadbands[narrow].as_u64() >= Some(8), "{narrow}: {angle}");
        }
        for wide in ["absolute-wide", "percent-wide"] {
            assert_eq!(deadbands[wide], 1, "{wide}: {angle}");
        }
        let out = step(&all, "out-of-range");
        assert_eq!(out["status"], "BadOutOfRange", "{out}");
        assert!(
            out["diagnostics"]
                .as_str()
                .unwrap()
                .contains("valid -2048 to 2047 rpm"),
            "{out}"
        );
        eventually(
            Duration::from_secs(20),
            "the brake stopping the conveyor",
            || (ua.d.sim().drive(1)?.speed_rpm.abs() < 1.0).then_some(()),
        )
        .await;
        // /metrics: the notifications the subscriptions were sent.
        eventually(Duration::from_secs(10), "notifications counted", || {
            let text = ua.d.metrics.render();
            (metric(&text, "drivegate_opcua_notifications_total") >= 10.0).then_some(())
        })
        .await;
        // The audit names each session by its user and its client's
        // address, as the client itself sees its end of the connection.
        let anonymous = step(&all, "anonymous-write");
        assert_eq!(anonymous["status"], "BadUserAccessDenied", "{anonymous}");
        let audit = wait_for(&mut ws, STEP, "the refusal's audit line", |m| {
            m["type"] == "write"
                && m["drive"] == "conveyor"
                && m["what"]
                    .as_str()
                    .is_some_and(|w| w.contains("speed setpoint 100 rpm"))
        })
        .await;
        assert_eq!(audit["ok"], false, "{audit}");
        assert_eq!(
            audit["who"].as_str(),
            Some(client_named("anonymous", anonymous).as_str()),
            "{audit}"
        );
        assert!(
            audit["answer"]
                .as_str()
                .is_some_and(|a| a.contains("operator")),
            "{audit}"
        );
        let audit = wait_for(&mut ws, STEP, "the setpoint's audit line", |m| {
            m["type"] == "write"
                && m["drive"] == "conveyor"
                && m["what"]
                    .as_str()
                    .is_some_and(|w| w.contains("speed setpoint 600 rpm"))
        })
        .await;
        assert_eq!(
            audit["who"].as_str(),
            Some(client_named(USER, step(&all, "connected")).as_str()),
            "{audit}"
        );
        assert_eq!(audit["ok"], true, "{audit}");
        // Refused before it became a request, and audited all the same:
        // the value out of range, the mode the drive does not have.
        assert_eq!(
            step(&all, "set-mode-wrong")["status"],
            "BadInvalidArgument",
            "{all:?}"
        );
        for (what, why) in [
            ("speed setpoint 99999 rpm", "valid -2048 to 2047 rpm"),
            ("mode \"fast\"", "speed, position or torque"),
        ] {
            let audit = wait_for(&mut ws, STEP, what, |m| {
                m["type"] == "write"
                    && m["drive"] == "conveyor"
                    && m["what"].as_str().is_some_and(|w| w.contains(what))
            })
            .await;
            assert_eq!(audit["ok"], false, "{audit}");
            assert_eq!(
                audit["who"].as_str(),
                Some(client_named(USER, step(&all, "connected")).as_str()),
                "{audit}"
            );
            assert!(
                audit["answer"]
                    .as_str()
                    .is_some_and(|a| a.starts_with("refused: ") && a.contains(why)),
                "{audit}"
            );
        }

        // node-opcua, on the feeder.
        assert_eq!(
            step(&node, "anonymous-write")["status"],
            "BadUserAccessDenied",
            "{node:?}"
        );
        assert_eq!(step(&node, "written")["status"], "Good", "{node:?}");
        assert_eq!(step(&node, "turned")["reached"], 450.0, "{node:?}");
        assert_eq!(
            step(&node, "out-of-range")["status"],
            "BadOutOfRange",
            "{node:?}"
        );
    })
    .await;
}

/// The Angle's monitored item of `angle` (the `operate` scenario's step):
/// at the sampling interval the variable says is its minimum, the poll's
/// period (four drives polled flat out at 115200 baud: a round of at least
/// 4 x 4.09 ms, far below the crate's own 100 ms), in a subscription
/// publishing as often with a queue of one, it is notified about as often
/// as its drive is polled (the bus's polls from /metrics over the window,
/// shared by its four drives), not capped at the crate's 10 a second (nor
/// at the 7 a second of the freshness's period, 136 ms, once the minimum).
fn subscribed_at_the_poll_rate(angle: &Value) {
    let sampling = angle["sampling_ms"].as_f64().unwrap_or_default();
    assert!((16.0..17.0).contains(&sampling), "{angle}");
    assert_eq!(angle["publishing_ms"].as_f64(), Some(sampling), "{angle}");
    let window = angle["window_s"].as_f64().unwrap_or_default();
    let notified = angle["notifications"].as_f64().unwrap_or_default() / window;
    let polled = angle["polls"].as_f64().unwrap_or_default() / 4.0 / window;
    // However fast a loaded machine lets the bus poll: as often as that
    // (so more than 10 a second whenever the drive is polled more than
    // 12.5 times a second, as it is on an idle machine, about 37).
    assert!(
        notified >= 0.8 * polled && notified <= 1.1 * polled + 1.0,
        "{notified:.1} notifications a second for {polled:.1} polls a second: {angle}"
    );
}

/// A client killed with -9 while its setpoint holds a lease: its session
/// times out (3 s, the most `[opcua]` allows here) and the lease ends with
/// `comm_loss_action` (zero speed): the motor stops. Both clients, at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_client_whose_session_times_out_stops_the_motor() {
    bounded(LIMIT, async {
        let ua = Ua::start(None).await;
        let pki = ua.pki.parent().unwrap().join("node-pki");
        // Both clients at once, each on its drive.
        let leg = |unit: u8, drive: &'static str, client: &'static str| {
            let (ua, pki) = (&ua, &pki);
            async move {
                let mut args = operator();
                args.extend([
                    "--drive".into(),
                    drive.into(),
                    "--value".into(),
                    "300".into(),
                ]);
                let mut c = match client {
                    "asyncua" => Client::asyncua(&ua.url, "lease", &args),
                    _ => Client::node(&ua.url, "lease", pki, &args),
                };
                let leased = c.until("leased").await;
                assert_eq!(leased["status"], "Good", "{client}: {leased}");
                eventually(Duration::from_secs(20), "the motor turning", || {
                    (ua.d.sim().drive(unit)?.speed_rpm.abs() > 50.0).then_some(())
                })
                .await;
                c.kill().await;
                let t0 = Instant::now();
                eventually(
                    Duration::from_secs(20),
                    "the motor stopped by the lease's end",
                    || (ua.d.sim().drive(unit)?.speed_rpm.abs() < 1.0).then_some(()),
                )
                .await;
                // Not before the session's timeout: the session outlives its
                // connection that long (a client may reconnect).
                assert!(
                    t0.elapsed() >= Duration::from_millis(1500),
                    "{client}: stopped after {:?}",
                    t0.elapsed()
                );
            }
        };
        tokio::join!(leg(1, "conveyor", "asyncua"), leg(2, "lift", "node-opcua"));
    })
    .await;
}

/// The server's certificate is made at the first start (its SANs: the
/// application URI and the address); an unknown client certificate is
/// refused and saved in `rejected/certs` as `<application
/// name>-<thumbprint>.der`; copied to `trusted/certs` as PEM under a name
/// of its own (the rejected copy left where it is), the same client is
/// served, without a restart, trusted by its content; the docs' `mv` line
/// works as written.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_certificate_is_refused_then_trusted_without_a_restart() {
    bounded(LIMIT, async {
        // The server's own certificate made at its first start.
        let dir = tempfile::tempdir().unwrap();
        let section = section_keys(&dir.path().join("pki"));
        let ua = Ua::start_with(None, dir, section).await;
        let own = ua.pki.join("own/cert.der");
        let out = std::process::Command::new("openssl")
            .args([
                "x509",
                "-inform",
                "der",
                "-noout",
                "-ext",
                "subjectAltName",
                "-in",
            ])
            .arg(&own)
            .output()
            .unwrap();
        let san = String::from_utf8_lossy(&out.stdout);
        assert!(
            san.contains(&format!("URI:urn:{}:drivegate", host_name())),
            "{san}"
        );
        assert!(san.contains("127.0.0.1"), "{san}");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(ua.pki.join("private/private.pem"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);

        let dir = ua.pki.parent().unwrap().to_path_buf();
        application_cert(&dir, "pyclient", "urn:freeopcua:client");
        let args: Vec<String> = [
            "--policy",
            "basic256sha256",
            "--cert",
            &dir.join("pyclient.der").display().to_string(),
            "--key",
            &dir.join("pyclient-key.pem").display().to_string(),
        ]
        .map(String::from)
        .to_vec();
        let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
        assert_ne!(step(&all, "secure")["status"], "Good", "{all:?}");
        let rejected = ua.pki.join("rejected/certs");
        let file = eventually(
            Duration::from_secs(20),
            "the certificate in rejected/certs",
            || {
                std::fs::read_dir(&rejected)
                    .ok()?
                    .flatten()
                    .map(|e| e.path())
                    .next()
            },
        )
        .await;
        // Counted once the mirror has moved it (the same pass).
        eventually(Duration::from_secs(10), "the refusal counted", || {
            let text = ua.d.metrics.render();
            (metric(&text, "drivegate_opcua_rejected_certificates_total") >= 1.0).then_some(())
        })
        .await;
        // Saved under a name that needs no quoting: the application's name
        // and the SHA-1 thumbprint.
        let der = std::fs::read(dir.join("pyclient.der")).unwrap();
        let thumbprint: String = drivegate::tls::sha1_fingerprint(&der)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let name = file.file_name().unwrap().to_string_lossy().to_string();
        assert_eq!(name, format!("pyclient-{thumbprint}.der"));
        // Copied (not moved) from the client's machine, as PEM under a name
        // of its own: trusted by its content, whatever rejected/ still holds.
        openssl(
            &dir,
            &[
                "x509",
                "-inform",
                "der",
                "-in",
                "pyclient.der",
                "-out",
                "copied.pem",
            ],
        );
        std::fs::copy(
            dir.join("copied.pem"),
            ua.pki.join("trusted/certs/pyclient from the laptop.pem"),
        )
        .unwrap();
        assert!(file.is_file(), "the rejected copy stays");
        // Trusted at the next secure channel (the store follows the
        // directory every second).
        let t0 = Instant::now();
        loop {
            let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
            if step(&all, "secure")["status"] == "Good" {
                break;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "still refused: {all:?}"
            );
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
        // The docs' `mv` line, as written (no quoting), works too.
        let mv = format!(
            "mv {}/{name} {}/",
            rejected.display(),
            ua.pki.join("trusted/certs").display()
        );
        let done = std::process::Command::new("sh")
            .args(["-c", &mv])
            .status()
            .unwrap();
        assert!(done.success(), "{mv}");
        let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
        assert_eq!(step(&all, "secure")["status"], "Good", "{all:?}");
    })
    .await;
}

/// The daemon on an external simulator: killed (the adapter unplugged),
/// a subscribed value turns `BadNoCommunication` (clients with no filter:
/// the default trigger).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn good_turns_bad_no_communication_when_the_adapter_goes_away() {
    bounded(LIMIT, async {
        let links = tempfile::tempdir().unwrap();
        let link = links.path().join("adapter");
        let sim = ExternalSim::start(&link, "1,2", &[]).await;
        let ua = Ua::start(Some(&link)).await;
        ua.d.wait_all_online(Duration::from_secs(30)).await;
        let mut c = Client::asyncua(&ua.url, "quality", &["--seconds".into(), "60".into()]);
        c.until("subscribed").await;
        loop {
            let v = c.until("value").await;
            if v["status"] == "Good" {
                break;
            }
        }
        sim.kill().await;
        let t0 = Instant::now();
        loop {
            let v = c.until("value").await;
            if v["status"] == "BadNoCommunication" {
                break;
            }
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
        c.kill().await;
    })
    .await;
}

/// An alarm of the book (a drive gone silent: offline) reaches both
/// clients, at once, as an AlarmConditionType event with their default
/// filters; acknowledged over OPC UA, the API shows it acknowledged.
/// The lift, silent here, is polled once a second, so that its data is
/// stale for a while before it is offline: its Speed in asyncua's
/// subscription (no filter: the default trigger) turns from `Good` to
/// `UncertainLastUsableValue` (its last value, kept) and then to
/// `BadNoCommunication`. Then the bus's variables say what the API's bus
/// view says (see [`buses_as_the_api_says`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_is_an_event_acknowledged_as_through_the_api() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let section = section(dir.path());
        let plant = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.drive_keys("lift", "poll_interval_ms = 1000"));
        let ua = Ua::start_plant(plant, false, dir, section).await;
        let api = Api::new(ua.d.http, Some(OPERATOR));
        let pki = ua.pki.parent().unwrap().join("node-pki");
        let leg = |unit: u8, drive: &'static str, client: &'static str| {
            let (ua, api, pki) = (&ua, &api, &pki);
            async move {
                let mut args = operator();
                args.extend([
                    "--drive".into(),
                    drive.into(),
                    "--seconds".into(),
                    "40".into(),
                ]);
                let mut c = match client {
                    "asyncua" => Client::asyncua(&ua.url, "events", &args),
                    _ => Client::node(&ua.url, "events", pki, &args),
                };
                c.until("subscribed").await;
                ua.d.sim().set_silent(unit, true);
                // Until acknowledged, and asyncua's Speed is no value.
                let (mut statuses, mut acked) = (Vec::<String>::new(), None);
                while acked.is_none()
                    || (client == "asyncua"
                        && statuses.last().map(String::as_str) != Some("BadNoCommunication"))
                {
                    let v = c.next().await.unwrap_or_else(|| panic!("{client} ended"));
                    match v["step"].as_str() {
                        Some("value") => {
                            statuses.push(v["status"].as_str().unwrap_or_default().into())
                        }
                        Some("acknowledged") => acked = Some(v),
                        _ => {}
                    }
                }
                let acked = acked.unwrap_or_default();
                assert_eq!(acked["status"], "Good", "{client}: {acked}");
                let t0 = Instant::now();
                loop {
                    let list = api
                        .get(&format!("/api/v1/alarms?drive={drive}"))
                        .await
                        .expect(200);
                    let offline = list["alarms"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .find(|a| a["kind"] == "offline")
                        .cloned();
                    if offline.as_ref().is_some_and(|a| a["acknowledged"] == true) {
                        break;
                    }
                    assert!(t0.elapsed() < STEP, "{client}: not acknowledged: {list:#}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                c.kill().await;
                statuses
            }
        };
        let (mut statuses, _) =
            tokio::join!(leg(2, "lift", "asyncua"), leg(4, "feeder", "node-opcua"));
        statuses.dedup();
        assert_eq!(
            statuses,
            ["Good", "UncertainLastUsableValue", "BadNoCommunication"]
        );
        buses_as_the_api_says(&ua, &api).await;
    })
    .await;
}

/// `ua`'s bus variables (`Objects/Buses/sim`), read by asyncua, against
/// the API's view of the bus (`/api/v1/buses/sim`, read before and after)
/// with two of its four drives silent: its state, two drives online (once
/// the server's refresh, every second, has caught up), the silent drives'
/// timeouts and retries (counted, never ahead of the API), no CRC error,
/// bad reply or reopening, the utilisation as `/metrics` has it (in %);
/// and the silent lift's Speed read as `BadNoCommunication`.
async fn buses_as_the_api_says(ua: &Ua, api: &Api) {
    let t0 = Instant::now();
    let (before, read, after) = loop {
        let before = api.get("/api/v1/buses/sim").await.expect(200);
        let all = Client::asyncua(&ua.url, "read", &["--drive".into(), "lift".into()])
            .steps()
            .await;
        let read = step(&all, "read").clone();
        let after = api.get("/api/v1/buses/sim").await.expect(200);
        if read["buses"]["sim"]["DrivesOnline"]["value"] == after["drives_online"] {
            break (before, read, after);
        }
        assert!(t0.elapsed() < STEP, "{read}: {after:#}");
    };
    let bus = &read["buses"]["sim"];
    let value = |name: &str| -> &Value {
        assert_eq!(bus[name]["status"], "Good", "{name}: {bus}");
        &bus[name]["value"]
    };
    assert_eq!(value("State"), &after["state"], "{bus}: {after:#}");
    assert_eq!(
        (value("State"), value("Reason")),
        (&"up".into(), &"".into())
    );
    assert!(after["reason"].is_null(), "{after:#}");
    assert_eq!(value("DrivesOnline"), 2, "{bus}");
    assert_eq!(before["drives_online"], 2, "{before:#}");
    for (name, counter) in [
        ("Timeouts", "timeouts"),
        ("Retries", "retries"),
        ("CrcErrors", "crc_errors"),
        ("BadReplies", "bad_replies"),
        ("Reopens", "reopens"),
    ] {
        let opc = value(name)
            .as_u64()
            .unwrap_or_else(|| panic!("{name}: {bus}"));
        let api = after["counters"][counter].as_u64().unwrap_or_default();
        assert!(
            opc <= api,
            "{name} {opc} > {counter} {api}: {bus} {after:#}"
        );
        let counted = matches!(name, "Timeouts" | "Retries");
        assert_eq!(opc > 0, counted, "{name}: {bus}");
    }
    let ratio = metric(
        &ua.d.metrics.render(),
        "drivegate_bus_utilisation_ratio{bus=\"sim\"}",
    );
    let utilisation = value("Utilisation").as_f64().unwrap_or(-1.0);
    assert!(
        utilisation > 0.0 && (utilisation - ratio * 100.0).abs() < 15.0,
        "{utilisation} %, /metrics {ratio}: {bus}"
    );
    let speed = &read["values"]["Speed"];
    assert_eq!(speed["status"], "BadNoCommunication", "{speed}");
    assert_eq!(read["values"]["Online"]["value"], false, "{read}");
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
        let all = Client::asyncua(&url(addr), "brake", &[]).steps().await;
        assert_eq!(
            step(&all, "brake")["status"],
            "BadUserAccessDenied",
            "{all:?}"
        );

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
