//! OPC UA's connections and sessions under the budget every listener
//! shares: 20 anonymous sessions from one address leave one for an
//! operator from another (asyncua, from two loopback addresses); 1,200
//! secure channels (raw HEL and OPN, policy None, no credentials) from one
//! address against the real binary under a 1,024-file limit (`prlimit`),
//! while HTTP, Modbus TCP and OPC UA from another address keep answering
//! and the log grows by a few lines, not gigabytes.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde_json::Value;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

use crate::support::config::ConfigBuilder;
use crate::support::input::{OPERATOR, role_tokens};
use crate::support::modbus_tcp::{Raw, read, registers};
use crate::support::opcua::server_pki;
use crate::support::{TestDaemon, bounded};

/// `tests/python/opcua_sessions.py URL GROUPS`, holding its sessions
/// until dropped; what it said of each group.
async fn sessions(url: &str, groups: &[&str]) -> (tokio::process::Child, Vec<Value>) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_sessions.py");
    let mut child = tokio::process::Command::new("python3")
        .arg(script)
        .arg(url)
        .args(groups)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("python3 with asyncua (scripts/test installs it into target/pyenv)");
    let stdout = child.stdout.take().expect("its output");
    let mut lines = BufReader::new(stdout).lines();
    let mut said = Vec::new();
    for _ in groups {
        let line = tokio::time::timeout(Duration::from_secs(60), lines.next_line())
            .await
            .expect("the sessions opened in time")
            .expect("its output")
            .expect("a line: asyncua installed? (scripts/test installs it)");
        said.push(serde_json::from_str(&line).expect("JSON"));
    }
    (child, said)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_anonymous_sessions_from_one_address_leave_one_for_an_operator_from_another() {
    bounded(Duration::from_secs(120), async {
        let dir = tempfile::tempdir().unwrap();
        let pki = server_pki(dir.path());
        let toml = role_tokens(ConfigBuilder::four_drives())
            .section(
                "opcua",
                &format!(
                    "listen = \"127.0.0.1:0\"\npki_dir = \"{}\"\nsecurity = [\"none\", \"basic256sha256\"]",
                    pki.display()
                ),
            )
            .toml();
        let d = TestDaemon::start(&toml).await;
        let addr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        let url = format!("opc.tcp://{addr}/");
        // max_sessions as it comes (20): the flood from 127.0.0.2 takes
        // every free one short of the last eighth (2), then is refused; the
        // operator, from another address, gets a session.
        let operator = format!("127.0.0.3,1,scada,{OPERATOR}");
        let (clients, said) = sessions(&url, &["127.0.0.2,20", &operator]).await;
        let (flood, got) = (&said[0], &said[1]);
        assert_eq!(flood["opened"], 18, "{flood}");
        assert_eq!(
            flood["refused"],
            serde_json::json!(["BadTooManySessions", "BadTooManySessions"]),
            "{flood}"
        );
        assert_eq!(got["opened"], 1, "{got}");
        let series = |s: &str| crate::support::metrics::metric(&d.metrics.render(), s);
        assert_eq!(
            series("drivegate_connections_refused_total{face=\"opcua_sessions\",reason=\"heaviest\"}"),
            2.0
        );
        assert_eq!(
            series("drivegate_connections_turned_away_total{face=\"opcua_sessions\",address=\"127.0.0.2\"}"),
            2.0
        );
        crate::support::wait::eventually(Duration::from_secs(5), "19 sessions counted", || {
            (series("drivegate_connections{face=\"opcua_sessions\"}") == 19.0).then_some(())
        })
        .await;
        println!(
            "OPC UA, max_sessions 20: 20 anonymous sessions from 127.0.0.2: 18 opened, 2 refused (BadTooManySessions); \
             the operator from 127.0.0.3 got a session in {} ms",
            got["slowest_ms"],
        );
        drop(clients);
        d.stop().await;
    })
    .await;
}

/// The OPC UA TCP message of type `kind` ("HEL", "OPN") with `body`.
pub(super) fn message(kind: &[u8; 3], body: &[u8]) -> Vec<u8> {
    let mut m = kind.to_vec();
    m.push(b'F');
    m.extend_from_slice(&u32::try_from(8 + body.len()).unwrap().to_le_bytes());
    m.extend_from_slice(body);
    m
}

pub(super) fn string(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&i32::try_from(s.len()).unwrap().to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

/// Hello: protocol 0, 64 KiB buffers, no message or chunk limit.
pub(super) fn hello(url: &str) -> Vec<u8> {
    let mut b = Vec::new();
    for v in [0u32, 65_536, 65_536, 0, 0] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    string(&mut b, url);
    message(b"HEL", &b)
}

/// OpenSecureChannel, policy None, mode None, asking for an hour.
pub(super) fn open() -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&0u32.to_le_bytes()); // secure channel id
    string(&mut b, "http://opcfoundation.org/UA/SecurityPolicy#None");
    b.extend_from_slice(&(-1i32).to_le_bytes()); // sender certificate
    b.extend_from_slice(&(-1i32).to_le_bytes()); // receiver thumbprint
    b.extend_from_slice(&1u32.to_le_bytes()); // sequence number
    b.extend_from_slice(&1u32.to_le_bytes()); // request id
    b.extend_from_slice(&[0x01, 0x00, 0xBE, 0x01]); // OpenSecureChannelRequest (446)
    b.extend_from_slice(&[0x00, 0x00]); // authentication token: null
    b.extend_from_slice(&0i64.to_le_bytes()); // timestamp
    b.extend_from_slice(&1u32.to_le_bytes()); // request handle
    b.extend_from_slice(&0u32.to_le_bytes()); // return diagnostics
    b.extend_from_slice(&(-1i32).to_le_bytes()); // audit entry id
    b.extend_from_slice(&10_000u32.to_le_bytes()); // timeout hint
    b.extend_from_slice(&[0x00, 0x00, 0x00]); // additional header: none
    b.extend_from_slice(&0u32.to_le_bytes()); // client protocol version
    b.extend_from_slice(&0u32.to_le_bytes()); // Issue
    b.extend_from_slice(&1u32.to_le_bytes()); // MessageSecurityMode None
    b.extend_from_slice(&0i32.to_le_bytes()); // client nonce: empty
    b.extend_from_slice(&3_600_000u32.to_le_bytes()); // requested lifetime
    message(b"OPN", &b)
}

/// The type of the next message on `s` ("ACK", "ERR", "OPN"), or why none.
pub(super) async fn next_type(s: &mut TcpStream) -> Result<String, String> {
    let mut head = [0u8; 8];
    tokio::time::timeout(Duration::from_secs(20), s.read_exact(&mut head))
        .await
        .map_err(|_| "no answer within 20 s".to_string())?
        .map_err(|e| e.to_string())?;
    let size = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
    let mut rest = vec![0u8; size.saturating_sub(8)];
    tokio::time::timeout(Duration::from_secs(20), s.read_exact(&mut rest))
        .await
        .map_err(|_| "a message cut short".to_string())?
        .map_err(|e| e.to_string())?;
    Ok(String::from_utf8_lossy(&head[..3]).into_owned())
}

/// A connection to `addr` from `source`.
pub(super) async fn connect_from(source: &str, addr: SocketAddr) -> std::io::Result<TcpStream> {
    let socket = tokio::net::TcpSocket::new_v4()?;
    socket.bind(format!("{source}:0").parse().unwrap())?;
    socket.connect(addr).await
}

/// A secure channel from `source`: the open socket once its OPN was
/// answered, or how it was turned away.
pub(super) async fn channel(source: &str, addr: SocketAddr) -> Result<TcpStream, String> {
    let mut s = connect_from(source, addr)
        .await
        .map_err(|e| e.to_string())?;
    let url = format!("opc.tcp://{addr}/");
    s.write_all(&hello(&url)).await.map_err(|e| e.to_string())?;
    match next_type(&mut s).await? {
        t if t == "ACK" => {}
        other => return Err(other),
    }
    s.write_all(&open()).await.map_err(|e| e.to_string())?;
    match next_type(&mut s).await? {
        t if t == "OPN" => Ok(s),
        other => Err(other),
    }
}

/// The daemon as its own process under a file limit, its log counted.
struct Limited {
    child: tokio::process::Child,
    log_bytes: Arc<AtomicU64>,
    http: SocketAddr,
    modbus: SocketAddr,
    opcua: SocketAddr,
    _dir: tempfile::TempDir,
}

impl Limited {
    async fn start(files: u32) -> Limited {
        crate::support::tools::require("prlimit");
        let dir = tempfile::tempdir().unwrap();
        let pki: PathBuf = server_pki(dir.path());
        let port = crate::support::ports::free_port;
        let (http, modbus, opcua): (SocketAddr, SocketAddr, SocketAddr) = (
            format!("127.0.0.1:{}", port()).parse().unwrap(),
            format!("127.0.0.1:{}", port()).parse().unwrap(),
            format!("127.0.0.1:{}", port()).parse().unwrap(),
        );
        // The listener's own limit far above the files, so that it is the
        // file reserve that bounds the flood.
        let toml = ConfigBuilder::four_drives()
            .http_listen(&http.to_string())
            .modbus_tcp_listen(&modbus.to_string())
            .section(
                "opcua",
                &format!(
                    "listen = \"{opcua}\"\npki_dir = \"{}\"\nsecurity = [\"none\"]\nmax_connections = 4096",
                    pki.display()
                ),
            )
            .toml();
        let path = dir.path().join("drivegate.toml");
        std::fs::write(&path, toml).unwrap();
        let mut child = tokio::process::Command::new("prlimit")
            .arg(format!("--nofile={files}:{files}"))
            .arg(env!("CARGO_BIN_EXE_drivegate"))
            .arg("serve")
            .arg("--config")
            .arg(&path)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .expect("prlimit (util-linux) runs the daemon");
        let log_bytes = Arc::new(AtomicU64::new(0));
        let mut stderr = child.stderr.take().unwrap();
        let counted = log_bytes.clone();
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            while let Ok(n) = stderr.read(&mut buf).await {
                if n == 0 {
                    break;
                }
                counted.fetch_add(n as u64, Ordering::Relaxed);
            }
        });
        let d = Limited {
            child,
            log_bytes,
            http,
            modbus,
            opcua,
            _dir: dir,
        };
        let t0 = Instant::now();
        loop {
            let ready = d.get("/readyz").await;
            if ready.contains("\"serving\":true") {
                break;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "OPC UA not serving: {ready}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        d
    }

    /// `GET path`'s body ("" when there is no answer).
    async fn get(&self, path: &str) -> String {
        self.get_from("127.0.0.1", path).await.unwrap_or_default()
    }

    /// `GET path` from `source`: its body, or why none.
    async fn get_from(&self, source: &str, path: &str) -> Result<String, String> {
        let mut s = connect_from(source, self.http)
            .await
            .map_err(|e| e.to_string())?;
        s.write_all(
            format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
                .as_bytes(),
        )
        .await
        .map_err(|e| e.to_string())?;
        let mut bytes = Vec::new();
        tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut bytes))
            .await
            .map_err(|_| "no answer in 10 s".to_string())?
            .map_err(|e| e.to_string())?;
        let text = String::from_utf8_lossy(&bytes).into_owned();
        if !text.starts_with("HTTP/1.1 200") {
            return Err(text.lines().next().unwrap_or_default().to_string());
        }
        Ok(text
            .split_once("\r\n\r\n")
            .map(|(_, b)| b.to_string())
            .unwrap_or_default())
    }

    async fn metric(&self, series: &str) -> f64 {
        crate::support::metrics::metric(&self.get("/metrics").await, series)
    }
}

/// The test process's own file limit raised to its hard limit: it holds
/// the attacker's 1,200 sockets.
fn room_for_the_attacker() {
    use nix::sys::resource::{Resource, getrlimit, setrlimit};
    let (_, hard) = getrlimit(Resource::RLIMIT_NOFILE).unwrap();
    let _ = setrlimit(Resource::RLIMIT_NOFILE, hard, hard);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twelve_hundred_secure_channels_from_one_address_under_a_low_file_limit_leave_the_faces_answering()
 {
    bounded(Duration::from_secs(180), async {
        room_for_the_attacker();
        let d = Limited::start(1024).await;
        let before = d.log_bytes.load(Ordering::Relaxed);
        let flood_started = Instant::now();
        // 1,200 channels from 127.0.0.2, a hundred at a time, all kept.
        let mut held = Vec::new();
        let mut refused = std::collections::BTreeMap::<String, u32>::new();
        for _ in 0..12 {
            let batch: Vec<_> = (0..100)
                .map(|_| {
                    let addr = d.opcua;
                    tokio::spawn(async move { channel("127.0.0.2", addr).await })
                })
                .collect();
            for b in batch {
                match b.await.unwrap() {
                    Ok(s) => held.push(s),
                    Err(why) => *refused.entry(why).or_insert(0) += 1,
                }
            }
        }
        let flood_took = flood_started.elapsed();
        // From another address, every face answers.
        let asked = Instant::now();
        let health = d.get_from("127.0.0.3", "/healthz").await;
        let http_waited = asked.elapsed();
        assert!(health.is_ok(), "HTTP from 127.0.0.3: {health:?}");
        let asked = Instant::now();
        let mut plc = Raw::from_stream(connect_from("127.0.0.3", d.modbus).await.unwrap());
        assert_eq!(registers(&plc.ask(1, &read(0xC0, 7)).await).len(), 7);
        let modbus_waited = asked.elapsed();
        let asked = Instant::now();
        let other = channel("127.0.0.3", d.opcua).await;
        let opcua_waited = asked.elapsed();
        assert!(other.is_ok(), "OPC UA from 127.0.0.3: {other:?}");
        let log_growth = d.log_bytes.load(Ordering::Relaxed) - before;
        let files_open = d.metric("drivegate_connections_files_open").await;
        let by_flood = d
            .metric("drivegate_connections_by_address{face=\"opcua\",address=\"127.0.0.2\"}")
            .await;
        let refused_files = d
            .metric("drivegate_connections_refused_total{face=\"opcua\",reason=\"files\"}")
            .await;
        println!(
            "OPC UA, 1,200 channels from 127.0.0.2 under a 1,024-file limit (in {:.1} s): {} open ({by_flood} by /metrics), refused {refused:?} ({refused_files} counted, reason files); \
             {files_open} files open; from 127.0.0.3: HTTP answered in {} ms, Modbus TCP in {} ms, an OPC UA channel opened in {} ms; the log grew by {log_growth} bytes",
            flood_took.as_secs_f64(),
            held.len(),
            http_waited.as_millis(),
            modbus_waited.as_millis(),
            opcua_waited.as_millis(),
        );
        // The flood was held below the shared reserve (an eighth of the
        // limit) and refused beyond it; what it holds keeps its channels.
        assert!(held.len() > 600 && held.len() < 900, "{} held", held.len());
        assert_eq!(by_flood, held.len() as f64);
        assert!(refused_files >= 300.0, "{refused_files}");
        assert!(files_open < 1024.0 - 32.0, "{files_open}");
        assert!(http_waited < Duration::from_secs(5));
        assert!(modbus_waited < Duration::from_secs(5));
        assert!(opcua_waited < Duration::from_secs(5));
        assert!(log_growth < 64 * 1024, "{log_growth} bytes of log during the flood");
        drop(held);
        let mut child = d.child;
        let _ = child.kill().await;
    })
    .await;
}
