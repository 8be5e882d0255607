//! The OPC UA face against an attacker's tools (asyncua made to misbehave,
//! raw requests it would not send, certificates made by openssl):
//!
//! - a program trusted as an application, presenting its own certificate
//!   (self-signed, with the role extension `admin`) as the user identity,
//!   is refused: no certificate grants itself a role; user certificates
//!   come from their own trust (`users/trusted/certs`, `user_ca`) with the
//!   role the configuration gives them;
//! - a password sent in clear is refused (and audited) while the same one,
//!   encrypted as the user token policy says, signs in;
//! - wrong passwords for a name from one address lock that name out from
//!   that address only: the operator signs in from another (over HTTP too,
//!   where an address is paused, not a token);
//! - 2 sessions x 10 subscriptions x 1,000 monitored items with queues of
//!   1,000 and no Publish stay within the caps, and the daemon's memory
//!   with them (the real binary in a process of its own).

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use serde_json::Value;
use tokio::io::AsyncWriteExt;

use super::opcua::{Client, LIMIT, STEP, USER, Ua, operator, section_keys, step};
use crate::support::certs::openssl;
use crate::support::config::ConfigBuilder;
use crate::support::input::{OPERATOR, raw_http, role_tokens};
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::metric;
use crate::support::opcua::{Held, server_pki};
use crate::support::wait::bounded;

/// The role extension's openssl line, for `role`.
fn role_line(role: &str) -> String {
    format!(
        "{}=ASN1:UTF8String:{role}",
        drivegate::config::ROLE_EXTENSION
    )
}

/// `name.der`/`name-key.pem` in `dir`: a self-signed certificate usable as
/// an application's (its URI in the SANs) carrying `extra` extensions.
fn self_signed(dir: &Path, name: &str, extra: &[String]) {
    let mut args: Vec<String> = [
        "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "30", "-subj",
    ]
    .map(String::from)
    .to_vec();
    args.push(format!("/CN={name}"));
    for (flag, value) in [
        ("-keyout", format!("{name}-key.pem")),
        ("-out", format!("{name}.pem")),
        (
            "-addext",
            format!("subjectAltName=URI:urn:{name}:client,DNS:localhost,IP:127.0.0.1"),
        ),
        (
            "-addext",
            "keyUsage=critical,digitalSignature,nonRepudiation,keyEncipherment,dataEncipherment"
                .to_string(),
        ),
        (
            "-addext",
            "extendedKeyUsage=clientAuth,serverAuth".to_string(),
        ),
    ] {
        args.extend([flag.to_string(), value]);
    }
    for e in extra {
        args.extend(["-addext".to_string(), e.clone()]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    openssl(dir, &args);
    to_der(dir, name);
}

/// `name.der` from `name.pem`.
fn to_der(dir: &Path, name: &str) {
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

/// `name.der`/`name-key.pem`: a user certificate signed by `ca`, with the
/// role extension `role`.
fn signed_user(dir: &Path, name: &str, role: &str) {
    openssl(
        dir,
        &[
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            &format!("{name}-key.pem"),
            "-out",
            &format!("{name}.csr"),
            "-subj",
            &format!("/CN={name}/O=plant"),
        ],
    );
    std::fs::write(
        dir.join(format!("{name}.ext")),
        format!("basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature,nonRepudiation\nextendedKeyUsage=clientAuth\n{}\n", role_line(role)),
    )
    .unwrap();
    openssl(
        dir,
        &[
            "x509",
            "-req",
            "-in",
            &format!("{name}.csr"),
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "30",
            "-out",
            &format!("{name}.pem"),
            "-extfile",
            &format!("{name}.ext"),
        ],
    );
    to_der(dir, name);
}

/// The SHA-1 fingerprint of `dir/name.der`, as openssl prints it.
fn fingerprint(dir: &Path, name: &str) -> String {
    let der = std::fs::read(dir.join(format!("{name}.der"))).unwrap();
    drivegate::control::identity::hex(&drivegate::tls::sha1_fingerprint(&der))
}

/// Client arguments presenting `dir/name` as the user certificate.
fn user_cert(dir: &Path, name: &str) -> Vec<String> {
    vec![
        "--drive".into(),
        "lift".into(),
        "--user-cert".into(),
        dir.join(format!("{name}.der")).display().to_string(),
        "--user-key".into(),
        dir.join(format!("{name}-key.pem")).display().to_string(),
    ]
}

/// Roles come only from the configuration. The finding first: a
/// self-signed certificate with the role extension `admin`, trusted as an
/// application (in `trusted/certs`, as an admin trusts a program) and
/// presented both as the application's and as the user's on a signed and
/// encrypted channel, is refused at sign-in: nothing written. Then:
/// certificates signed by `user_ca` sign in with their role extension
/// (operator: Brake() done) unless `[[opcua.user_certificate]]` names
/// them (by subject: the viewer's certificate made operator); one in
/// `users/trusted/certs` claiming admin has the role its thumbprint is
/// given (viewer: Brake() refused), and without one it is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_certificate_grants_itself_a_role() {
    bounded(LIMIT, async {
        capture_logs();
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let pki = server_pki(d);
        openssl(d, &["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
            "-days", "30", "-subj", "/CN=plant users", "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign"]);
        signed_user(d, "olivia", "operator");
        signed_user(d, "vera", "viewer");
        let admin = [role_line("admin")];
        self_signed(d, "rogue", &admin);
        self_signed(d, "dana", &admin);
        self_signed(d, "ivan", &admin);
        for (name, list) in [("rogue", "trusted/certs"), ("dana", "users/trusted/certs"), ("ivan", "users/trusted/certs")] {
            std::fs::create_dir_all(pki.join(list)).unwrap();
            std::fs::copy(d.join(format!("{name}.der")), pki.join(list).join(format!("{name}.der"))).unwrap();
        }
        let section = format!(
            "{}\nuser_ca = \"{}\"",
            section_keys(&pki),
            d.join("ca.pem").display()
        );
        let tables = format!(
            "[[opcua.user_certificate]]\nthumbprint = \"{}\"\nrole = \"viewer\"\n\n[[opcua.user_certificate]]\nsubject = \"O=plant, CN=vera\"\nrole = \"operator\"\n",
            fingerprint(d, "dana")
        );
        let builder = ConfigBuilder::four_drives().tables(&tables);
        let dir_path = d.to_path_buf();
        let ua = Ua::start_plant(builder, false, dir, section).await;
        let d = dir_path.as_path();

        let mut rogue = user_cert(d, "rogue");
        rogue.extend(
            [
                "--policy".into(),
                "basic256sha256".into(),
                "--cert".into(),
                d.join("rogue.der").display().to_string(),
                "--key".into(),
                d.join("rogue-key.pem").display().to_string(),
            ],
        );
        let brake = |name: &'static str| Client::asyncua(&ua.url, "brake", &user_cert(d, name)).steps();
        let (rogue, olivia, vera, dana, ivan) = tokio::join!(
            Client::asyncua(&ua.url, "claim", &rogue).steps(),
            brake("olivia"),
            brake("vera"),
            brake("dana"),
            brake("ivan"),
        );
        let claim = step(&rogue, "claim");
        assert!(
            claim["session"].as_str().is_some_and(|s| s.contains("BadIdentityTokenRejected")),
            "the self-granted admin: {claim}"
        );
        assert_eq!(step(&olivia, "brake")["status"], "Good", "{olivia:?}");
        assert_eq!(step(&vera, "brake")["status"], "Good", "{vera:?}");
        assert_eq!(step(&dana, "brake")["status"], "BadUserAccessDenied", "{dana:?}");
        assert_eq!(step(&ivan, "session")["status"], "BadIdentityTokenRejected", "{ivan:?}");
        // The drive kept its settings: nothing was written.
        let text = ua.d.metrics.render();
        let signed = |result: &str| {
            metric(&text, &format!("drivegate_opcua_sign_ins_total{{kind=\"certificate\",result=\"{result}\"}}"))
        };
        assert_eq!((signed("accepted"), signed("refused")), (3.0, 2.0));
        let log = log_text();
        let rogue = fingerprint(d, "rogue");
        assert!(
            log.lines().any(|l| l.contains("sign-in refused") && l.contains(&rogue) && l.contains("nor signed by user_ca")),
            "the rogue's refusal audited (SHA-1 {rogue})"
        );
        assert!(
            log.lines().any(|l| l.contains("sign-in refused") && l.contains("ivan") && l.contains("no [[opcua.user_certificate]]")),
            "ivan's refusal audited"
        );
    })
    .await;
}

/// Secrets never in clear, and lockouts a stranger cannot cause. The
/// operator's password sent in clear on the endpoint without security
/// (asyncua made to ignore the user token policy) is refused and audited;
/// the same password encrypted with the server's key signs in. Ten wrong
/// passwords for the operator's name from 127.0.0.2 lock that name out
/// from 127.0.0.2 (the right password refused there), while the operator
/// signs in from 127.0.0.1 at once. The API pauses an address, not a
/// token: ten unknown tokens from 127.0.0.2 and the operator's token still
/// works from 127.0.0.1.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn passwords_are_never_in_clear_and_a_stranger_locks_no_one_out() {
    bounded(LIMIT, async {
        capture_logs();
        let ua = Ua::start(None).await;
        let mut args = operator();
        args.extend(["--drive".into(), "lift".into(), "--source".into(), "127.0.0.2".into()]);
        let all = Client::asyncua(&ua.url, "clear-password,guess", &args).steps().await;
        let clear = step(&all, "clear-password");
        assert_ne!(clear["status"], "Good", "{clear}");
        assert_eq!(step(&all, "encrypted-password")["status"], "Good", "{all:?}");
        let guessed = step(&all, "guessed")["statuses"].as_array().unwrap().clone();
        assert_eq!(guessed.len(), 10);
        assert!(guessed.iter().all(|s| s != "Good"), "{guessed:?}");
        let paused = step(&all, "paused");
        assert_ne!(paused["status"], "Good", "the name from the guessing address: {paused}");
        let elsewhere = step(&all, "elsewhere");
        assert_eq!(elsewhere["status"], "Good", "the operator from another address: {elsewhere}");
        let waited = elsewhere["seconds"].as_f64().unwrap_or(f64::MAX);
        println!("the operator signed in from 127.0.0.1 and braked in {waited:.3} s, its name locked from 127.0.0.2");
        assert!(waited < 10.0, "{elsewhere}");
        // Audited, with the client's address; the secret never.
        let log = log_text();
        assert!(
            log.lines().any(|l| l.contains("sign-in refused") && l.contains("in clear") && l.contains("127.0.0.2")),
            "the clear password's refusal audited"
        );
        assert!(
            log.lines().any(|l| l.contains("sign-in refused") && l.contains("too many failed sign-ins") && l.contains("127.0.0.2")),
            "the paused name's refusal audited"
        );
        assert!(!log.contains(OPERATOR), "a password reached the log");
        let text = ua.d.metrics.render();
        assert!(metric(&text, "drivegate_opcua_sign_ins_total{kind=\"user\",result=\"refused\"}") >= 12.0);

        // HTTP: ten unknown tokens from 127.0.0.2 pause that address only.
        let request = |token: &str| {
            format!("GET /api/v1/drives HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {token}\r\nConnection: close\r\n\r\n")
        };
        for i in 0..10 {
            let status = http_from("127.0.0.2", ua.d.http, &request(&format!("guess-{i}"))).await;
            assert_eq!(status, 401);
        }
        assert_eq!(http_from("127.0.0.2", ua.d.http, &request(OPERATOR)).await, 429);
        let t0 = Instant::now();
        let answer = raw_http(ua.d.http, request(OPERATOR).as_bytes()).await.unwrap();
        assert_eq!(answer.status, 200, "{}", answer.text());
        println!("the operator's API token answered from 127.0.0.1 in {:?}, 127.0.0.2 paused", t0.elapsed());
    })
    .await;
}

/// The status of one HTTP request sent from `source` to `to`.
async fn http_from(source: &str, to: std::net::SocketAddr, request: &str) -> u16 {
    use tokio::io::AsyncReadExt;
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    let mut stream = socket.connect(to).await.unwrap();
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).await.unwrap();
    let text = String::from_utf8_lossy(&answer);
    text.split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0)
}

/// The CPU time process `pid` used so far (user and system), s.
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // The fields after the command's closing parenthesis: utime and stime
    // are the 12th and 13th, in clock ticks (100 a second on Linux).
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .unwrap()
        .1
        .split_whitespace()
        .collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    ticks / 100.0
}

/// `(VmRSS, VmHWM)` of process `pid`, MB.
fn memory(pid: u32) -> (f64, f64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb = |key: &str| -> f64 {
        status
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
            .unwrap()
    };
    (kb("VmRSS:") / 1000.0, kb("VmHWM:") / 1000.0)
}

/// The monitored-item flood, bounded. The real binary in a process of its
/// own (its memory is its own), `[opcua] max_monitored_items = 1500`, the
/// other caps at their defaults; the conveyor turning (its angle changes at
/// every poll). From 127.0.0.2, 2 anonymous sessions x 10 subscriptions x
/// 1,000 monitored items on the angle, queues of 1,000 asked, and never a
/// Publish request: the first session gets its 1,000 items (the cap per
/// session) and the second 500 (the cap in all), each with a queue of 10
/// (the stack's default), the rest `BadTooManyMonitoredItems`. The
/// daemon's resident memory, sampled for 5 s of the flood, grows by less
/// than 40 MB, and an operator from 127.0.0.1 signs in and brakes
/// meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_monitored_item_flood_stays_within_its_caps() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let pki = server_pki(dir.path());
        let (http, opc) = (crate::support::ports::free_port(), crate::support::ports::free_port());
        let toml = role_tokens(ConfigBuilder::four_drives())
            .http_listen(&format!("127.0.0.1:{http}"))
            .modbus_tcp_listen("127.0.0.1:0")
            .section(
                "opcua",
                &format!(
                    "listen = \"127.0.0.1:{opc}\"\npki_dir = \"{}\"\nsecurity = [\"none\"]\nmax_monitored_items = 1500",
                    pki.display()
                ),
            )
            .toml();
        let config = dir.path().join("drivegate.toml");
        std::fs::write(&config, toml).unwrap();
        let mut daemon = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .arg("serve")
            .arg("--config")
            .arg(&config)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let pid = daemon.id().unwrap();
        let api: std::net::SocketAddr = format!("127.0.0.1:{http}").parse().unwrap();
        let get = |path: &'static str| async move {
            raw_http(api, format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").as_bytes())
                .await
                .ok()
                .map(|a| a.text())
                .unwrap_or_default()
        };
        let t0 = Instant::now();
        while !get("/readyz").await.contains("\"serving\":true") {
            assert!(t0.elapsed() < STEP, "OPC UA not serving");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let url = format!("opc.tcp://127.0.0.1:{opc}/");
        let _turning = Held::lease(&url, (USER, OPERATOR), ("conveyor", 600.0), STEP).await;
        let mut args = operator();
        args.extend(["--drive".into(), "lift".into()]);
        let quiet = Client::asyncua(&url, "sign-in", &args).steps().await;
        let quiet = step(&quiet, "sign-in")["seconds"].as_f64().unwrap_or(f64::MAX);
        let before = memory(pid);
        let cpu_before = cpu_seconds(pid);

        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_client.py");
        let mut flood = tokio::process::Command::new("python3")
            .arg(script)
            .arg(&url)
            .arg("flood")
            .args(["--source", "127.0.0.2", "--sessions", "2", "--subscriptions", "10", "--items", "1000", "--queue", "1000"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let mut lines = tokio::io::AsyncBufReadExt::lines(tokio::io::BufReader::new(flood.stdout.take().unwrap()));
        let flooded: Value = loop {
            let line = tokio::time::timeout(STEP, lines.next_line()).await.expect("the flood in time").unwrap().expect("the flood's steps");
            if let Ok(v) = serde_json::from_str::<Value>(&line) {
                assert_ne!(v["step"], "error", "{v}");
                if v["step"] == "flooded" {
                    break v;
                }
            }
        };
        let results = &flooded["results"];
        assert_eq!(results["session0 Good queue 10"], 1000, "{flooded}");
        assert_eq!(results["session1 Good queue 10"], 500, "{flooded}");
        let refused: u64 = results
            .as_object()
            .unwrap()
            .iter()
            .filter(|(k, _)| k.contains("BadTooManyMonitoredItems"))
            .map(|(_, v)| v.as_u64().unwrap_or(0))
            .sum();
        assert_eq!(refused, 18_500, "{flooded}");

        // The flood held, no Publish: the queues fill within a second at the
        // poll rate; sampled for 5 s, an operator braking meanwhile.
        let t0 = Instant::now();
        let cpu_flood = cpu_seconds(pid);
        let operator_run = Client::asyncua(&url, "sign-in", &args).steps();
        let sampling = async {
            let mut peak = before.0;
            while t0.elapsed() < Duration::from_secs(5) {
                peak = peak.max(memory(pid).0);
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            peak
        };
        let (steps, peak) = tokio::join!(operator_run, sampling);
        let signed_in = step(&steps, "sign-in");
        assert_eq!(signed_in["status"], "Good", "{steps:?}");
        let waited = signed_in["seconds"].as_f64().unwrap_or(f64::MAX);
        let after = memory(pid);
        let cpu = (cpu_seconds(pid) - cpu_flood) / t0.elapsed().as_secs_f64();
        let metrics = get("/metrics").await;
        let items = metric(&metrics, "drivegate_opcua_monitored_items");
        assert_eq!(metric(&metrics, "drivegate_opcua_limit{limit=\"monitored_items\"}"), 1500.0);
        assert_eq!(metric(&metrics, "drivegate_opcua_limit{limit=\"queue_size\"}"), 10.0);
        println!(
            "monitored-item flood (2 x 10 x 1,000 asked, queue 1,000, no Publish): {items} items; \
             VmRSS {:.1} MB before, {peak:.1} MB at most during 5 s, {:.1} MB after (VmHWM {:.1} MB); \
             the daemon's CPU {:.0} % of a core (creating the items: {:.1} s of CPU); an operator \
             from 127.0.0.1 signed in and braked in {waited:.2} s ({quiet:.2} s before the flood)",
            before.0, after.0, after.1, cpu * 100.0, cpu_flood - cpu_before
        );
        assert!(items <= 1500.0 + 10.0, "{items}");
        // Served, not starved: a starved client waits out its request's
        // timeout or is refused. The bound follows what the same client
        // took before the flood on this machine (0.26 s quiet, 0.7 s beside
        // a CPU hog and seven other tests, where 11 s was seen once).
        let bound = 10.0 + 20.0 * quiet;
        assert!(waited < bound, "the operator waited {waited} s (at most {bound:.1} s)");
        assert!(peak - before.0 < 40.0, "{before:?} -> {peak} MB");
        drop(flood.stdin.take());
        let _ = flood.wait().await;
        let _ = daemon.start_kill();
        let _ = daemon.wait().await;
    })
    .await;
}
