//! A simulator that the machine keeps from running: a reply it could only
//! send after the master gave up is not sent, so it never crosses the
//! master's next request (no gap violation, no stray bytes, no reply taken
//! for another request's); the master retries and nothing fails.

use std::time::Duration;

use crate::support::{FOUR_DRIVES, TestDaemon, eventually};

const LIMIT: Duration = Duration::from_secs(60);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reply_later_than_the_master_waits_is_not_sent() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let bus = d.plant.buses()[0].handle.clone();
        let sim = d.sim();
        let before = (sim.stats(), bus.stats());
        // The polls go on: one arrives while the simulator is held for
        // twice the response timeout (250 ms).
        let requests = before.0.requests;
        tokio::task::block_in_place(|| sim.stall(Duration::from_millis(500)));
        // The master timed out, retried, and goes on polling.
        eventually(Duration::from_secs(20), "polls after the stall", || {
            (sim.stats().requests >= requests + 20).then_some(())
        })
        .await;
        let after = (sim.stats(), bus.stats());
        assert!(after.0.stalled > before.0.stalled, "{}", after.0);
        assert_eq!(
            after.0.gap_violations, before.0.gap_violations,
            "{}",
            after.0
        );
        assert_eq!(after.1.stray_bytes, before.1.stray_bytes, "{:?}", after.1);
        assert!(after.1.retries > before.1.retries, "{:?}", after.1);
        // The retry made good: no transaction failed.
        let failed = |s: &drivegate::bus::stats::BusStatsSnapshot| {
            s.transactions
                .iter()
                .filter(|((_, outcome), _)| *outcome != drivegate::bus::stats::Outcome::Ok)
                .map(|(_, n)| n)
                .sum::<u64>()
        };
        assert_eq!(failed(&after.1), failed(&before.1), "{:?}", after.1);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
