//! The soak in CI size: two simulated buses of eight drives in one daemon,
//! HTTP, WebSocket and Modbus TCP clients busy and reconnecting every
//! second, a metrics scraper, 1 % of each wire fault, for a few seconds.
//! Functional checks: every answer correct (or a failure the daemon
//! promises for a wire fault), every client kind served, no file
//! descriptor or task left once the clients have gone, the buses still
//! polling at the end. The long run with its memory and rate figures is
//! `cargo bench --bench soak` (see docs/reliability.md).
//!
//! It runs alone in a process of its own (`support::alone`): the file
//! descriptor and memory figures are the process's.

#![allow(clippy::unwrap_used, clippy::expect_used)]

// The soak itself, shared with `benches/soak.rs` (the long run).
#[allow(clippy::module_inception)]
mod soak;

use std::time::Duration;

use crate::support::alone;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_short_soak_leaks_nothing_and_answers_every_client_correctly() {
    let name = "a_short_soak_leaks_nothing_and_answers_every_client_correctly";
    if !alone::here(module_path!(), name) {
        return;
    }
    let plan = soak::Plan {
        buses: 2,
        // Bound by time: about 6 s.
        transactions: u64::MAX,
        max_duration: Duration::from_secs(6),
        http_clients: 2,
        ws_clients: 2,
        tcp_clients: 2,
        reconnect_every: Duration::from_secs(1),
        pace: Duration::from_millis(20),
        fault_rate: 0.01,
        sample_every: Duration::from_millis(100),
        progress_every: None,
    };
    let report = tokio::time::timeout(Duration::from_secs(50), soak::run(plan))
        .await
        .expect("the soak ends in time");
    report.print();
    // Loose bounds for a few seconds of a debug build: the memory check
    // only catches a runaway, and the buses need only still be polling at
    // the end (in thirds of two seconds a few faults, 200 ms each, swing
    // the rate). The long run holds memory to 5 % and the rate to 10 %.
    let broken = report.broken(&soak::Bounds {
        memory_growth: 0.5,
        memory_slack_kib: 4096,
        poll_rate_kept: 0.0,
    });
    assert!(broken.is_empty(), "{broken:#?}");
    // Faults were injected, and clients reconnected several times.
    assert!(
        report.injected.values().sum::<u64>() > 0,
        "{:?}",
        report.injected
    );
    assert!(report.retries > 0);
    use std::sync::atomic::Ordering::Relaxed;
    for kind in [
        &report.clients.http,
        &report.clients.ws,
        &report.clients.tcp,
    ] {
        assert!(kind.connections.load(Relaxed) >= 4, "{kind:?}");
    }
}
