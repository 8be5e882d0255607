//! The trends' cost, on the pure store (`src/history/store.rs`) with the
//! default `[history]` (60 minutes, 60 s at full rate): the time to keep
//! one status (what each poll costs the history's task), the time to
//! answer an hour's query whole and merged for a chart, and the memory of
//! one drive's full history against its stated bound.
//!
//! `cargo bench --bench history`; `DRIVEGATE_BENCH_RATE` sets the statuses
//! per second fed (default 170: one drive alone on a 115200-baud bus, its
//! status-poll limit). Exits 1 if the memory is over the bound or a status
//! costs more than 10 us (a bus polls at most 171 statuses a second).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use drivegate::config::HistoryConfig;
use drivegate::drive::Status;
use drivegate::history::store::DriveHistory;

fn main() {
    let rate: i64 = std::env::var("DRIVEGATE_BENCH_RATE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(170);
    let limits = HistoryConfig::default().settings().limits();
    let mut h = DriveHistory::new(limits);
    let start_ms = 1_790_000_000_000_i64;
    // 65 minutes: the window full, and five minutes of it replaced.
    let n = 65 * 60 * rate;
    let began = Instant::now();
    for i in 0..n {
        let status = Status {
            speed_rpm: (i % 2000) as i16 - 1000,
            current_counts: (i % 256) as i16,
            voltage_v: 24,
            temperature_c: 40 + (i / 60_000) as i16,
            angle_centideg: ((i * 37) % 36_000 - 18_000) as i16,
            flags: 0xC8,
            turns: (i / 100) as u16,
        };
        h.push(start_ms + i * 1000 / rate, status);
    }
    let push_ns = began.elapsed().as_nanos() as f64 / n as f64;
    let now = start_ms + (n - 1) * 1000 / rate;

    let time = |max_points: usize| {
        let rounds = 20;
        let began = Instant::now();
        let mut points = 0;
        for _ in 0..rounds {
            points = h.query(i64::MIN, i64::MAX, now, max_points).len();
        }
        (
            points,
            began.elapsed().as_secs_f64() * 1000.0 / rounds as f64,
        )
    };
    let (whole, whole_ms) = time(usize::MAX);
    let (merged, merged_ms) = time(1000);
    let bytes = h.bytes();
    let bound = limits.bytes_per_drive();

    println!(
        "history of one drive, [history] minutes = 60, full_rate_s = 60, fed {rate} statuses/s for 65 min"
    );
    println!("  keeping a status:            {push_ns:.0} ns");
    println!("  an hour's query, whole:      {whole} points in {whole_ms:.2} ms");
    println!("  an hour's query, 1000 points: {merged} points in {merged_ms:.2} ms");
    println!(
        "  memory: {bytes} bytes (bound {bound} bytes: {} samples x 24 + {} buckets x 48)",
        limits.full_rate_samples, limits.buckets
    );
    let mut ok = true;
    if bytes > bound {
        println!("MISSED: memory over its bound");
        ok = false;
    }
    if push_ns > 10_000.0 {
        println!("MISSED: a status costs more than 10 us");
        ok = false;
    }
    if !ok {
        std::process::exit(1);
    }
}
