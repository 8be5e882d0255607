//! The silence between frames in `/metrics`: measured for every request
//! that was waiting when the line became free, never shorter than t3.5.

use std::time::Duration;

use crate::support::metrics::exported;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_silence_between_frames_is_exported_and_never_below_t3_5() {
    // Polling as fast as the bus allows: every poll is waiting when the
    // line becomes free.
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let count = "drivegate_bus_interframe_idle_seconds_count{bus=\"sim\"}";
    eventually(Duration::from_secs(10), "100 silences measured", || {
        (exported(&d.metrics.render(), count) >= 100.0).then_some(())
    })
    .await;
    let text = d.metrics.render();
    let n = exported(&text, count);
    let sum = exported(
        &text,
        "drivegate_bus_interframe_idle_seconds_sum{bus=\"sim\"}",
    );
    // t3.5 at 115200 baud is 1.75 ms: no silence is shorter, so the mean
    // is not either, and the buckets below it are empty.
    assert!(sum / n >= 0.00175, "mean {}", sum / n);
    for below in ["0.001", "0.0015"] {
        let bucket =
            format!("drivegate_bus_interframe_idle_seconds_bucket{{bus=\"sim\",le=\"{below}\"}}");
        assert_eq!(exported(&text, &bucket), 0.0, "{bucket}");
    }
    let all = "drivegate_bus_interframe_idle_seconds_bucket{bus=\"sim\",le=\"+Inf\"}";
    assert_eq!(exported(&text, all), n);
    assert_eq!(d.sim().stats().gap_violations, 0);
    d.stop().await;
}
