//! What security costs (`cargo bench --bench tls`), not a test: the daemon
//! in-process on the built-in simulator (4 drives, 115200 baud), with
//! certificates made by `openssl` (P-256) and a Rust load client on
//! loopback, each figure measured plain and over TLS on the same daemon:
//!
//! 1. Cached status reads over HTTP and HTTPS: `CLIENTS` keep-alive clients
//!    read `GET /api/v1/drives/conveyor/status` for `SECONDS`: reads/s, p99.
//! 2. Modbus TCP and Modbus/TCP Security: `CLIENTS` connections read the
//!    status block (answered from the polled copy, so the wire is not the
//!    limit) for `SECONDS`: reads/s, p99.
//! 3. Modbus/TCP Security handshakes: one client opening connections (with
//!    its client certificate) and reading once, for `SECONDS`: handshakes/s.
//!
//! Environment: `BENCH_SECONDS` (default 5), `BENCH_CLIENTS` (16).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use drivegate::config::Config;
use drivegate::metrics::Metrics;
use drivegate::plant::Plant;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_util::sync::CancellationToken;

// The tests' certificate maker, and the tool lookup it reports through
// (its `super::tools`).
#[allow(dead_code, unreachable_pub)]
#[path = "../tests/support/certs.rs"]
mod certs;
#[allow(dead_code, unreachable_pub)]
#[path = "../tests/support/tools.rs"]
mod tools;

const DRIVES: &str = r#"
[[modbus_tcp.polled_copy]]
bus = "sim"
max_age_ms = 1000
[[bus]]
name = "sim"
port = "sim"
baud = 115200
response_timeout_ms = 50
retries = 1
poll_interval_ms = 0
[bus.sim]
turnaround_ms = 0.5
seed = 1
[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
[[bus.drive]]
unit = 2
name = "lift"
gear_ratio = 10.0
[[bus.drive]]
unit = 3
name = "turntable"
gear_ratio = 3.75
[[bus.drive]]
unit = 4
name = "feeder"
gear_ratio = 1.0
"#;

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn client_config(dir: &Path, with_cert: bool) -> Arc<rustls::ClientConfig> {
    let mut roots = rustls::RootCertStore::empty();
    for c in drivegate::tls::load_certificates(&dir.join("ca.pem"), "CA").unwrap() {
        roots.add(c).unwrap();
    }
    let builder = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots);
    Arc::new(if with_cert {
        let chain = drivegate::tls::load_certificates(&dir.join("plc.pem"), "cert").unwrap();
        let key = drivegate::tls::load_key(&dir.join("plc.key")).unwrap();
        builder.with_client_auth_cert(chain, key).unwrap()
    } else {
        builder.with_no_client_auth()
    })
}

trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

async fn open(addr: SocketAddr, tls: Option<&Arc<rustls::ClientConfig>>) -> Box<dyn Io> {
    let tcp = TcpStream::connect(addr).await.unwrap();
    tcp.set_nodelay(true).unwrap();
    match tls {
        None => Box::new(tcp),
        Some(config) => {
            let name = rustls::pki_types::ServerName::IpAddress(addr.ip().into());
            Box::new(
                tokio_rustls::TlsConnector::from(config.clone())
                    .connect(name, tcp)
                    .await
                    .unwrap(),
            )
        }
    }
}

/// One keep-alive status read: request, then the head and the body by its length.
async fn http_read(io: &mut Box<dyn Io>, buf: &mut Vec<u8>) {
    io.write_all(b"GET /api/v1/drives/conveyor/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        .await
        .unwrap();
    buf.clear();
    loop {
        let mut chunk = [0u8; 4096];
        let n = io.read(&mut chunk).await.unwrap();
        assert!(n > 0, "closed");
        buf.extend_from_slice(&chunk[..n]);
        if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&buf[..end]).to_ascii_lowercase();
            assert!(head.starts_with("http/1.1 200"), "{head}");
            let len: usize = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .unwrap()
                .trim()
                .parse()
                .unwrap();
            if buf.len() >= end + 4 + len {
                return;
            }
        }
    }
}

/// One Modbus read of the status block of unit 1.
async fn modbus_read(io: &mut Box<dyn Io>, transaction: u16) {
    let t = transaction.to_be_bytes();
    io.write_all(&[t[0], t[1], 0, 0, 0, 6, 1, 0x03, 0x00, 0xC0, 0x00, 0x07])
        .await
        .unwrap();
    let mut reply = [0u8; 9 + 14];
    io.read_exact(&mut reply).await.unwrap();
    assert_eq!(&reply[..2], &t, "transaction");
    assert_eq!(reply[7], 0x03, "exception {:02x}", reply[8]);
}

async fn load(
    what: &str,
    addr: SocketAddr,
    tls: Option<Arc<rustls::ClientConfig>>,
    modbus: bool,
    clients: u64,
    seconds: u64,
) -> (f64, Duration) {
    let stop = Arc::new(AtomicBool::new(false));
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let (stop, tls) = (stop.clone(), tls.clone());
            tokio::spawn(async move {
                let mut io = open(addr, tls.as_ref()).await;
                let mut buf = Vec::new();
                let mut latencies = Vec::new();
                let mut transaction = 0u16;
                while !stop.load(Ordering::Relaxed) {
                    let t = Instant::now();
                    if modbus {
                        transaction = transaction.wrapping_add(1);
                        modbus_read(&mut io, transaction).await;
                    } else {
                        http_read(&mut io, &mut buf).await;
                    }
                    latencies.push(t.elapsed());
                }
                latencies
            })
        })
        .collect();
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    stop.store(true, Ordering::Relaxed);
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    all.sort();
    let rate = all.len() as f64 / seconds as f64;
    let p99 = all[((all.len() as f64 * 0.99) as usize).min(all.len() - 1)];
    println!(
        "{what:<34} {rate:>9.0} reads/s   p99 {:>7.2} ms",
        p99.as_secs_f64() * 1e3
    );
    (rate, p99)
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let seconds = env("BENCH_SECONDS", 5);
    let clients = env("BENCH_CLIENTS", 16);
    // The tests' certificates: a CA, a server certificate for 127.0.0.1,
    // and a PLC's client certificate with the viewer role.
    let pki = certs::Pki::new();
    pki.client("plc", "ca", Some("ASN1:UTF8String:viewer"));
    let dir = &pki.dir;
    let p = |n: &str| dir.path().join(n).display().to_string();
    let faces = |tls: bool| {
        let http_tls = if tls {
            format!(
                "[http.tls]\ncert = \"{}\"\nkey = \"{}\"\n",
                p("server.pem"),
                p("server.key")
            )
        } else {
            String::new()
        };
        format!(
            "[http]\nlisten = \"127.0.0.1:0\"\nmax_connections = 1024\n{http_tls}[modbus_tcp]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp.tls]\nlisten = \"127.0.0.1:0\"\ncert = \"{}\"\nkey = \"{}\"\nclient_ca = \"{}\"\n{DRIVES}",
            p("server.pem"),
            p("server.key"),
            p("ca.pem")
        )
    };
    println!(
        "security's cost: {clients} clients, {seconds} s each, loopback, {} CPUs",
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let mut results = Vec::new();
    for tls in [false, true] {
        let config = Config::parse(&faces(tls), "bench").unwrap();
        let plant = Arc::new(Plant::start(&config).unwrap());
        let metrics = Metrics::new(plant.clone());
        let shutdown = CancellationToken::new();
        let f =
            drivegate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
                .await
                .unwrap();
        // Let every drive answer a poll first (the polled copy).
        tokio::time::sleep(Duration::from_secs(2)).await;
        let server_only = client_config(dir.path(), false);
        let http = load(
            if tls {
                "HTTPS cached status reads"
            } else {
                "HTTP cached status reads"
            },
            f.http,
            tls.then(|| server_only.clone()),
            false,
            clients,
            seconds,
        )
        .await;
        results.push(http);
        if !tls {
            load(
                "Modbus TCP status reads",
                f.modbus_tcp.unwrap(),
                None,
                true,
                clients,
                seconds,
            )
            .await;
        } else {
            let with_cert = client_config(dir.path(), true);
            load(
                "Modbus/TCP Security status reads",
                f.modbus_tls.unwrap(),
                Some(with_cert.clone()),
                true,
                clients,
                seconds,
            )
            .await;
            // Handshakes: new connections, one read each, from one client.
            let start = Instant::now();
            let mut n = 0u64;
            while start.elapsed() < Duration::from_secs(seconds) {
                let mut io = open(f.modbus_tls.unwrap(), Some(&with_cert)).await;
                modbus_read(&mut io, 1).await;
                n += 1;
            }
            println!(
                "{:<34} {:>9.0} handshakes/s (with one read each, one client)",
                "Modbus/TCP Security connections",
                n as f64 / start.elapsed().as_secs_f64()
            );
        }
        shutdown.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), f.wait()).await;
        drivegate::control::shutdown(&plant, config.safety.on_shutdown).await;
    }
}
