//! Wire faults through the real pty, eight simulated drives, each fault on
//! its own at 5 % of the replies: corrupted CRCs, dropped replies, replies
//! later than the response timeout (inside the guard time), and noise bytes
//! after replies. For each, while every drive takes unique writes and reads
//! them back and the daemon polls them all:
//! - no reply reaches the wrong request (every read carries the simulator's
//!   value for that drive and register),
//! - every accepted write is confirmed (and true in the simulator) or
//!   reported failed,
//! - every drive keeps being polled,
//! - `/metrics` accounts for every injected fault, exactly where the RTU
//!   model allows and with the honest bound where it does not.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;
mod faults_support;

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use common::TestDaemon;
use drivegate::sim::{FaultRates, SimStats};
use faults_support::{
    Allowed, Injected, PollCounter, Tally, Truth, UNITS, Wire, assert_polled, eight_drives,
    stop_and_scrape, traffic_on,
};
use tokio_util::sync::CancellationToken;

/// Every test ends within this, whatever happens.
const LIMIT: Duration = Duration::from_secs(45);
/// Write/read-back rounds per drive.
const ROUNDS: u32 = 24;
const BUS: &str = "line";
/// The shortest and longest reply frames of the traffic: a one-register
/// read (7 bytes) and the status block (19 bytes).
const SHORTEST_REPLY: u64 = 7;
const LONGEST_REPLY: u64 = 19;

async fn bounded(test: impl Future<Output = ()>) {
    tokio::time::timeout(LIMIT, test)
        .await
        .expect("test did not finish in time");
}

/// What one fault run left behind.
struct Run {
    tally: Tally,
    wire: Wire,
    sim: SimStats,
}

impl Run {
    /// Transactions that failed on their last attempt, client jobs and polls:
    /// the failures someone was told about.
    fn reported_failures(&self) -> u64 {
        self.tally.writes_failed + self.tally.reads_failed + self.wire.poll_failures
    }
}

/// Starts the daemon with `bus_keys`, turns `rates` on, runs the checked
/// workload on all eight drives, stops, and checks what holds for every
/// wire fault.
async fn run(bus_keys: &str, rates: FaultRates, allowed: Allowed) -> Run {
    let d = TestDaemon::start(&eight_drives("sim", bus_keys, "")).await;
    let bus = d.plant.buses()[0].handle.clone();
    let truth = Arc::new(Truth::of_plant(d.plant.clone()));
    let polls = PollCounter::start(&bus);
    d.sim().set_fault_rates(rates).unwrap();
    let (tally, _) = traffic_on(
        &bus,
        &truth,
        UNITS,
        ROUNDS,
        allowed,
        &CancellationToken::new(),
    )
    .await;
    let polls = polls.finish().await;
    let (scrape, plant) = stop_and_scrape(d).await;
    let sim = plant.buses()[0].sim.as_ref().unwrap().stats();
    let wire = Wire::of(&scrape, BUS);
    let injected = Injected::of(&scrape, BUS);
    eprintln!("{tally:?}\n{wire:?}\n{sim}\npolls {polls:?}");

    // The simulator's counters in /metrics are the simulator's.
    assert_eq!(
        injected,
        Injected {
            requests: sim.requests,
            dropped: sim.dropped,
            corrupted: sim.corrupted,
            late: sim.late,
            noise: sim.noise_bursts,
            gap_violations: sim.gap_violations,
        }
    );
    // Every frame the master sent reached the drives intact: each
    // transaction once plus its retries. Nothing was sent twice or lost.
    assert_eq!(sim.requests, wire.attempts(), "{wire:?} {sim}");
    assert_eq!(sim.bad_crc_requests + sim.truncated_frames, 0, "{sim}");
    // Whatever the line did, the master kept the silence before each frame.
    assert_eq!(sim.gap_violations, 0);
    // No port trouble, nothing dropped unsent, no exception.
    assert_eq!(
        (
            wire.port_error,
            wire.dropped,
            wire.exception,
            wire.port_errors
        ),
        (0, 0, 0, 0)
    );
    tally.assert_nothing_lost();
    assert_eq!(tally.writes_refused + tally.reads_refused, 0, "{tally:?}");
    // Most writes went through; each failure was reported.
    assert!(
        tally.writes_confirmed * 10 >= tally.writes_accepted * 8,
        "{tally:?}"
    );
    assert_polled(&polls, UNITS, 4);
    Run { tally, wire, sim }
}

fn failures_of(tally: &Tally, kind: &str) -> u64 {
    tally.failures.get(kind).copied().unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupted_replies_are_retried_or_reported_and_each_is_counted() {
    bounded(async {
        // A long timeout: no reply can be late here, so every failed attempt
        // is a corrupted reply. The whole corrupted frame arrives, so a short
        // guard suffices.
        let r = run(
            "response_timeout_ms = 200\nguard_ms = 10",
            FaultRates {
                crc_error_rate: 0.05,
                ..FaultRates::default()
            },
            &["bad_reply"],
        )
        .await;
        assert!(r.sim.corrupted >= 5, "{}", r.sim);
        assert_eq!(r.sim.dropped + r.sim.late + r.sim.noise_bursts, 0);
        // Exact: each corrupted reply ends one attempt with a CRC error,
        // which is either retried or, on the last attempt, the outcome.
        assert_eq!(r.wire.retries + r.wire.crc_error, r.sim.corrupted);
        // Every crc_error outcome was reported to its client or counted as a
        // failed poll; nothing else failed.
        assert_eq!(r.wire.crc_error, r.reported_failures());
        assert_eq!(
            failures_of(&r.tally, "bad_reply"),
            r.tally.writes_failed + r.tally.reads_failed
        );
        assert_eq!(
            (r.wire.timeout, r.wire.bad_reply, r.wire.stray_bytes),
            (0, 0, 0)
        );
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropped_replies_time_out_and_each_is_counted() {
    bounded(async {
        // A timeout twice the default: a reply delayed by the machine's
        // scheduling cannot pass for a dropped one.
        let r = run(
            "response_timeout_ms = 100\nguard_ms = 20",
            FaultRates {
                drop_rate: 0.05,
                ..FaultRates::default()
            },
            &["timeout"],
        )
        .await;
        assert!(r.sim.dropped >= 5, "{}", r.sim);
        assert_eq!(r.sim.corrupted + r.sim.late + r.sim.noise_bursts, 0);
        // Exact: each dropped reply is one attempt that timed out.
        assert_eq!(r.wire.retries + r.wire.timeout, r.sim.dropped);
        assert_eq!(r.wire.timeout, r.reported_failures());
        assert_eq!(
            (r.wire.crc_error, r.wire.bad_reply, r.wire.stray_bytes),
            (0, 0, 0)
        );
        assert_eq!(r.sim.unanswered, 0, "every drive heard every request");
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_replies_fall_in_the_guard_and_never_answer_the_next_request() {
    bounded(async {
        // A reply 120 ms late misses the 60 ms timeout and arrives inside the
        // 150 ms guard that follows it (the promise: a reply later than
        // timeout + guard cannot be told from an answer on RTU).
        let r = run(
            "response_timeout_ms = 60\nguard_ms = 150",
            FaultRates {
                late_rate: 0.05,
                late_ms: 120.0,
                ..FaultRates::default()
            },
            &["timeout"],
        )
        .await;
        assert!(r.sim.late >= 5, "{}", r.sim);
        assert_eq!(r.sim.corrupted + r.sim.dropped + r.sim.noise_bursts, 0);
        // Exact: each late reply is one attempt that timed out.
        assert_eq!(r.wire.retries + r.wire.timeout, r.sim.late);
        assert_eq!(r.wire.timeout, r.reported_failures());
        assert_eq!((r.wire.crc_error, r.wire.bad_reply), (0, 0));
        // Each late reply was discarded, whole, as stray bytes. Which
        // requests were late is the simulator's secret, so the byte count is
        // bounded by the shortest and longest reply of the traffic.
        assert!(
            (SHORTEST_REPLY * r.sim.late..=LONGEST_REPLY * r.sim.late)
                .contains(&r.wire.stray_bytes),
            "{} stray bytes for {} late replies",
            r.wire.stray_bytes,
            r.sim.late
        );
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn noise_between_frames_is_discarded_or_spoils_one_attempt() {
    bounded(async {
        // A long timeout: no reply can be late here, so a failed attempt
        // is the noise's doing.
        let r = run(
            "response_timeout_ms = 200\nguard_ms = 50",
            FaultRates {
                noise_rate: 0.05,
                ..FaultRates::default()
            },
            &["bad_reply"],
        )
        .await;
        let noise = r.sim.noise_bursts;
        assert!(noise >= 5, "{}", r.sim);
        assert_eq!(r.sim.corrupted + r.sim.dropped + r.sim.late, 0);
        // Noise follows a reply by t3.5, when the master may already be
        // waiting for the next reply. A burst is then either discarded
        // before the next request (stray bytes) or read in front of the next
        // reply, which spoils that one attempt (a bad frame, retried or
        // reported). Which one happens is a race of microseconds, so the
        // accounting is two bounds: no attempt fails without a burst, and
        // every burst shows as stray bytes or a failed attempt (the last
        // reply's burst may come after the bus stopped: + 1).
        let failed = r.wire.failed_attempts();
        assert!(failed <= noise, "{failed} failed attempts, {noise} bursts");
        assert!(
            noise <= r.wire.stray_bytes + failed + 1,
            "{noise} bursts, {} stray bytes, {failed} failed attempts",
            r.wire.stray_bytes
        );
        // A burst is 1 to 4 bytes; a spoiled attempt's reply is discarded too.
        assert!(r.wire.stray_bytes <= 4 * noise + LONGEST_REPLY * failed);
        // Noise never silences a drive.
        assert_eq!(r.wire.timeout, 0);
        assert_eq!(r.wire.crc_error + r.wire.bad_reply, r.reported_failures());
    })
    .await;
}

/// The control: without faults every write is confirmed, every read
/// answered, and no attempt fails, so the failures above are the faults'.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_faults_everything_is_confirmed() {
    bounded(async {
        let r = run("response_timeout_ms = 50", FaultRates::default(), &[]).await;
        let t = &r.tally;
        assert_eq!(t.writes_confirmed, u64::from(ROUNDS) * 8);
        assert_eq!(t.reads_answered, u64::from(ROUNDS) * 8);
        assert_eq!(r.wire.failed_attempts(), 0);
        assert_eq!(r.wire.stray_bytes, 0);
    })
    .await;
}
