//! The OPC UA benchmark: one drivegate daemon (a process of the built
//! binary) with 32 simulated drives on 4 buses at 115200 baud, polled as
//! fast as the wire allows, every motor turning (so the angle changes at
//! every poll); then
//! - **OPC UA**: 4 sessions (asyncua, `benches/opcua_subscriber.py`, one
//!   process each), each monitoring every variable of every drive
//!   (sampling interval 0: the poll period): notifications per second, and
//!   the latency from the poll (the value's source timestamp) to the
//!   client handling it, p50 / p99 / max;
//! - **WebSocket**: the same load on the stream: 4 clients subscribed to
//!   every drive (`?drives=all`): status messages per second (each holds
//!   every variable of a drive) and the latency from the poll (`seen_at`)
//!   to the client;
//! - for each, the daemon's CPU (share of one core, `/proc/<pid>/stat`)
//!   over the window and its resident memory at the end.
//!
//! The clients run on the same machine: their CPU is not the daemon's, but
//! they share its two cores (asyncua decodes in Python: its own share of
//! the latency is in the OPC UA figures).
//!
//! `cargo bench --bench opcua`; environment: `DRIVEGATE_BENCH_SECS` (the
//! measured window, default 10). Needs python3 with asyncua (scripts/test
//! puts it in target/pyenv).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::fmt::Write as _;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use futures_util::StreamExt;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

const BUSES: usize = 4;
const DRIVES: u8 = 8;
const SESSIONS: usize = 4;
const TOKEN: &str = "bench-admin-0f3a9c1d7e5b2468";

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn now_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1000.0)
}

/// `YYYY-MM-DDTHH:MM:SS[.fff]Z` as Unix milliseconds.
fn parse_ms(text: &str) -> Option<f64> {
    let num = |r: std::ops::Range<usize>| text.get(r)?.parse::<i64>().ok();
    let (y, m, d) = (num(0..4)?, num(5..7)?, num(8..10)?);
    let (hh, mm, ss) = (num(11..13)?, num(14..16)?, num(17..19)?);
    let frac: f64 = text
        .get(19..)
        .and_then(|t| t.strip_suffix('Z'))
        .filter(|t| t.starts_with('.'))
        .and_then(|t| format!("0{t}").parse().ok())
        .unwrap_or(0.0);
    // Days from the civil date (Howard Hinnant's algorithm).
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some(((days * 86_400 + hh * 3600 + mm * 60 + ss) as f64 + frac) * 1000.0)
}

struct Daemon {
    child: Child,
    http: u16,
    opcua: u16,
}

impl Daemon {
    fn spawn(dir: &Path) -> Daemon {
        let (http, opcua) = (free_port(), free_port());
        let mut toml = format!(
            "[http]\nlisten = \"127.0.0.1:{http}\"\n\
             [[http.token]]\nname = \"bench\"\nrole = \"admin\"\nenv = \"DRIVEGATE_BENCH_TOKEN\"\n\
             [modbus_tcp]\nenabled = false\n[log]\nlevel = \"warn\"\n\
             [safety]\nstate_dir = \"{}\"\non_shutdown = \"none\"\n\
             [opcua]\nlisten = \"127.0.0.1:{opcua}\"\nsecurity = [\"none\"]\nmax_sessions = 20\n",
            dir.join("state").display()
        );
        for bus in 1..=BUSES {
            let _ = write!(
                toml,
                "[[bus]]\nname = \"line{bus}\"\nport = \"sim\"\nbaud = 115200\npoll_interval_ms = 0\n[bus.sim]\nseed = {bus}\n"
            );
            for unit in 1..=DRIVES {
                let _ = write!(
                    toml,
                    "[[bus.drive]]\nunit = {unit}\nname = \"l{bus}d{unit}\"\n"
                );
            }
        }
        let file = dir.join("drivegate.toml");
        std::fs::write(&file, toml).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["serve", "--config"])
            .arg(&file)
            .env("DRIVEGATE_BENCH_TOKEN", TOKEN)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("daemon.log")).unwrap())
            .spawn()
            .unwrap();
        Daemon { child, http, opcua }
    }

    /// CPU seconds (user + system) so far.
    fn cpu_s(&self) -> f64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap_or_default();
        let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
        let f: Vec<&str> = rest.split_whitespace().collect();
        let ticks: f64 = f.get(11).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0)
            + f.get(12).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        ticks / 100.0
    }

    /// Resident memory, MiB.
    fn rss_mib(&self) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .unwrap_or_default();
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|kb| kb.parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    }

    fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}{path}", self.http)
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Until the OPC UA server serves and every drive answers; then every
/// motor turns (speed mode, a setpoint each).
async fn prepare(d: &Daemon, http: &reqwest::Client) {
    let t0 = Instant::now();
    loop {
        let ready: Value = match http.get(d.url("/readyz")).send().await {
            Ok(r) => r.json().await.unwrap_or(Value::Null),
            Err(_) => Value::Null,
        };
        if ready["opcua"]["serving"] == true && ready["ready"] == true {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "not ready: {ready}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    for bus in 1..=BUSES {
        for unit in 1..=DRIVES {
            let drive = format!("l{bus}d{unit}");
            let send = |r: reqwest::RequestBuilder| r.bearer_auth(TOKEN).send();
            send(http.post(d.url(&format!("/api/v1/drives/{drive}/commands/activate"))))
                .await
                .unwrap();
            send(
                http.put(d.url(&format!("/api/v1/drives/{drive}/mode")))
                    .json(&json!({"mode": "speed"})),
            )
            .await
            .unwrap();
            let speed = 100 + 20 * i64::from(unit);
            send(
                http.put(d.url(&format!("/api/v1/drives/{drive}/setpoint")))
                    .json(&json!({"speed_rpm": speed})),
            )
            .await
            .unwrap();
        }
    }
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((q * sorted.len() as f64) as usize).min(sorted.len() - 1)]
}

struct Figures {
    per_second: f64,
    p50: f64,
    p99: f64,
    max: f64,
    cpu: f64,
    rss: f64,
}

fn python() -> PathBuf {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/pyenv/bin/python3");
    if venv.is_file() {
        venv
    } else {
        PathBuf::from("python3")
    }
}

/// 4 asyncua sessions monitoring every variable.
async fn over_opcua(d: &Daemon, secs: f64) -> (Figures, u64) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/opcua_subscriber.py");
    let warmup = 8.0;
    let clients: Vec<Child> = (0..SESSIONS)
        .map(|_| {
            Command::new(python())
                .arg(&script)
                .arg(format!("opc.tcp://127.0.0.1:{}/", d.opcua))
                .args([
                    "--seconds",
                    &secs.to_string(),
                    "--warmup",
                    &warmup.to_string(),
                ])
                .stdout(Stdio::piped())
                .spawn()
                .expect("python3 with asyncua")
        })
        .collect();
    tokio::time::sleep(Duration::from_secs_f64(warmup)).await;
    let cpu0 = d.cpu_s();
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    let cpu = (d.cpu_s() - cpu0) / t0.elapsed().as_secs_f64();
    let rss = d.rss_mib();
    let (mut rate, mut p50, mut p99, mut max, mut items) = (0.0, 0.0f64, 0.0f64, 0.0f64, 0);
    for c in clients {
        let out = c.wait_with_output().unwrap();
        let v: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|_| panic!("subscriber: {}", String::from_utf8_lossy(&out.stdout)));
        rate += v["per_second"].as_f64().unwrap_or(0.0);
        p50 = p50.max(v["p50_ms"].as_f64().unwrap_or(f64::NAN));
        p99 = p99.max(v["p99_ms"].as_f64().unwrap_or(f64::NAN));
        max = max.max(v["max_ms"].as_f64().unwrap_or(f64::NAN));
        items = v["items"].as_u64().unwrap_or(0);
    }
    (
        Figures {
            per_second: rate,
            p50,
            p99,
            max,
            cpu,
            rss,
        },
        items,
    )
}

/// 4 WebSocket clients subscribed to every drive.
async fn over_websocket(d: &Daemon, secs: f64) -> Figures {
    let mut tasks = Vec::new();
    for _ in 0..SESSIONS {
        let mut request = format!("ws://127.0.0.1:{}/api/v1/stream?drives=all", d.http)
            .into_client_request()
            .unwrap();
        request
            .headers_mut()
            .insert("authorization", format!("Bearer {TOKEN}").parse().unwrap());
        let (mut ws, _) = tokio_tungstenite::connect_async(request).await.unwrap();
        tasks.push(tokio::spawn(async move {
            let warm = Instant::now() + Duration::from_secs(2);
            let end = warm + Duration::from_secs_f64(secs);
            let (mut n, mut lat) = (0u64, Vec::new());
            while let Ok(Some(Ok(m))) = tokio::time::timeout_at(end.into(), ws.next()).await {
                let Message::Text(t) = m else { continue };
                if Instant::now() < warm {
                    continue;
                }
                let v: Value = serde_json::from_str(&t).unwrap_or(Value::Null);
                if v["type"] == "status" {
                    n += 1;
                    if let Some(at) = v["seen_at"].as_str().and_then(parse_ms) {
                        lat.push(now_ms() - at);
                    }
                }
            }
            (n, lat)
        }));
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    let cpu0 = d.cpu_s();
    let t0 = Instant::now();
    let mut all = Vec::new();
    let mut n = 0;
    for t in tasks {
        let (k, lat) = t.await.unwrap();
        n += k;
        all.extend(lat);
    }
    let cpu = (d.cpu_s() - cpu0) / t0.elapsed().as_secs_f64();
    all.sort_by(f64::total_cmp);
    Figures {
        per_second: n as f64 / secs,
        p50: quantile(&all, 0.5),
        p99: quantile(&all, 0.99),
        max: all.last().copied().unwrap_or(f64::NAN),
        cpu,
        rss: d.rss_mib(),
    }
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .unwrap_or_default()
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ")
}

#[tokio::main]
async fn main() {
    let secs: f64 = std::env::var("DRIVEGATE_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10.0);
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::spawn(dir.path());
    let http = reqwest::Client::new();
    prepare(&d, &http).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let idle0 = d.cpu_s();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let idle = (d.cpu_s() - idle0) / 3.0;
    println!(
        "opcua bench: {BUSES} buses x {DRIVES} drives at 115200 baud, every motor turning; \
         {SESSIONS} clients each; window {secs} s; load {}",
        load()
    );
    println!(
        "no client: daemon CPU {:.1} % of a core, RSS {:.1} MiB",
        idle * 100.0,
        d.rss_mib()
    );
    let (ua, items) = over_opcua(&d, secs).await;
    let ws = over_websocket(&d, secs).await;
    println!("| face | per second | latency p50 / p99 / max (ms) | daemon CPU | daemon RSS |");
    println!("|---|---|---|---|---|");
    println!(
        "| OPC UA, {SESSIONS} sessions x {items} monitored items | {:.0} notifications | {:.0} / {:.0} / {:.0} | {:.1} % | {:.1} MiB |",
        ua.per_second,
        ua.p50,
        ua.p99,
        ua.max,
        ua.cpu * 100.0,
        ua.rss
    );
    println!(
        "| WebSocket, {SESSIONS} clients x 32 drives | {:.0} status messages | {:.0} / {:.0} / {:.0} | {:.1} % | {:.1} MiB |",
        ws.per_second,
        ws.p50,
        ws.p99,
        ws.max,
        ws.cpu * 100.0,
        ws.rss
    );
    println!("load after: {}", load());
}
