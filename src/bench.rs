//! `drivegate bench`: how close the bus engine gets to the wire's limit.
//!
//! For each drive count it runs the simulator (wire-timed, no faults) and a
//! bus polling every drive as fast as the bus allows, measures the achieved
//! status polls per second against the theoretical limit (request + reply on
//! the wire + 2 x t3.5 + turnaround), counts the silent-interval violations
//! the simulator saw and the silence it saw before each request (t3.5 plus
//! the master's overhead), and injects commands at random moments to
//! measure how long a command waits while polling saturates the bus.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};

use crate::bus::handle::JobOptions;
use crate::bus::scheduler::{self, BusSettings};
use crate::drive::DriveRequest;
use crate::sim::{SimConfig, Simulator};

/// Arguments of `drivegate bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Drive counts to measure, e.g. "1,8,32".
    #[arg(long, default_value = "1,8,32", value_delimiter = ',')]
    pub drives: Vec<u8>,
    /// Seconds of polling measured per drive count.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// The simulated drives' turnaround, in ms (the limit accounts for it).
    #[arg(long, default_value_t = 0.0)]
    pub turnaround_ms: f64,
    /// Baud rate of the simulated line.
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
    /// Commands injected while polling (for the latency figures).
    #[arg(long, default_value_t = 300)]
    pub commands: usize,
}

/// Figures of one run.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchResult {
    /// Drives polled.
    pub drives: u8,
    /// Status polls per second achieved.
    pub polls_per_s: f64,
    /// Theoretical limit in polls per second.
    pub limit_per_s: f64,
    /// Silent-interval violations the simulator counted.
    pub gap_violations: u64,
    /// Polls that failed.
    pub poll_failures: u64,
    /// Command latency percentiles (p50, p99, max), submit to confirmation.
    pub command_latency: (Duration, Duration, Duration),
    /// One status transaction on the wire (the unit of the latency figures).
    pub transaction: Duration,
    /// The silence before each request as the wire saw it (p50, p99): t3.5
    /// plus the master's overhead.
    pub wire_idle: (Duration, Duration),
}

/// Runs one measurement with `drives` drives.
pub async fn measure(args: &BenchArgs, drives: u8) -> Result<BenchResult, String> {
    let units: Vec<u8> = (1..=drives).collect();
    let mut sim_config = SimConfig::for_units(units.iter().copied());
    sim_config.baud = args.baud;
    sim_config.turnaround_ms = args.turnaround_ms;
    let sim =
        Simulator::start(sim_config).map_err(|e| format!("cannot start the simulator: {e}"))?;
    let port = sim.port_path().display().to_string();
    let settings = BusSettings::new(
        "bench",
        &port,
        args.baud,
        units.iter().map(|&u| (u, Duration::ZERO)).collect(),
    );
    let (bus, thread) =
        scheduler::spawn(settings).map_err(|e| format!("cannot start the bus: {e}"))?;

    // Warm up until every drive answered once.
    let start = Instant::now();
    while bus.drives().iter().any(|d| d.status.is_none()) {
        if start.elapsed() > Duration::from_secs(10) {
            return Err("the simulated drives did not answer within 10 s".to_string());
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }

    let line = bus.line();
    let turnaround = Duration::from_secs_f64(args.turnaround_ms / 1000.0);
    let transaction = line.transaction_time(8, 19, turnaround);

    // Poll rate, undisturbed.
    let gaps_before = sim.gaps();
    let before = (bus.stats(), sim.stats(), Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    let after = (bus.stats(), sim.stats(), Instant::now());
    let gaps = sim.gaps().since(&gaps_before);
    let wire_idle = (
        gaps.quantile(0.5).unwrap_or_default(),
        gaps.quantile(0.99).unwrap_or_default(),
    );
    let elapsed = (after.2 - before.2).as_secs_f64();
    let polls = after.0.polls - before.0.polls;
    let poll_failures = after.0.poll_failures - before.0.poll_failures;
    let mut gap_violations = after.1.gap_violations - before.1.gap_violations;

    // Command latency while polling saturates the bus: a write at a random
    // moment, so it lands anywhere in the transaction in flight.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut latencies = Vec::with_capacity(args.commands);
    let command = DriveRequest::Rs485Control { enabled: true };
    let sim_before = sim.stats();
    for i in 0..args.commands {
        let pause = Duration::from_micros(rng.random_range(2_000..12_000));
        tokio::time::sleep(pause).await;
        let unit = units[i % units.len()];
        let t = Instant::now();
        bus.execute(unit, &command, JobOptions::default())
            .await
            .map_err(|e| format!("command {i} failed: {e}"))?;
        latencies.push(t.elapsed());
    }
    gap_violations += sim.stats().gap_violations - sim_before.gap_violations;
    latencies.sort();
    let pct = |p: f64| latencies[((latencies.len() as f64 - 1.0) * p).round() as usize];
    let command_latency = if latencies.is_empty() {
        (Duration::ZERO, Duration::ZERO, Duration::ZERO)
    } else {
        (pct(0.5), pct(0.99), pct(1.0))
    };

    bus.stop();
    let _ = tokio::task::spawn_blocking(move || thread.join()).await;
    drop(sim);
    Ok(BenchResult {
        drives,
        polls_per_s: polls as f64 / elapsed,
        limit_per_s: 1.0 / transaction.as_secs_f64(),
        gap_violations,
        poll_failures,
        command_latency,
        transaction,
        wire_idle,
    })
}

/// Runs every measurement and prints the table.
pub async fn run(args: BenchArgs) -> Result<(), String> {
    println!(
        "status polling on one simulated bus at {} baud, turnaround {} ms; limit = wire time of request + reply + 2 x t3.5 + turnaround",
        args.baud, args.turnaround_ms
    );
    println!(
        "{:>6} {:>10} {:>10} {:>8} {:>6} {:>6} {:>10} {:>10} {:>10} {:>16}",
        "drives",
        "polls/s",
        "limit/s",
        "of limit",
        "gaps",
        "fails",
        "cmd p50",
        "cmd p99",
        "cmd max",
        "idle p50/p99"
    );
    for &n in &args.drives {
        let r = measure(&args, n).await?;
        let ms = |d: Duration| format!("{:.2} ms", d.as_secs_f64() * 1000.0);
        println!(
            "{:>6} {:>10.1} {:>10.1} {:>7.1}% {:>6} {:>6} {:>10} {:>10} {:>10} {:>16}",
            r.drives,
            r.polls_per_s,
            r.limit_per_s,
            100.0 * r.polls_per_s / r.limit_per_s,
            r.gap_violations,
            r.poll_failures,
            ms(r.command_latency.0),
            ms(r.command_latency.1),
            ms(r.command_latency.2),
            format!(
                "{:.2}/{:.2} ms",
                r.wire_idle.0.as_secs_f64() * 1e3,
                r.wire_idle.1.as_secs_f64() * 1e3
            ),
        );
        println!(
            "{:>6} command p99 = {:.2} status transaction times ({} per transaction)",
            "",
            r.command_latency.1.as_secs_f64() / r.transaction.as_secs_f64(),
            ms(r.transaction)
        );
    }
    Ok(())
}
