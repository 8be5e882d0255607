//! The trends through the API on the simulator: the history of a turning
//! drive, with the fields asked for, the recent seconds at the poll rate
//! and older ones in one-second buckets, merged down to `max_points`, and
//! the memory it takes within its stated bound. (An hour of it is the
//! store's unit test, fed directly: `src/history/store.rs`.)

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::support::TestDaemon;
use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::metrics::metric;
use crate::support::wait::bounded;

const LIMIT: Duration = Duration::from_secs(60);
const EVENT: Duration = Duration::from_secs(20);

/// Asks `path` until `want` holds for the answer.
async fn until(api: &Api, path: &str, what: &str, want: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let v = api.get(path).await.expect(200);
        if want(&v) {
            return v;
        }
        assert!(start.elapsed() < EVENT, "no {what} within {EVENT:?}: {v:#}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_history_of_a_turning_drive_is_served_as_asked_within_its_bound() {
    bounded(LIMIT, async {
        // One second at full rate, so buckets come within seconds.
        let toml = ConfigBuilder::four_drives()
            .section("history", "minutes = 2\nfull_rate_s = 1")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        api.activate_in("lift", "speed").await;
        api.put("/api/v1/drives/lift/setpoint", json!({"speed_rpm": 100}))
            .await
            .expect(200);

        let path = "/api/v1/drives/lift/history?fields=speed_rpm,current_a";
        let h = until(&api, path, "buckets and samples of the lift turning", |h| {
            let spans = h["span_ms"].as_array().unwrap();
            let turning = h["fields"]["speed_rpm"]["max"]
                .as_array()
                .unwrap()
                .iter()
                .any(|v| v.as_f64().unwrap() > 50.0);
            turning
                && spans.iter().any(|s| s == 1000)
                && spans.iter().filter(|s| **s == 0).count() >= 10
        })
        .await;
        assert_eq!((h["drive"].as_str(), h["unit"].as_u64()), (Some("lift"), Some(2)));
        assert_eq!((h["minutes"].as_u64(), h["full_rate_s"].as_u64()), (Some(2), Some(1)));
        // Only the fields asked for, each column as long as the times.
        let fields: Vec<&String> = h["fields"].as_object().unwrap().keys().collect();
        assert_eq!(fields, ["current_a", "speed_rpm"]);
        let n = h["t_ms"].as_array().unwrap().len();
        for key in ["span_ms", "samples", "flags_any"] {
            assert_eq!(h[key].as_array().unwrap().len(), n, "{key}");
        }
        for field in ["speed_rpm", "current_a"] {
            for column in ["min", "max", "mean"] {
                assert_eq!(h["fields"][field][column].as_array().unwrap().len(), n);
            }
        }
        // Oldest first; buckets before the samples at full rate; a bucket
        // holds several reads, its min <= mean <= max.
        let t: Vec<i64> = h["t_ms"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect();
        assert!(t.windows(2).all(|w| w[0] <= w[1]), "{t:?}");
        let spans: Vec<i64> = h["span_ms"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect();
        let first_sample = spans.iter().position(|s| *s == 0).unwrap();
        assert!(spans[first_sample..].iter().all(|s| *s == 0));
        let speed = &h["fields"]["speed_rpm"];
        for i in 0..first_sample {
            let (lo, mean, hi) = (
                speed["min"][i].as_f64().unwrap(),
                speed["mean"][i].as_f64().unwrap(),
                speed["max"][i].as_f64().unwrap(),
            );
            assert!(lo <= mean && mean <= hi, "point {i}: {lo} {mean} {hi}");
            assert!(h["samples"][i].as_u64().unwrap() >= 1);
        }

        // Merged down to at most 5 points, every read still counted.
        let all_reads: u64 = h["samples"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).sum();
        let since = t[0];
        let until_ms = t[n - 1];
        let merged = api
            .get(&format!(
                "/api/v1/drives/lift/history?fields=voltage_v&since={since}&until={until_ms}&max_points=5"
            ))
            .await
            .expect(200);
        let m = merged["t_ms"].as_array().unwrap().len();
        assert!((1..=5).contains(&m), "{merged:#}");
        let merged_reads: u64 = merged["samples"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).sum();
        assert!(merged_reads >= all_reads, "{merged_reads} < {all_reads}");
        assert!(merged["fields"]["voltage_v"]["min"][0].as_f64().unwrap() > 0.0);

        // Refused with words: an unknown field, an empty range, max_points.
        let p = api
            .get("/api/v1/drives/lift/history?fields=rpm")
            .await
            .expect_problem(400, "invalid-request");
        assert!(p["detail"].as_str().unwrap().contains("speed_rpm"), "{p:#}");
        api.get("/api/v1/drives/lift/history?since=2026-11-25T02:00:00Z&until=2026-11-25T01:00:00Z")
            .await
            .expect_problem(400, "invalid-request");
        api.get("/api/v1/drives/lift/history?max_points=0")
            .await
            .expect_problem(422, "out-of-range");
        api.get("/api/v1/drives/nowhere/history")
            .await
            .expect_problem(404, "unknown-drive");

        // The memory taken, within the stated bound of each drive.
        let text = d.metrics.render();
        let bytes = metric(&text, "drivegate_history_bytes ");
        let limit = metric(&text, "drivegate_history_drive_limit_bytes ");
        let drives = metric(&text, "drivegate_history_drives ");
        assert_eq!(limit, (100 * 24 + 120 * 48) as f64);
        assert_eq!(drives, 4.0);
        assert!(bytes > 0.0 && bytes <= drives * limit, "{bytes} of {drives} x {limit}");
        d.stop().await;
    })
    .await;
}
