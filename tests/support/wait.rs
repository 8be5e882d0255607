//! Bounds on a test's waits: a test waits for an event, never for a fixed
//! time, and every wait has a limit so a lost event fails the test instead
//! of hanging the suite.

use std::future::Future;
use std::time::{Duration, Instant};

/// Runs `test` and returns its output, or fails the test when it has not
/// finished within `limit`. Every end-to-end test runs inside one, so that
/// a lost reply or a stuck task names itself instead of hanging the run.
pub async fn bounded<F: Future>(limit: Duration, test: F) -> F::Output {
    tokio::time::timeout(limit, test)
        .await
        .unwrap_or_else(|_| panic!("the test did not finish within {limit:?}"))
}

/// Polls `f` every 10 ms until it returns `Some`, or panics after `limit`.
pub async fn eventually<T>(limit: Duration, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(
            start.elapsed() < limit,
            "timed out after {limit:?} waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}
