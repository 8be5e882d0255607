//! The scope's rate and the bus monitor's cost, as shares of the wire's
//! physical limit, on the simulator (wire-timed, 115200 baud, no faults,
//! 0 turnaround unless `DRIVEGATE_BENCH_TURNAROUND_MS` says otherwise).
//!
//! - Scope: samples per second of a capture of 1 drive and of 4 drives,
//!   alone on their bus and among 8 drives (the others at `[scope]
//!   floor_rate_hz`, 10 by default), against the status-poll limit (one
//!   read = 8 + 19 bytes on the wire + 2 x t3.5 = 5.844 ms: 171.1/s); the
//!   floor rate the other drives kept.
//! - Monitor: status polls per second of 4 drives with `[monitor]` off, on
//!   with no client, and on with two live WebSocket clients, and the CPU
//!   time of the bus thread in each case.
//! - Memory: a full ring of `[monitor] ring_frames` (default 10000) and the
//!   largest capture (`[scope] max_samples`, default 200000).
//!
//! `cargo bench --bench scope`; `DRIVEGATE_BENCH_SECS` sets each window
//! (default 5), `DRIVEGATE_BENCH_ROUNDS` the interleaved rounds of the
//! monitor's measurement (default 3, the median is shown),
//! `DRIVEGATE_BENCH_PAIRS` the alternating windows without and with live
//! clients (default 5), `DRIVEGATE_BENCH_PARTS` which parts run (default
//! `scope,monitor,tap`), `DRIVEGATE_BENCH_VERBOSE` each window's figures. Exits 1 if a goal is missed: scope >= 95 % of the limit
//! for a drive alone on its bus, bus rate with the monitor and two
//! clients >= 99 % of the rate with it off.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use drivegate::bus::Origin;
use drivegate::bus::master::Fault;
use drivegate::bus::tap::WireTap;
use drivegate::config::{Config, MonitorConfig, ScopeConfig};
use drivegate::daemon::supervisor;
use drivegate::drive::StatusField;
use drivegate::metrics::Metrics;
use drivegate::modbus::rtu_frame::encode;
use drivegate::modbus::timing::LineTiming;
use drivegate::monitor::record::Direction;
use drivegate::monitor::{BusMonitor, MonitorSettings};
use drivegate::plant::Plant;
use drivegate::scope::field::RECORDED;
use drivegate::scope::spec::{Amount, CaptureSpec};
use drivegate::scope::trigger::Trigger;
use drivegate::scope::{Scope, ScopeSettings};
use futures_util::StreamExt;
use tokio_util::sync::CancellationToken;

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn config(drives: u8, monitor: bool, turnaround_ms: f64) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
         [monitor]\nenabled = {monitor}\n\
         [[bus]]\nname = \"bench\"\nport = \"sim\"\nbaud = 115200\n\
         [bus.sim]\nturnaround_ms = {turnaround_ms}\nseed = 3\n"
    );
    for unit in 1..=drives {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\ngear_ratio = 3.75\n"
        ));
    }
    toml
}

async fn start(toml: &str) -> Arc<Plant> {
    let config = Config::parse(toml, "bench").unwrap();
    let plant = Arc::new(Plant::start(&config).unwrap());
    let t = Instant::now();
    while !plant.buses()[0]
        .handle
        .drives()
        .iter()
        .all(|d| d.status.is_some())
    {
        assert!(t.elapsed() < Duration::from_secs(10), "drives offline");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    plant
}

/// CPU seconds the bus thread has used (from /proc, 10 ms ticks).
fn bus_thread_cpu() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return f64::NAN;
    };
    for task in tasks.flatten() {
        let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        if comm.trim() == "bus-bench" {
            let stat = std::fs::read_to_string(task.path().join("stat")).unwrap_or_default();
            // Fields after the command's closing parenthesis: utime is the
            // 12th, stime the 13th.
            let rest = stat.rsplit(')').next().unwrap_or("");
            let f: Vec<&str> = rest.split_whitespace().collect();
            let ticks: f64 = f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap();
            return ticks / 100.0;
        }
    }
    f64::NAN
}

struct ScopeRun {
    captured: u8,
    drives: u8,
    /// Status polls per second of the same bus just before the capture.
    before_per_s: f64,
    /// Samples per second, all captured drives.
    samples_per_s: f64,
    /// Polls per second each other drive kept (min, max).
    others: Option<(f64, f64)>,
}

async fn scope_run(drives: u8, captured: u8, secs: f64, turnaround: f64) -> ScopeRun {
    let plant = start(&config(drives, true, turnaround)).await;
    let bus = plant.buses()[0].handle.clone();
    let first = plant.buses()[0].clone();
    let (scope, monitor) = (first.scope(), first.monitor());
    // The same bus's plain polling, just before: the machine's pace now.
    let (p0, t0) = (bus.stats().polls, Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(secs.min(3.0))).await;
    let before_per_s = (bus.stats().polls - p0) as f64 / t0.elapsed().as_secs_f64();
    let units: Vec<u8> = (1..=captured).collect();
    let spec = CaptureSpec {
        units: units.clone(),
        fields: vec![StatusField::SpeedRpm],
        trigger: Trigger::Immediate,
        pre_trigger: Amount::Samples(0),
        length: Amount::Seconds(secs),
        wait: Duration::from_secs(10),
    };
    scope.arm(spec, Instant::now()).unwrap();
    bus.wake();
    while scope.is_running() {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let (count, first, last) = scope
        .with_capture(|c| {
            let samples: Vec<_> = c.samples().collect();
            (
                samples.len(),
                samples.first().map(|s| s.at),
                samples.last().map(|s| s.at),
            )
        })
        .unwrap();
    let span = (last.unwrap() - first.unwrap()).as_secs_f64();
    let samples_per_s = (count - 1) as f64 / span;
    // The other drives' polls in the capture's time, from the monitor.
    let from = monitor.ns_since_start(first.unwrap());
    let to = monitor.ns_since_start(last.unwrap());
    let frames = monitor.last(monitor.capacity());
    let others = (captured < drives).then(|| {
        let rates: Vec<f64> = (captured + 1..=drives)
            .map(|u| {
                let n = frames
                    .iter()
                    .filter(|r| {
                        r.direction == Direction::Request
                            && r.unit == u
                            && r.origin == Origin::Poller
                            && r.at_ns >= from
                            && r.at_ns < to
                    })
                    .count();
                n as f64 / span
            })
            .collect();
        (
            rates.iter().copied().fold(f64::MAX, f64::min),
            rates.iter().copied().fold(0.0, f64::max),
        )
    });
    drivegate::control::shutdown(&plant, drivegate::control::stop_action::StopAction::None).await;
    ScopeRun {
        captured,
        drives,
        before_per_s,
        samples_per_s,
        others,
    }
}

struct BusRun {
    polls_per_s: f64,
    cpu_share: f64,
    frames_to_clients: u64,
    lost: u64,
}

async fn bus_run(monitor: bool, with_clients: bool, secs: f64, turnaround: f64) -> BusRun {
    let toml = config(4, monitor, turnaround);
    let config = Config::parse(&toml, "bench").unwrap();
    let plant = start(&toml).await;
    let metrics = Metrics::new(plant.clone());
    let shutdown = CancellationToken::new();
    let faces = supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
        .await
        .unwrap();
    let received = Arc::new(AtomicU64::new(0));
    let lost = Arc::new(AtomicU64::new(0));
    let readers = if with_clients {
        clients(faces.http, &received, &lost).await
    } else {
        Vec::new()
    };
    tokio::time::sleep(Duration::from_millis(500)).await;
    let bus = plant.buses()[0].handle.clone();
    let (polls0, cpu0, t0, got0) = (
        bus.stats().polls,
        bus_thread_cpu(),
        Instant::now(),
        received.load(Ordering::Relaxed),
    );
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    let (polls1, cpu1, t1, got1) = (
        bus.stats().polls,
        bus_thread_cpu(),
        Instant::now(),
        received.load(Ordering::Relaxed),
    );
    let elapsed = (t1 - t0).as_secs_f64();
    shutdown.cancel();
    for r in readers {
        r.abort();
    }
    let _ = tokio::time::timeout(Duration::from_secs(5), faces.wait()).await;
    drivegate::control::shutdown(&plant, drivegate::control::stop_action::StopAction::None).await;
    BusRun {
        polls_per_s: (polls1 - polls0) as f64 / elapsed,
        cpu_share: (cpu1 - cpu0) / elapsed,
        frames_to_clients: got1 - got0,
        lost: lost.load(Ordering::Relaxed),
    }
}

/// Two live clients reading every frame.
async fn clients(
    http: std::net::SocketAddr,
    received: &Arc<AtomicU64>,
    lost: &Arc<AtomicU64>,
) -> Vec<tokio::task::JoinHandle<()>> {
    let mut readers = Vec::new();
    for _ in 0..2 {
        let url = format!("ws://{http}/api/v1/buses/bench/monitor/live?backlog=0");
        let (mut ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
        let (received, lost) = (received.clone(), lost.clone());
        readers.push(tokio::spawn(async move {
            // Light readers, so that what is measured is the daemon's side:
            // frames counted by their "seq", "lost" read where it stands.
            while let Some(Ok(m)) = ws.next().await {
                if let Ok(text) = m.into_text()
                    && text.starts_with("{\"type\":\"frames\"")
                {
                    let text = text.as_str();
                    received.fetch_add(text.matches("\"seq\":").count() as u64, Ordering::Relaxed);
                    let n = text
                        .split("\"lost\":")
                        .nth(1)
                        .and_then(|t| t.split(',').next())
                        .and_then(|n| n.parse::<u64>().ok())
                        .unwrap_or(0);
                    lost.fetch_add(n, Ordering::Relaxed);
                }
            }
        }));
    }
    readers
}

/// The same bus, monitor on, in alternating windows without and with two
/// live clients: what the clients cost the bus, with the machine's load
/// drifting alike under both. Returns polls/s without, with, and the
/// frames the clients got and lost.
/// Polls of `bus` in the next `window` seconds, and the time taken.
async fn measure(bus: &drivegate::bus::BusHandle, window: f64) -> (u64, f64) {
    let (p0, t0) = (bus.stats().polls, Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(window)).await;
    (bus.stats().polls - p0, t0.elapsed().as_secs_f64())
}

async fn clients_ab(pairs: usize, window: f64, turnaround: f64) -> (f64, f64, u64, u64) {
    let toml = config(4, true, turnaround);
    let config = Config::parse(&toml, "bench").unwrap();
    let plant = start(&toml).await;
    let metrics = Metrics::new(plant.clone());
    let shutdown = CancellationToken::new();
    let faces = supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
        .await
        .unwrap();
    let bus = plant.buses()[0].handle.clone();
    let (received, lost) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let mut totals = [(0u64, 0.0f64); 2];
    for _ in 0..pairs {
        let (n, t) = measure(&bus, window).await;
        totals[0] = (totals[0].0 + n, totals[0].1 + t);
        let readers = clients(faces.http, &received, &lost).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
        let (m, u) = measure(&bus, window).await;
        totals[1] = (totals[1].0 + m, totals[1].1 + u);
        if std::env::var_os("DRIVEGATE_BENCH_VERBOSE").is_some() {
            println!(
                "   without {:.1}/s, with {:.1}/s",
                n as f64 / t,
                m as f64 / u
            );
        }
        for r in readers {
            r.abort();
        }
        while plant.buses()[0].monitor().clients() > 0 {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
    shutdown.cancel();
    let _ = tokio::time::timeout(Duration::from_secs(5), faces.wait()).await;
    drivegate::control::shutdown(&plant, drivegate::control::stop_action::StopAction::None).await;
    (
        totals[0].0 as f64 / totals[0].1,
        totals[1].0 as f64 / totals[1].1,
        received.load(Ordering::Relaxed),
        lost.load(Ordering::Relaxed),
    )
}

/// CPU time of the calling thread.
fn thread_cpu() -> Duration {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map(Duration::from)
        .unwrap_or_default()
}

/// CPU time the bus thread spends in the tap for one status read (its
/// request and reply frames): with the monitor off, on, and on with a
/// capture of the drive running. Thread CPU time, so the machine's load
/// does not count.
fn tap_cost() -> [Duration; 3] {
    const READS: u32 = 200_000;
    let line = LineTiming::new_8n1(115_200);
    let request = encode(1, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
    let mut pdu = vec![0x03, 14];
    pdu.extend_from_slice(&[0x12; 14]);
    let reply = encode(1, &pdu);
    let mut costs = [Duration::ZERO; 3];
    for (i, cost) in costs.iter_mut().enumerate() {
        let monitor = Arc::new(BusMonitor::new(
            MonitorSettings {
                enabled: i > 0,
                ring_frames: 10_000,
            },
            line,
            vec![1, 2, 3, 4],
        ));
        let scope = Arc::new(Scope::new(
            ScopeSettings {
                max_samples: 1_000_000,
                ..ScopeSettings::default()
            },
            line,
            vec![1, 2, 3, 4],
        ));
        if i == 2 {
            let spec = CaptureSpec {
                units: vec![1],
                fields: RECORDED.to_vec(),
                trigger: Trigger::Immediate,
                pre_trigger: Amount::Samples(0),
                length: Amount::Samples(READS + 1),
                wait: Duration::from_secs(10),
            };
            scope.arm(spec, Instant::now()).unwrap();
        }
        let mut tap = WireTap::detached(line);
        tap.attach(vec![monitor, scope.clone()]);
        let start = thread_cpu();
        for _ in 0..READS {
            let now = Instant::now();
            tap.cause(if i == 2 {
                Origin::Scope
            } else {
                Origin::Poller
            });
            tap.request(1, &request, now, 1, Duration::from_micros(1750));
            tap.reply(Some(&reply), now, None::<&Fault>);
            if i == 2 {
                // What the scheduler asks of a running capture per poll.
                let _ = scope.steer(now, |_| true, |_| false);
                scope.polled(1, now);
            }
        }
        *cost = (thread_cpu() - start) / READS;
        if i == 2 {
            assert!(scope.is_running(), "the capture ended early");
        }
    }
    costs
}

fn main() {
    let secs: f64 = env("DRIVEGATE_BENCH_SECS", 5.0);
    let turnaround: f64 = env("DRIVEGATE_BENCH_TURNAROUND_MS", 0.0);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let line = LineTiming::new_8n1(115_200);
    let read = line.transaction_time(8, 19, Duration::from_secs_f64(turnaround / 1000.0));
    let limit = 1.0 / read.as_secs_f64();
    let mut failed = false;
    let parts: String = env("DRIVEGATE_BENCH_PARTS", "scope,monitor,tap".to_string());
    let part = |name: &str| parts.split(',').any(|p| p.trim() == name);
    if part("scope") {
        println!(
            "scope at 115200 baud, turnaround {turnaround} ms: status-read limit {limit:.1}/s ({:.3} ms a read), {secs} s a capture",
            read.as_secs_f64() * 1000.0
        );
        println!(
            "{:>9} {:>7} {:>12} {:>9} {:>26} {:>20}",
            "captured",
            "drives",
            "samples/s",
            "of limit",
            "others' polls/s (min-max)",
            "polls/s before it"
        );
        runtime.block_on(async {
        for (drives, captured) in [(1, 1), (4, 4), (8, 1), (8, 4)] {
            let r = scope_run(drives, captured, secs, turnaround).await;
            let share = r.samples_per_s / limit;
            let others = r
                .others
                .map_or("-".to_string(), |(a, b)| format!("{a:.1} - {b:.1}"));
            println!(
                "{:>9} {:>7} {:>12.1} {:>8.1}% {:>26} {:>13.1} ({:.1}%)",
                r.captured,
                r.drives,
                r.samples_per_s,
                100.0 * share,
                others,
                r.before_per_s,
                100.0 * r.before_per_s / limit
            );
            // The goal is 95 % of the limit; on a loaded machine the bus's
            // own polling may not reach it either, and then the capture
            // must keep the pace the bus had just before it.
            if r.captured == r.drives && share < 0.95 && r.samples_per_s < 0.98 * r.before_per_s {
                println!(
                    "   goal missed: a capture alone on its bus below 95 % of the limit and below the bus's own pace"
                );
                failed = true;
            }
        }
    });
    }

    if part("monitor") {
        println!();
        println!("bus of 4 drives polled at full rate; monitor off, on, on with two live clients");
        println!(
            "{:>30} {:>10} {:>9} {:>10} {:>14} {:>6}",
            "", "polls/s", "of limit", "bus CPU", "frames to clients", "lost"
        );
        let rounds: usize = env("DRIVEGATE_BENCH_ROUNDS", 3);
        runtime.block_on(async {
        // Interleaved rounds, the median of each: the machine's load moves
        // under the bench, the same way for the three.
        let mut runs: [Vec<BusRun>; 3] = Default::default();
        for _ in 0..rounds {
            runs[0].push(bus_run(false, false, secs, turnaround).await);
            runs[1].push(bus_run(true, false, secs, turnaround).await);
            runs[2].push(bus_run(true, true, secs, turnaround).await);
        }
        let median = |runs: &mut Vec<BusRun>| {
            runs.sort_by(|a, b| a.polls_per_s.total_cmp(&b.polls_per_s));
            runs.remove(runs.len() / 2)
        };
        let [off, on, two] = runs.each_mut().map(median);
        for (name, r) in [
            ("monitor off", &off),
            ("monitor on, no client", &on),
            ("monitor on, two live clients", &two),
        ] {
            println!(
                "{:>30} {:>10.1} {:>8.1}% {:>9.1}% {:>14} {:>6}",
                name,
                r.polls_per_s,
                100.0 * r.polls_per_s / limit,
                100.0 * r.cpu_share,
                r.frames_to_clients,
                r.lost
            );
        }
        println!(
            "(separate daemons, medians of {rounds} interleaved rounds: with two clients {:.2} % of the rate with the monitor off)",
            100.0 * two.polls_per_s / off.polls_per_s
        );
        let pairs: usize = env("DRIVEGATE_BENCH_PAIRS", 5);
        let window = (secs / 2.0).max(1.0);
        let (without, with, got, lost) = clients_ab(pairs, window, turnaround).await;
        let ratio = with / without;
        println!(
            "one daemon, monitor on, {pairs} pairs of {window} s windows without / with two live clients: {without:.1} / {with:.1} polls/s; with = {:.2} % of without ({got} frames to the clients, {lost} lost)",
            100.0 * ratio
        );
        if ratio < 0.99 {
            println!("   goal missed: below 99 %");
            failed = true;
        }
    });
    }

    if part("tap") {
        println!();
        let [off, on, capture] = tap_cost();
        let share = |d: Duration| 100.0 * d.as_secs_f64() / read.as_secs_f64();
        println!(
            "bus-thread CPU per status read in the tap (thread CPU time, 200000 reads): monitor off {:.2} us ({:.3} % of a read's {:.3} ms), on {:.2} us ({:.3} %), on with a capture running {:.2} us ({:.3} %)",
            off.as_secs_f64() * 1e6,
            share(off),
            read.as_secs_f64() * 1000.0,
            on.as_secs_f64() * 1e6,
            share(on),
            capture.as_secs_f64() * 1e6,
            share(capture)
        );
    }

    println!();
    let monitor = MonitorConfig::default();
    let scope = ScopeConfig::default();
    println!(
        "memory: a full ring of {} frames {:.2} MB per bus ({} bytes a frame); the largest capture, {} samples, {:.2} MB ({} bytes a sample)",
        monitor.ring_frames,
        monitor.memory_per_bus() as f64 / 1e6,
        monitor.memory_per_bus() / monitor.ring_frames,
        scope.max_samples,
        scope.memory_per_capture() as f64 / 1e6,
        scope.memory_per_capture() / scope.max_samples,
    );
    if failed {
        std::process::exit(1);
    }
}
