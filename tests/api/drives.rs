//! Reading drives over real HTTP against the daemon on the simulator: the
//! list, one drive by name or unit, the status from the cache and fresh from
//! the bus, health, readiness and metrics, and unknown routes.

use std::time::Duration;

use crate::support::api::Api;
use crate::support::{FOUR_DRIVES, TestDaemon};

const LIMIT: Duration = Duration::from_secs(30);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drives_list_and_status_show_the_simulated_truth() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);

        let list = api.get("/api/v1/drives").await.expect(200);
        let names: Vec<&str> = list
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["name"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["conveyor", "lift", "turntable", "feeder"]);
        let lift = &list[1];
        assert_eq!(
            (lift["bus"].as_str(), lift["unit"].as_u64()),
            (Some("sim"), Some(2))
        );
        assert_eq!(lift["gear_ratio"], 10.0);
        assert_eq!(
            (lift["link"].as_str(), lift["online"].as_bool()),
            (Some("online"), Some(true))
        );
        assert!(lift["last_seen"].as_str().unwrap().ends_with('Z'));
        assert!(lift["status"]["voltage_v"].as_u64().unwrap() > 0);
        assert!(lift["lease"].is_null());

        // By name and, with one bus, by unit number.
        let by_name = api.get("/api/v1/drives/turntable").await.expect(200);
        let by_unit = api.get("/api/v1/drives/3").await.expect(200);
        assert_eq!(by_name["name"], "turntable");
        assert_eq!(by_unit["name"], "turntable");

        // The status has the interface's field names and the simulator's values.
        let status = api.get("/api/v1/drives/conveyor/status").await.expect(200);
        for field in [
            "turns",
            "angle_deg",
            "speed_rpm",
            "current_a",
            "current_counts",
            "voltage_v",
            "temperature_c",
            "active",
            "calibrated",
            "stalled",
            "mode",
            "fault",
            "fault_code",
        ] {
            assert!(!status[field].is_null(), "status lacks {field}: {status:#}");
        }
        assert_eq!(status["source"], "cache");
        assert_eq!(status["fault"], "none");
        assert_eq!(status["fault_code"], 0);
        assert_eq!(status["mode"], "open_loop");
        assert_eq!(status["active"], false);
        assert_eq!(status["calibrated"], true);
        let truth = d.sim().drive(1).unwrap();
        assert_eq!(
            status["voltage_v"].as_u64(),
            Some(u64::from(truth.status.voltage_v))
        );
        assert!(status["age_ms"].as_u64().unwrap() < 5_000);

        // A fresh read goes to the bus now.
        let polls_before = d.plant.buses()[0].handle.stats().on_wire();
        let fresh = api
            .get("/api/v1/drives/conveyor/status?fresh=true")
            .await
            .expect(200);
        assert_eq!(
            (fresh["source"].as_str(), fresh["age_ms"].as_u64()),
            (Some("bus"), Some(0))
        );
        assert!(d.plant.buses()[0].handle.stats().on_wire() > polls_before);
        api.get("/api/v1/drives/conveyor/status?fresh=maybe")
            .await
            .expect_problem(400, "invalid-request");

        // An injected fault shows by name and code.
        d.sim()
            .inject_fault(4, drivegate::drive::Fault::OverTemperature)
            .unwrap();
        let status =
            crate::support::eventually(Duration::from_secs(5), "fault in the status", || {
                let s = d.plant.buses()[0].handle.drive(4)?.status?;
                (s.fault() != drivegate::drive::Fault::None).then_some(s)
            })
            .await;
        assert_eq!(status.fault().code(), 4);
        let status = api.get("/api/v1/drives/feeder/status").await.expect(200);
        assert_eq!(
            (status["fault"].as_str(), status["fault_code"].as_u64()),
            (Some("over_temperature"), Some(4))
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_readiness_metrics_and_unknown_routes() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);

        let health = api.get("/healthz").await.expect(200);
        assert_eq!(health["status"], "ok");
        let ready = api.get("/readyz").await.expect(200);
        assert_eq!(ready["ready"], true);
        assert_eq!(ready["buses"][0]["drives_online"], 4);

        // Unknown drives, routes and methods are problems too.
        let p = api.get("/api/v1/drives/nosuch").await.expect_problem(404, "unknown-drive");
        assert!(p["detail"].as_str().unwrap().contains("nosuch"));
        // A slip of the keyboard gets the name meant, and the list.
        let p = api.get("/api/v1/drives/conveyr/status").await.expect_problem(404, "unknown-drive");
        assert_eq!(
            p["detail"],
            "no drive named \"conveyr\" is configured: did you mean \"conveyor\"? \
             (the drives are conveyor, lift, turntable, feeder)"
        );
        api.get("/api/v1/drives/9/status").await.expect_problem(404, "unknown-drive");
        api.get("/api/v1/nothing/here").await.expect_problem(404, "not-found");
        api.delete("/api/v1/drives").await.expect_problem(405, "method-not-allowed");

        // Metrics count requests by route template, never by raw path.
        let metrics = api
            .raw(|c| c.get(api.url("/metrics")))
            .await;
        assert_eq!(metrics.status, 200);
        assert!(metrics.content_type().starts_with("text/plain; version=0.0.4"));
        let text = reqwest::get(api.url("/metrics")).await.unwrap().text().await.unwrap();
        assert!(
            text.contains(r#"drivegate_http_requests_total{method="GET",route="/api/v1/drives/{drive}/status",status="404"} 2"#),
            "{text}"
        );
        assert!(text.contains(r#"route="unmatched",status="404"} 1"#), "{text}");
        assert!(text.contains(r#"route="/healthz",status="200"} 1"#), "{text}");
        assert!(!text.contains("nosuch"));

        // Every drive silent: not ready, with the reason.
        for unit in 1..=4 {
            d.sim().set_silent(unit, true);
        }
        // Three failed polls each, two attempts a poll, 300 ms an attempt.
        crate::support::eventually(Duration::from_secs(30), "every drive offline", || {
            d.plant.buses()[0]
                .handle
                .drives()
                .iter()
                .all(|s| s.link == drivegate::bus::cache::Link::Offline)
                .then_some(())
        })
        .await;
        let r = api.get("/readyz").await;
        assert_eq!(r.status, 503);
        assert_eq!(r.body["ready"], false);
        assert!(
            r.body["reasons"][0].as_str().unwrap().contains("no drive answers"),
            "{:#}",
            r.body
        );
        let list = api.get("/api/v1/drives").await.expect(200);
        assert_eq!(list[0]["link"], "offline");
        assert_eq!(list[0]["online"], false);
        assert!(list[0]["consecutive_failures"].as_u64().unwrap() >= 3);
        // The health check only says the process is alive.
        api.get("/healthz").await.expect(200);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
