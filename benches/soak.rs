//! The soak: a million bus transactions (by default) on eight simulated
//! buses of eight drives at 115200 baud in one daemon, with HTTP,
//! WebSocket and Modbus TCP clients all busy and reconnecting, a metrics
//! scraper, and 0.25 % of each wire fault (dropped, corrupted, late, noise)
//! on every bus. Eight buses because each is its own wire: one bus at
//! 115200 baud carries about 170 status polls a second, so a million
//! transactions on one would take over an hour and a half; eight carry
//! them in about a quarter of an hour.
//!
//! It prints the figures and exits with status 1 if a bound breaks: a
//! wrong or missing answer; a file descriptor or task still open after the
//! clients left; the last third's highest resident memory more than 5 %
//! above the first third's (after a tenth of the run to warm up); the last
//! third's poll rate more than 10 % below the first third's; a gap
//! violation.
//!
//! `cargo bench --bench soak`; environment:
//! `DRIVEGATE_SOAK_TRANSACTIONS` (default 1000000),
//! `DRIVEGATE_SOAK_BUSES` (8), `DRIVEGATE_SOAK_MINUTES` (at most, 60),
//! `DRIVEGATE_SOAK_FAULT_RATE` (each fault, 0.0025).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

#[path = "../tests/soak/soak.rs"]
mod soak;

use std::time::Duration;

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let plan = soak::Plan {
        buses: env("DRIVEGATE_SOAK_BUSES", 8),
        transactions: env("DRIVEGATE_SOAK_TRANSACTIONS", 1_000_000),
        max_duration: Duration::from_secs(60 * env("DRIVEGATE_SOAK_MINUTES", 60)),
        http_clients: 4,
        ws_clients: 4,
        tcp_clients: 4,
        reconnect_every: Duration::from_secs(10),
        pace: Duration::from_millis(20),
        fault_rate: env("DRIVEGATE_SOAK_FAULT_RATE", 0.0025),
        sample_every: Duration::from_secs(1),
        progress_every: Some(Duration::from_secs(60)),
    };
    println!(
        "soak: until {} transactions or {:?}, {} buses",
        plan.transactions, plan.max_duration, plan.buses
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let report = runtime.block_on(soak::run(plan));
    report.print();
    let broken = report.broken(&soak::Bounds {
        memory_growth: 0.05,
        memory_slack_kib: 0,
        poll_rate_kept: 0.90,
    });
    if broken.is_empty() {
        println!(
            "the soak held: every answer correct, nothing leaked, memory flat, poll rate kept"
        );
    } else {
        println!("SOAK BROKEN:\n  {}", broken.join("\n  "));
        std::process::exit(1);
    }
}
