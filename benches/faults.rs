//! Poll rate under faults: eight simulated drives on one wire-timed bus at
//! 115200 baud, each fault of the fault suite in turn, and the rate at which
//! the healthy drives' status polls are answered, next to the fault-free
//! rate.
//!
//! The bound: the other drives keep their poll rate within 10 %
//! of the fault-free rate, except for the time the faulty traffic itself
//! takes. That time, F, is measured from the bus's own counters: the wire
//! time of the window (`busy_seconds`) minus what the answered polls took
//! at the fault-free cost of one poll, plus the time the port was down.
//! The adjusted rate is the healthy drives' answered polls over (window -
//! F); the run fails (exit status 1) if it falls more than 10 % below the
//! fault-free rate.
//!
//! Two modes: `saturated` polls as fast as the bus allows
//! (`poll_interval_ms = 0`), where every millisecond a fault takes is lost
//! to the others; `paced` polls each drive every 100 ms (half the wire),
//! where the spare time absorbs the faults.
//!
//! `cargo bench --bench faults`; `DRIVEGATE_BENCH_SECS` sets each window
//! (default 10).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use drivegate::bus::BusEvent;
use drivegate::config::Config;
use drivegate::control::stop_action::StopAction;
use drivegate::plant::Plant;
use drivegate::sim::{FaultRates, SimConfig, SimStats, Simulator};

const DRIVES: u8 = 8;
/// The drive the single-drive faults hit.
const FAULTY: u8 = 8;
const BOUND: f64 = 0.90;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    None,
    Corrupted,
    Dropped,
    Late,
    Noise,
    Silent,
    PowerCycle,
    Unplug,
}

impl Fault {
    const ALL: [Fault; 8] = [
        Fault::None,
        Fault::Corrupted,
        Fault::Dropped,
        Fault::Late,
        Fault::Noise,
        Fault::Silent,
        Fault::PowerCycle,
        Fault::Unplug,
    ];

    fn name(self) -> &'static str {
        match self {
            Fault::None => "none (baseline)",
            Fault::Corrupted => "5 % corrupted",
            Fault::Dropped => "5 % dropped",
            Fault::Late => "5 % late (70 ms)",
            Fault::Noise => "5 % noise",
            Fault::Silent => "unit 8 silent",
            Fault::PowerCycle => "unit 8 power cut /2 s",
            Fault::Unplug => "unplugged 0.5 s",
        }
    }

    fn rates(self) -> FaultRates {
        let mut r = FaultRates::default();
        match self {
            Fault::Corrupted => r.crc_error_rate = 0.05,
            Fault::Dropped => r.drop_rate = 0.05,
            Fault::Late => {
                // Past the 50 ms timeout, inside the 50 ms guard after it.
                r.late_rate = 0.05;
                r.late_ms = 70.0;
            }
            Fault::Noise => r.noise_rate = 0.05,
            _ => {}
        }
        r
    }

    /// Drives not hit by the fault.
    fn healthy(self) -> Vec<u8> {
        match self {
            Fault::Silent | Fault::PowerCycle => (1..=DRIVES).filter(|u| *u != FAULTY).collect(),
            _ => (1..=DRIVES).collect(),
        }
    }
}

fn config(port: &str, poll_interval_ms: u64) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
         [[bus]]\nname = \"bench\"\nport = \"{port}\"\nbaud = 115200\nresponse_timeout_ms = 50\n\
         retries = 1\npoll_interval_ms = {poll_interval_ms}\n"
    );
    if port == "sim" {
        toml.push_str("[bus.sim]\nturnaround_ms = 0.5\nseed = 5\n");
    }
    for unit in 1..=DRIVES {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\ngear_ratio = 3.75\n"
        ));
    }
    toml
}

/// What one window measured.
struct Measure {
    window: f64,
    healthy: usize,
    /// Answered polls of the healthy drives.
    healthy_polls: u64,
    /// Answered polls per unit.
    per_unit: BTreeMap<u8, u64>,
    /// Wire time in the window, s.
    busy: f64,
    /// Transactions that ended well.
    ok: u64,
    /// Attempts that failed (retries and failed transactions).
    failed_attempts: u64,
    /// Time the port was down, s.
    down: f64,
    sim: SimStats,
}

async fn wait_online(plant: &Plant) {
    let start = Instant::now();
    while !plant.buses()[0]
        .handle
        .drives()
        .iter()
        .all(|d| d.status.is_some())
    {
        assert!(start.elapsed() < Duration::from_secs(10), "drives offline");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

async fn run(fault: Fault, poll_interval_ms: u64, secs: f64) -> Measure {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyBENCH");
    // An unplug needs a simulator the bench owns, behind a link.
    let mut linked = (fault == Fault::Unplug).then(|| {
        let mut sim = Simulator::start(SimConfig::for_units(1..=DRIVES)).unwrap();
        sim.link_at(&link).unwrap();
        sim
    });
    let port = if linked.is_some() {
        link.display().to_string()
    } else {
        "sim".to_string()
    };
    let config = Config::parse(&config(&port, poll_interval_ms), "bench").unwrap();
    let plant = Plant::start(&config).unwrap();
    wait_online(&plant).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let bus = plant.buses()[0].handle.clone();

    let window = Duration::from_secs_f64(secs);
    let mut events = bus.subscribe();
    let before = bus.stats();
    let sim_before = plant.buses()[0].sim.as_ref().map(|s| s.stats());
    let start = Instant::now();
    let end = start + window;
    if let Some(sim) = plant.buses()[0].sim.as_ref() {
        sim.set_fault_rates(fault.rates()).unwrap();
        if fault == Fault::Silent {
            sim.set_silent(FAULTY, true);
        }
    }

    let mut per_unit: BTreeMap<u8, u64> = BTreeMap::new();
    let mut down_since: Option<Instant> = None;
    let mut down = Duration::ZERO;
    let mut next_cut = start + Duration::from_millis(500);
    let unplug_at = start + window / 2 - Duration::from_millis(250);
    let mut replug_at = None;
    let mut sim_stats = SimStats::default();
    loop {
        let now = Instant::now();
        if now >= end {
            break;
        }
        if fault == Fault::PowerCycle && now >= next_cut {
            plant.buses()[0]
                .sim
                .as_ref()
                .unwrap()
                .power_cycle(FAULTY)
                .unwrap();
            next_cut += Duration::from_secs(2);
        }
        if fault == Fault::Unplug && now >= unplug_at && replug_at.is_none() {
            let sim = linked.take().unwrap();
            sim_stats = sim.stats();
            drop(sim);
            replug_at = Some(now + Duration::from_millis(500));
        }
        if let Some(at) = replug_at
            && now >= at
            && linked.is_none()
        {
            let mut sim = Simulator::start(SimConfig::for_units(1..=DRIVES)).unwrap();
            sim.link_at(&link).unwrap();
            linked = Some(sim);
        }
        match tokio::time::timeout(Duration::from_millis(5), events.recv()).await {
            Ok(Ok(BusEvent::Status { unit, .. })) => *per_unit.entry(unit).or_default() += 1,
            Ok(Ok(BusEvent::BusDown { .. })) => down_since = Some(Instant::now()),
            Ok(Ok(BusEvent::BusUp { .. })) => {
                if let Some(t) = down_since.take() {
                    down += t.elapsed();
                }
            }
            Ok(Ok(_)) | Err(_) => {}
            Ok(Err(e)) => panic!("event stream: {e}"),
        }
    }
    if let Some(t) = down_since {
        down += t.elapsed();
    }
    let after = bus.stats();
    let elapsed = start.elapsed().as_secs_f64();
    let sim = match (plant.buses()[0].sim.as_ref(), sim_before) {
        (Some(s), Some(b)) => diff(&s.stats(), &b),
        _ => sim_stats,
    };
    drivegate::control::shutdown(&plant, StopAction::None).await;
    let sim = match linked.take() {
        Some(replugged) => add(&sim, &replugged.stats()),
        None => sim,
    };

    let healthy = fault.healthy();
    let failed = |s: &drivegate::bus::stats::BusStatsSnapshot| {
        use drivegate::bus::stats::Outcome;
        s.retries
            + s.count(Outcome::Timeout)
            + s.count(Outcome::CrcError)
            + s.count(Outcome::BadReply)
    };
    let ok =
        |s: &drivegate::bus::stats::BusStatsSnapshot| s.count(drivegate::bus::stats::Outcome::Ok);
    Measure {
        window: elapsed,
        healthy: healthy.len(),
        healthy_polls: healthy
            .iter()
            .map(|u| per_unit.get(u).copied().unwrap_or(0))
            .sum(),
        per_unit,
        busy: after.busy_seconds - before.busy_seconds,
        ok: ok(&after) - ok(&before),
        failed_attempts: failed(&after) - failed(&before),
        down: down.as_secs_f64(),
        sim,
    }
}

fn add(a: &SimStats, b: &SimStats) -> SimStats {
    SimStats {
        requests: a.requests + b.requests,
        replies: a.replies + b.replies,
        broadcasts: a.broadcasts + b.broadcasts,
        gap_violations: a.gap_violations + b.gap_violations,
        bad_crc_requests: a.bad_crc_requests + b.bad_crc_requests,
        truncated_frames: a.truncated_frames + b.truncated_frames,
        unanswered: a.unanswered + b.unanswered,
        merged_frames: a.merged_frames + b.merged_frames,
        dropped: a.dropped + b.dropped,
        corrupted: a.corrupted + b.corrupted,
        late: a.late + b.late,
        stalled: a.stalled + b.stalled,
        noise_bursts: a.noise_bursts + b.noise_bursts,
        exceptions: a.exceptions + b.exceptions,
        collisions: a.collisions + b.collisions,
        connections: a.connections + b.connections,
    }
}

fn diff(a: &SimStats, b: &SimStats) -> SimStats {
    SimStats {
        requests: a.requests - b.requests,
        replies: a.replies - b.replies,
        broadcasts: a.broadcasts - b.broadcasts,
        gap_violations: a.gap_violations - b.gap_violations,
        bad_crc_requests: a.bad_crc_requests - b.bad_crc_requests,
        truncated_frames: a.truncated_frames - b.truncated_frames,
        unanswered: a.unanswered - b.unanswered,
        merged_frames: a.merged_frames - b.merged_frames,
        dropped: a.dropped - b.dropped,
        corrupted: a.corrupted - b.corrupted,
        late: a.late - b.late,
        stalled: a.stalled - b.stalled,
        noise_bursts: a.noise_bursts - b.noise_bursts,
        exceptions: a.exceptions - b.exceptions,
        collisions: a.collisions - b.collisions,
        connections: a.connections - b.connections,
    }
}

fn main() {
    let secs: f64 = std::env::var("DRIVEGATE_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10.0);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    println!(
        "Poll rate under faults: {DRIVES} drives at 115200 baud, response timeout 50 ms, 1 retry, \
         guard 50 ms, {secs} s per window. F = wire time of the faulty traffic + port down time; \
         adjusted = healthy polls / (window - F); bound: adjusted >= {:.0} % of the baseline.",
        BOUND * 100.0
    );
    let mut broken = Vec::new();
    for (mode, interval) in [("saturated", 0u64), ("paced", 100)] {
        println!(
            "\n== {mode}: poll_interval_ms = {interval} ==\n{:<22} {:>7} {:>11} {:>8} {:>13} {:>9} {:>10} {:>6}  injected",
            "fault",
            "healthy",
            "polls/s/dr",
            "raw %",
            "F s (% win)",
            "adjusted",
            "failed att",
            "gaps",
        );
        let mut baseline: Option<(f64, f64)> = None;
        for fault in Fault::ALL {
            let m = runtime.block_on(run(fault, interval, secs));
            let rate = m.healthy_polls as f64 / m.healthy as f64 / m.window;
            // Fault-free cost of one answered poll, and the baseline rate.
            let (rate0, cost) = *baseline.get_or_insert((rate, m.busy / m.ok.max(1) as f64));
            let f = (m.busy - m.ok as f64 * cost).max(0.0) + m.down;
            let adjusted = m.healthy_polls as f64 / m.healthy as f64 / (m.window - f);
            let ratio = adjusted / rate0;
            let s = &m.sim;
            println!(
                "{:<22} {:>7} {:>11.2} {:>7.1}% {:>6.2} ({:>4.1}%) {:>8.1}% {:>10} {:>6}  \
                 corrupted {} dropped {} late {} noise {} unanswered {} down {:.2} s",
                fault.name(),
                m.healthy,
                rate,
                100.0 * rate / rate0,
                f,
                100.0 * f / m.window,
                100.0 * ratio,
                m.failed_attempts,
                s.gap_violations,
                s.corrupted,
                s.dropped,
                s.late,
                s.noise_bursts,
                s.unanswered,
                m.down
            );
            let least = m
                .per_unit
                .iter()
                .filter(|(u, _)| fault.healthy().contains(u))
                .map(|(_, n)| *n)
                .min()
                .unwrap_or(0);
            if ratio < BOUND || s.gap_violations > 0 {
                broken.push(format!(
                    "{mode} / {}: adjusted {:.1} %",
                    fault.name(),
                    100.0 * ratio
                ));
            }
            if least == 0 {
                broken.push(format!(
                    "{mode} / {}: a healthy drive was not polled",
                    fault.name()
                ));
            }
        }
    }
    if broken.is_empty() {
        println!("\nevery fault kept the healthy drives within 10 % of the fault-free poll rate");
    } else {
        println!("\nBOUND BROKEN:\n  {}", broken.join("\n  "));
        std::process::exit(1);
    }
}
