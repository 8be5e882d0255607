//! Modbus TCP passthrough benchmark: 16 concurrent TCP clients (tokio-modbus's
//! client) reading the status block of 8 drives on one simulated, wire-timed
//! bus at 115200 baud, while the daemon polls every drive.
//!
//! Phase 0, one client alone: the latency of a passthrough read without
//! other clients (the polls still run).
//!
//! Phase 1, strict passthrough: every read is a bus transaction. Reports the
//! transactions/s achieved as a fraction of the bus's theoretical limit
//! (wire time of request and reply + 2 x t3.5 + the drive's turnaround), the
//! latency p50/p99 seen by the clients, and how evenly the clients shared
//! the bus.
//!
//! Phase 2, polled copy on: reads are answered from the latest poll, first
//! with each client reading every 5 ms (a dashboard), then back to back (the
//! ceiling, bound by the CPU). Reports reads/s and the staleness the clients
//! saw. Phase 3, communication loss: phase 2's back-to-back reads again, the clients' network under a
//! communication-loss time (each request renews its connection's leases).
//! Staleness is measured
//! physically: every drive turns at a constant speed, and each reply's
//! position (CYCLE_NUM, ANGLE) is compared with the simulated drive's true
//! position when the reply arrives; the lag divided by the speed is the age
//! of the data. Phase 1 measures it too, for comparison.
//!
//! `cargo bench --bench modbus_tcp`; `DRIVEGATE_BENCH_SECS` sets each
//! phase's length (default 10).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::sync::Arc;
use std::time::{Duration, Instant};

use drivegate::bus::handle::JobOptions;
use drivegate::config::Config;
use drivegate::drive::{ConfigCommand, DriveRequest, Status};
use drivegate::metrics::Metrics;
use drivegate::modbus::timing::LineTiming;
use drivegate::plant::Plant;
use tokio_modbus::client::Reader;
use tokio_modbus::{Slave, client::tcp};
use tokio_util::sync::CancellationToken;

const CLIENTS: usize = 16;
const DRIVES: u8 = 8;
const BAUD: u32 = 115_200;
const TURNAROUND_MS: f64 = 0.5;
/// Output speed of every drive during the run, rpm.
const SPEED_RPM: i16 = 60;

fn config(poll_interval_ms: u64, polled_copy: &str) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nlisten = \"127.0.0.1:0\"\n\
         max_connections_per_address = 64\n{polled_copy}\n\
         [[bus]]\nname = \"bench\"\nport = \"sim\"\nbaud = {BAUD}\nresponse_timeout_ms = 50\nretries = 1\n\
         poll_interval_ms = {poll_interval_ms}\n[bus.sim]\nturnaround_ms = {TURNAROUND_MS}\nseed = 3\n"
    );
    for unit in 1..=DRIVES {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\ngear_ratio = 3.75\n"
        ));
    }
    toml
}

struct Sample {
    latency: Duration,
    staleness: Option<Duration>,
}

struct PhaseResult {
    elapsed: Duration,
    samples: Vec<Sample>,
    per_client: Vec<usize>,
    errors: usize,
    wire_transactions: u64,
    polls: u64,
    busy_seconds: f64,
    gap_violations: u64,
}

/// Degrees of a status position (turns and angle), relative to `reference`'s
/// turn count so wrapping does not matter.
fn lag_degrees(truth: &Status, read: &Status) -> f64 {
    let turns = f64::from(truth.turns.wrapping_sub(read.turns) as i16);
    turns * 360.0
        + f64::from(i32::from(truth.angle_centideg) - i32::from(read.angle_centideg)) / 100.0
}

/// Runs one phase; with `pace`, each client sends one read per period
/// (a dashboard polling at a fixed rate) instead of back to back.
async fn run_phase(
    name: &str,
    toml: &str,
    secs: u64,
    clients: usize,
    pace: Option<Duration>,
) -> PhaseResult {
    let config = Config::parse(toml, name).unwrap();
    let plant = Arc::new(Plant::start(&config).unwrap());
    let metrics = Metrics::new(plant.clone());
    let shutdown = CancellationToken::new();
    let faces =
        drivegate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
            .await
            .unwrap();
    let addr = faces.modbus_tcp.unwrap();
    let bus = plant.buses()[0].handle.clone();
    let sim = drivegate::plant::SimRef::of(plant.buses()[0].clone()).unwrap();

    // Every drive turning at a constant speed.
    for unit in 1..=DRIVES {
        for request in [
            DriveRequest::Config(ConfigCommand::Activate),
            DriveRequest::Config(ConfigCommand::SpeedMode),
            DriveRequest::Speed { rpm: SPEED_RPM },
        ] {
            bus.execute(unit, &request, JobOptions::default())
                .await
                .unwrap();
        }
    }
    tokio::time::sleep(Duration::from_secs(2)).await;

    let stats_before = bus.stats();
    let sim_before = sim.stats();
    let start = Instant::now();
    let deadline = start + Duration::from_secs(secs);
    let mut tasks = Vec::new();
    for client in 0..clients {
        let unit = (client % usize::from(DRIVES)) as u8 + 1;
        let plant = plant.clone();
        tasks.push(tokio::spawn(async move {
            let sim = drivegate::plant::SimRef::of(plant.buses()[0].clone()).unwrap();
            let mut ctx = tcp::connect_slave(addr, Slave(unit)).await.unwrap();
            let mut samples = Vec::new();
            let mut errors = 0;
            let mut ticks = pace.map(|p| {
                let mut t = tokio::time::interval(p);
                t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
                t
            });
            while Instant::now() < deadline {
                if let Some(t) = ticks.as_mut() {
                    t.tick().await;
                }
                let sent = Instant::now();
                let reply = ctx.read_holding_registers(0x00C0, 7).await;
                let latency = sent.elapsed();
                match reply {
                    Ok(Ok(regs)) if regs.len() == 7 => {
                        let truth = sim.drive(unit).unwrap();
                        let read = Status::from_registers(regs.try_into().unwrap());
                        let deg_per_s = truth.speed_rpm.abs() * 6.0;
                        let staleness = (deg_per_s > 1.0).then(|| {
                            let lag = lag_degrees(&truth.status, &read) / deg_per_s;
                            Duration::from_secs_f64(lag.max(0.0))
                        });
                        samples.push(Sample { latency, staleness });
                    }
                    _ => errors += 1,
                }
            }
            (samples, errors)
        }));
    }
    let mut samples = Vec::new();
    let mut per_client = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let (s, e) = t.await.unwrap();
        per_client.push(s.len());
        samples.extend(s);
        errors += e;
    }
    let elapsed = start.elapsed();
    let stats_after = bus.stats();
    let sim_after = sim.stats();
    let result = PhaseResult {
        elapsed,
        samples,
        per_client,
        errors,
        wire_transactions: stats_after.on_wire() - stats_before.on_wire(),
        polls: stats_after.polls - stats_before.polls,
        busy_seconds: stats_after.busy_seconds - stats_before.busy_seconds,
        gap_violations: sim_after.gap_violations - sim_before.gap_violations,
    };
    shutdown.cancel();
    faces.wait().await;
    drivegate::control::shutdown(&plant, drivegate::control::stop_action::StopAction::None).await;
    result
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn ms(d: Duration) -> String {
    format!("{:.2} ms", d.as_secs_f64() * 1e3)
}

fn report(name: &str, r: &PhaseResult, limit_per_s: f64) {
    let secs = r.elapsed.as_secs_f64();
    let reads = r.samples.len() as f64 / secs;
    let mut latencies: Vec<Duration> = r.samples.iter().map(|s| s.latency).collect();
    latencies.sort();
    let mut stale: Vec<Duration> = r.samples.iter().filter_map(|s| s.staleness).collect();
    stale.sort();
    let wire = r.wire_transactions as f64 / secs;
    let polls = r.polls as f64 / secs;
    // A snapshot taken between a poll's transaction count and its poll
    // count makes the polls' difference one more than the transactions'.
    let tcp_on_wire = r.wire_transactions.saturating_sub(r.polls) as f64 / secs;
    println!("\n== {name} ==");
    println!(
        "TCP reads answered: {reads:.1}/s ({} in {secs:.1} s, {} errors); per client min {} max {}",
        r.samples.len(),
        r.errors,
        r.per_client.iter().min().unwrap_or(&0),
        r.per_client.iter().max().unwrap_or(&0)
    );
    println!(
        "bus: {wire:.1} transactions/s = {:.1} % of the {limit_per_s:.1}/s limit \
         (TCP {tcp_on_wire:.1}/s = {:.1} %, polls {polls:.1}/s); wire busy {:.1} %; gap violations {}",
        100.0 * wire / limit_per_s,
        100.0 * tcp_on_wire / limit_per_s,
        100.0 * r.busy_seconds / secs,
        r.gap_violations
    );
    println!(
        "latency p50 {} p99 {} max {}",
        ms(percentile(&latencies, 0.50)),
        ms(percentile(&latencies, 0.99)),
        ms(latencies.last().copied().unwrap_or_default())
    );
    println!(
        "staleness p50 {} p99 {} max {} ({} samples)",
        ms(percentile(&stale, 0.50)),
        ms(percentile(&stale, 0.99)),
        ms(stale.last().copied().unwrap_or_default()),
        stale.len()
    );
}

fn main() {
    let secs = std::env::var("DRIVEGATE_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10u64);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let line = LineTiming::new_8n1(BAUD);
    // Status read: 8-byte request, 19-byte reply.
    let transaction = line.transaction_time(8, 19, Duration::from_secs_f64(TURNAROUND_MS / 1e3));
    let limit = 1.0 / transaction.as_secs_f64();
    println!(
        "Modbus TCP benchmark: {CLIENTS} clients, {DRIVES} drives at {BAUD} baud, turnaround {TURNAROUND_MS} ms, \
         {secs} s per phase; status read {} on the wire -> limit {limit:.1} transactions/s",
        ms(transaction)
    );
    let alone = runtime.block_on(run_phase("one client", &config(100, ""), secs, 1, None));
    report(
        "strict passthrough, one client alone (poll_interval_ms = 100 per drive)",
        &alone,
        limit,
    );
    let passthrough = runtime.block_on(run_phase(
        "passthrough",
        &config(100, ""),
        secs,
        CLIENTS,
        None,
    ));
    report(
        "strict passthrough, clients back to back (poll_interval_ms = 100 per drive)",
        &passthrough,
        limit,
    );
    let polled_copy = "[[modbus_tcp.polled_copy]]\nbus = \"bench\"\nmax_age_ms = 100";
    let paced = runtime.block_on(run_phase(
        "polled copy, paced",
        &config(0, polled_copy),
        secs,
        CLIENTS,
        Some(Duration::from_millis(5)),
    ));
    report(
        "polled copy, each client reading every 5 ms (poll_interval_ms = 0, max_age_ms = 100)",
        &paced,
        limit,
    );
    let flat_out = runtime.block_on(run_phase(
        "polled copy, back to back",
        &config(0, polled_copy),
        secs,
        CLIENTS,
        None,
    ));
    report(
        "polled copy, clients back to back (CPU-bound: the machine's cores are the limit)",
        &flat_out,
        limit,
    );
    // The same with the clients' network under a communication-loss time:
    // every request renews its connection's leases (the cost of the
    // function, where requests cost least).
    let watched = format!(
        "{polled_copy}\n[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"\ncomm_loss_ms = 1000"
    );
    let comm_loss = runtime.block_on(run_phase(
        "polled copy, back to back, comm_loss_ms",
        &config(0, &watched),
        secs,
        CLIENTS,
        None,
    ));
    report(
        "polled copy, clients back to back, the clients' network with comm_loss_ms = 1000",
        &comm_loss,
        limit,
    );
}
