//! HTTP API benchmark (`cargo bench --bench http_api`), not a test: the
//! daemon runs in-process on the built-in simulator (4 drives, 115200 baud,
//! polling as fast as the bus allows, so the bus is always saturated), with
//! a Rust load client on loopback.
//!
//! 1. Cached status reads: `CLIENTS` keep-alive clients read
//!    `GET /api/v1/drives/conveyor/status` for `SECONDS`: requests/s and
//!    latency, and the bus's poll rate meanwhile (reads must not cost bus time).
//! 2. Command latency on the saturated bus: `PUT .../setpoint` one after
//!    the other, each returning after the drive's echo: p50/p99/max, next
//!    to the transaction times of the wire.
//! 3. The same commands while the readers of (1) keep running.
//! 4. Setpoints with a 1 s lease (`"lease_ms": 1000`), one after the other:
//!    with `BENCH_STATE_DIR` set, the safety journal is kept there and each
//!    one waits for its records to be synced to that disk; without, there
//!    is no journal. Run both to see what the sync costs.
//! 5. With `BENCH_STATE_DIR`: an hour of a lease renewed every 100 ms
//!    (36,000 renewals), through the lease book and the journal with the
//!    hour's instants passed in (the horizon rule sees the real spacing;
//!    only the waiting is skipped): records, syncs, compactions, the
//!    journal's size.
//!
//! Environment: `BENCH_SECONDS` (default 10), `BENCH_CLIENTS` (32),
//! `BENCH_COMMANDS` (500), `BENCH_STATE_DIR` (none).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use drivegate::config::Config;
use drivegate::metrics::Metrics;
use drivegate::plant::Plant;
use tokio_util::sync::CancellationToken;

const CONFIG: &str = r#"
[http]
listen = "127.0.0.1:0"
max_connections = 1024
[modbus_tcp]
enabled = false
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

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn ms(d: Duration) -> String {
    format!("{:.2} ms", d.as_secs_f64() * 1000.0)
}

/// Runs `clients` readers of the cached status until `stop`; returns the
/// request count and every latency.
async fn readers(
    base: &str,
    clients: u64,
    stop: Arc<AtomicBool>,
) -> Vec<tokio::task::JoinHandle<Vec<Duration>>> {
    (0..clients)
        .map(|_| {
            let url = format!("{base}/api/v1/drives/conveyor/status");
            let stop = stop.clone();
            tokio::spawn(async move {
                let http = reqwest::Client::new();
                let mut latencies = Vec::new();
                while !stop.load(Ordering::Relaxed) {
                    let t = Instant::now();
                    let r = http.get(&url).send().await.unwrap();
                    assert_eq!(r.status(), 200);
                    r.bytes().await.unwrap();
                    latencies.push(t.elapsed());
                }
                latencies
            })
        })
        .collect()
}

async fn commands(base: &str, n: u64) -> Vec<Duration> {
    setpoints(base, n, None).await
}

async fn setpoints(base: &str, n: u64, lease_ms: Option<u64>) -> Vec<Duration> {
    let http = reqwest::Client::new();
    let url = format!("{base}/api/v1/drives/lift/setpoint");
    let mut latencies = Vec::with_capacity(n as usize);
    for i in 0..n {
        let rpm = if i % 2 == 0 { 20 } else { 25 };
        let mut body = serde_json::json!({ "speed_rpm": rpm });
        if let Some(ms) = lease_ms {
            body["lease_ms"] = ms.into();
        }
        let t = Instant::now();
        let r = http.put(&url).json(&body).send().await.unwrap();
        assert_eq!(r.status(), 200, "{}", r.text().await.unwrap_or_default());
        r.bytes().await.unwrap();
        latencies.push(t.elapsed());
    }
    latencies.sort();
    latencies
}

fn report_commands(what: &str, latencies: &[Duration]) {
    println!(
        "{what}: {} commands, p50 {}, p99 {}, max {}",
        latencies.len(),
        ms(percentile(latencies, 0.5)),
        ms(percentile(latencies, 0.99)),
        ms(*latencies.last().unwrap_or(&Duration::ZERO)),
    );
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let seconds = env("BENCH_SECONDS", 10);
    let clients = env("BENCH_CLIENTS", 32);
    let n_commands = env("BENCH_COMMANDS", 500);

    let state_dir = std::env::var_os("BENCH_STATE_DIR").map(std::path::PathBuf::from);
    let mut config = Config::parse(CONFIG, "benchmark").unwrap();
    if let Some(dir) = &state_dir {
        // A journal of its own, on the disk the directory is on.
        let _ = std::fs::remove_dir_all(dir);
        config.safety.state_dir = Some(dir.join("daemon"));
    }
    let plant = Arc::new(Plant::start(&config).unwrap());
    let metrics = Metrics::new(plant.clone());
    let shutdown = CancellationToken::new();
    let faces =
        drivegate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
            .await
            .unwrap();
    let base = format!("http://{}", faces.http);
    let bus = plant.buses()[0].handle.clone();
    while bus.drives().iter().any(|d| d.status.is_none()) {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let line = bus.line();
    println!(
        "drivegate HTTP benchmark: 4 simulated drives at 115200 baud, polling as fast as the bus allows"
    );
    println!(
        "wire: a status poll takes {}, a single-register write {} (request + reply + 2 x t3.5 + 0.5 ms turnaround)",
        ms(line.transaction_time(8, 19, Duration::from_micros(500))),
        ms(line.transaction_time(8, 8, Duration::from_micros(500))),
    );

    // Warm up: activate the lift in speed mode.
    let http = reqwest::Client::new();
    for (path, body) in [
        ("/api/v1/drives/lift/commands/activate", None),
        (
            "/api/v1/drives/lift/mode",
            Some(serde_json::json!({"mode": "speed"})),
        ),
    ] {
        let req = match body {
            Some(b) => http.put(format!("{base}{path}")).json(&b),
            None => http.post(format!("{base}{path}")),
        };
        assert_eq!(req.send().await.unwrap().status(), 200);
    }

    // 1. Cached reads.
    let polls_before = bus.stats().polls;
    let started = Instant::now();
    let stop = Arc::new(AtomicBool::new(false));
    let tasks = readers(&base, clients, stop.clone()).await;
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    stop.store(true, Ordering::Relaxed);
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    let elapsed = started.elapsed().as_secs_f64();
    let polls = bus.stats().polls - polls_before;
    all.sort();
    println!(
        "cached status reads: {clients} clients, {seconds} s: {:.0} requests/s, p50 {}, p99 {}, max {}; bus polls meanwhile {:.0}/s",
        all.len() as f64 / elapsed,
        ms(percentile(&all, 0.5)),
        ms(percentile(&all, 0.99)),
        ms(*all.last().unwrap_or(&Duration::ZERO)),
        polls as f64 / elapsed,
    );

    // 2. Commands on the saturated bus.
    let polls_before = bus.stats().polls;
    let started = Instant::now();
    let latencies = commands(&base, n_commands).await;
    let elapsed = started.elapsed().as_secs_f64();
    report_commands("setpoint commands, bus saturated by polling", &latencies);
    println!(
        "  bus polls meanwhile {:.0}/s",
        (bus.stats().polls - polls_before) as f64 / elapsed
    );

    // 3. Commands while the readers keep hammering the cache.
    let stop = Arc::new(AtomicBool::new(false));
    let tasks = readers(&base, clients, stop.clone()).await;
    let reads = AtomicU64::new(0);
    let started = Instant::now();
    let latencies = commands(&base, n_commands).await;
    let elapsed = started.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        reads.fetch_add(t.await.unwrap().len() as u64, Ordering::Relaxed);
    }
    report_commands(
        &format!("setpoint commands, bus saturated, {clients} readers running"),
        &latencies,
    );
    println!(
        "  cached reads meanwhile {:.0}/s",
        reads.load(Ordering::Relaxed) as f64 / elapsed
    );
    println!(
        "  bus gap violations seen by the simulator: {}",
        plant.buses()[0]
            .sim
            .as_ref()
            .map_or(0, |s| s.stats().gap_violations)
    );

    // 4. Leased setpoints: each syncs its lease to the journal first.
    let latencies = setpoints(&base, n_commands, Some(1000)).await;
    report_commands(
        &format!(
            "setpoints with a 1 s lease, bus saturated, safety journal {}",
            match &state_dir {
                Some(d) => format!("in {}", d.display()),
                None => "off".to_string(),
            }
        ),
        &latencies,
    );
    let (health, counts) = faces.control.journal();
    println!(
        "  journal: {health:?}, {} records, {} compactions, {} bytes",
        counts.records, counts.compactions, counts.bytes
    );

    shutdown.cancel();
    faces.wait().await;
    drivegate::control::shutdown(&plant, config.safety.on_shutdown).await;

    // 5. An hour of renewals every 100 ms.
    if let Some(dir) = &state_dir {
        soak(&dir.join("soak"));
    }
}

/// A 1 s HTTP lease renewed every 100 ms for an hour, through the lease
/// book (the hour's instants passed in) and the journal on the disk.
fn soak(dir: &std::path::Path) {
    use drivegate::control::Applied;
    use drivegate::control::journal::Journal;
    use drivegate::control::journal::format::{Action, HolderKind, ModeName, Record, unix_ms};
    use drivegate::control::lease_book::{Holder, LeaseAsk, LeaseBook, Note, WriteKind};

    let mut journal = Journal::open(Some(dir), 1).journal;
    let mut book = LeaseBook::new(drivegate::control::stop_action::StopAction::ZeroSpeed);
    let t0 = Instant::now();
    let wall0 = std::time::SystemTime::now();
    let mut records = 0u64;
    let mut syncs = 0u64;
    let mut append = |book: &mut LeaseBook, journal: &mut Journal| {
        let batch: Vec<Record> = book
            .take_notes()
            .into_iter()
            .filter_map(|n| match n {
                Note::Lease {
                    owner,
                    deadline,
                    length,
                    ..
                } => Some(Record::Lease {
                    drive: "lift".into(),
                    owner: owner.to_string(),
                    holder: HolderKind::Http,
                    deadline_ms: unix_ms(wall0 + (deadline - t0)),
                    length_ms: length.as_millis() as u64,
                    action: Action::ZeroSpeed,
                    mode: ModeName::Speed,
                }),
                _ => None,
            })
            .collect();
        if !batch.is_empty() {
            records += batch.len() as u64;
            syncs += 1;
            journal.append(&batch).unwrap();
        }
    };
    let ask = LeaseAsk {
        owner: "scada".into(),
        holder: Holder::Request,
        mode: drivegate::drive::Mode::Speed,
        length: Duration::from_secs(1),
        allowance: Duration::from_secs(2),
        action: None,
        comm_loss: false,
    };
    let (grant, _) = book.grant(1, ask, t0);
    let ticket = book.begin_write(
        1,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: drivegate::drive::Mode::Speed,
        },
        "bench".into(),
    );
    book.end_write(&ticket, Applied::Yes, t0);
    append(&mut book, &mut journal);
    let renewals = 36_000u32;
    let started = Instant::now();
    for i in 1..=renewals {
        let now = t0 + Duration::from_millis(100) * i;
        book.renew(1, None, now).unwrap();
        append(&mut book, &mut journal);
    }
    let took = started.elapsed();
    let counts = journal.counts();
    let size = std::fs::metadata(dir.join("safety.journal")).map_or(0, |m| m.len());
    println!(
        "an hour of a 1 s lease renewed every 100 ms ({renewals} renewals): {records} records in {syncs} syncs, {} compactions, journal {size} bytes at the end (largest before a compaction: {} KiB); the syncs took {:.1} s of the hour",
        counts.compactions,
        drivegate::control::journal::COMPACT_AT / 1024,
        took.as_secs_f64()
    );
}
