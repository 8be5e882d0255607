//! Every class of error, over real HTTP against the daemon on the
//! simulator: each has its own status and problem type, says what to do,
//! and a refused request changes nothing on the drive.

use std::time::Duration;

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::cache::Link;
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{ConfigCommand, DriveRequest};
use drivegate::sim::FaultRates;
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(40);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_out_of_range_requests_change_nothing() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        api.activate_in("conveyor", "speed").await;
        let setpoint = "/api/v1/drives/conveyor/setpoint";

        // Wrong JSON, wrong types, unknown and contradictory fields: 400.
        let r = api
            .raw(|c| {
                c.put(api.url(setpoint))
                    .header("content-type", "application/json")
                    .body("{\"speed_rpm\": ")
            })
            .await;
        r.expect_problem(400, "invalid-request");
        let p = api
            .put(setpoint, json!({"speed_rpm": "fast"}))
            .await
            .expect_problem(400, "invalid-request");
        assert!(p["detail"].as_str().unwrap().contains("speed_rpm"), "{p:#}");
        let p = api
            .put(setpoint, json!({"speed": 100}))
            .await
            .expect_problem(400, "invalid-request");
        assert!(p["detail"].as_str().unwrap().contains("speed"), "{p:#}");
        api.put(setpoint, json!({"speed_rpm": 10, "torque_a": 1.0}))
            .await
            .expect_problem(400, "invalid-request");
        api.put("/api/v1/drives/conveyor/mode", json!({"mode": "fast"}))
            .await
            .expect_problem(400, "invalid-request");
        // Not JSON at all: 415; too large: 413.
        api.raw(|c| c.put(api.url(setpoint)).body("speed_rpm=100"))
            .await
            .expect_problem(415, "unsupported-media-type");
        let huge = json!({"speed_rpm": 1, "pad": "x".repeat(70_000)});
        api.put(setpoint, huge)
            .await
            .expect_problem(413, "payload-too-large");

        // Unknown things: 404 with what exists.
        api.put("/api/v1/drives/nosuch/setpoint", json!({"speed_rpm": 1}))
            .await
            .expect_problem(404, "unknown-drive");
        let p = api
            .post_empty("/api/v1/drives/conveyor/commands/launch")
            .await
            .expect_problem(404, "unknown-command");
        assert!(
            p["detail"].as_str().unwrap().contains("fault-reset"),
            "{p:#}"
        );
        api.get("/api/v1/buses/nosuch")
            .await
            .expect_problem(404, "unknown-bus");

        // Out of range: 422 naming the range in the request's unit.
        for (path, body, min, max, unit) in [
            (setpoint, json!({"speed_rpm": 3000}), -2048.0, 2047.0, "rpm"),
            (
                setpoint,
                json!({"position_deg": -200.5}),
                -180.0,
                180.0,
                "deg",
            ),
            (setpoint, json!({"torque_a": 20}), -16.0, 15.9921875, "A"),
            (
                setpoint,
                json!({"torque_counts": 5000}),
                -2048.0,
                2047.0,
                "counts",
            ),
            (
                setpoint,
                json!({"speed_rpm": 10, "lease_ms": 5}),
                100.0,
                60000.0,
                "ms",
            ),
            (
                "/api/v1/drives/conveyor/protection",
                json!({"limit_a": 1.0, "stall_ms": 70000}),
                0.0,
                60000.0,
                "ms",
            ),
            (
                "/api/v1/drives/conveyor/protection",
                json!({"limit_counts": -1, "stall_ms": 10}),
                0.0,
                2047.0,
                "counts",
            ),
            (
                "/api/v1/drives/conveyor/inertia",
                json!({"ratio": 0}),
                1.0,
                65535.0,
                "",
            ),
            (
                "/api/v1/drives/conveyor/ramps/speed",
                json!({"alpha": -1}),
                0.0,
                4294967295.0,
                "",
            ),
            (
                "/api/v1/drives/conveyor/ramps/position",
                json!({"time_s": 0.1, "step_deg": 400}),
                0.01,
                360.0,
                "deg",
            ),
        ] {
            let p = api
                .put(path, body.clone())
                .await
                .expect_problem(422, "out-of-range");
            let range = &p["valid_range"];
            assert_eq!(
                (
                    range["min"].as_f64(),
                    range["max"].as_f64(),
                    range["unit"].as_str()
                ),
                (Some(min), Some(max), Some(unit)),
                "{body}: {p:#}"
            );
        }
        // A ramp time the alpha cannot reach names the time range.
        let p = api
            .put(
                "/api/v1/drives/conveyor/ramps/speed",
                json!({"time_s": 100, "step_rpm": 133}),
            )
            .await
            .expect_problem(422, "out-of-range");
        assert_eq!(p["valid_range"]["unit"], "s");
        api.post(
            "/api/v1/buses/sim/address",
            json!({"address": 300, "only_drive_on_bus": true}),
        )
        .await
        .expect_problem(422, "out-of-range");

        // Nothing reached the drive.
        let conveyor = sim.drive(1).unwrap();
        assert_eq!(conveyor.setpoints.speed_rpm, 0);
        assert_eq!(conveyor.settings, drivegate::sim::model::Settings::FACTORY);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drive_state_conflicts_are_409() {
    tokio::time::timeout(LIMIT, async {
        // The feeder is polled once a minute: its cached status goes stale.
        let config = ConfigBuilder::four_drives()
            .with_bus("sim", |b| {
                b.drive_keys("feeder", "poll_interval_ms = 60000")
            })
            .toml();
        let d = TestDaemon::start(&config).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();

        // Not active (from the status): 409, nothing written.
        let p = api
            .put("/api/v1/drives/lift/setpoint", json!({"speed_rpm": 50}))
            .await
            .expect_problem(409, "drive-not-active");
        assert_eq!(p["drive"], "lift");
        assert_eq!(sim.drive(2).unwrap().setpoints.speed_rpm, 0);

        // Not active, though the cache still says active: the drive's own
        // refusal (exception 0x04) is the same 409.
        api.activate_in("feeder", "speed").await;
        let fresh = api
            .get("/api/v1/drives/feeder/status?fresh=true")
            .await
            .expect(200);
        assert_eq!(fresh["active"], true);
        let (_, bus) = d.plant.drive("feeder").unwrap();
        bus.execute(
            4,
            &DriveRequest::Config(ConfigCommand::Deactivate),
            JobOptions::default(),
        )
        .await
        .unwrap();
        assert!(
            bus.drive(4).unwrap().status.unwrap().active(),
            "the cache should be stale"
        );
        let p = api
            .put("/api/v1/drives/feeder/setpoint", json!({"speed_rpm": 50}))
            .await
            .expect_problem(409, "drive-not-active");
        assert_eq!(p["exception_code"], 4);

        // Saving while the motor turns: 409 unless forced.
        api.activate_in("lift", "speed").await;
        api.put("/api/v1/drives/lift/setpoint", json!({"speed_rpm": 100}))
            .await
            .expect(200);
        eventually(Duration::from_secs(5), "the lift turning", || {
            (sim.drive(2)?.speed_rpm > 50.0).then_some(())
        })
        .await;
        let p = api
            .put(
                "/api/v1/drives/lift/inertia",
                json!({"ratio": 3, "save": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        assert!(p["detail"].as_str().unwrap().contains("force"), "{p:#}");
        api.post_empty("/api/v1/drives/lift/commands/factory-reset")
            .await
            .expect_problem(409, "drive-moving");
        assert_eq!(sim.drive(2).unwrap().flash.settings.inertia_ratio, 1);
        // Without saving, the setting itself is fine while moving.
        api.put("/api/v1/drives/lift/inertia", json!({"ratio": 3}))
            .await
            .expect(200);
        let r = api
            .put(
                "/api/v1/drives/lift/inertia",
                json!({"ratio": 3, "save": true, "force": true}),
            )
            .await
            .expect(200);
        assert_eq!(r["saved"], true);
        let lift = sim.drive(2).unwrap();
        assert_eq!(
            (lift.flash.settings.inertia_ratio, lift.saves_while_moving),
            (3, 1)
        );

        // Calibrating: the drive is busy (0x06), 409 with Retry-After.
        api.activate_in("turntable", "speed").await;
        api.command("turntable", "calibrate").await;
        let r = api
            .put(
                "/api/v1/drives/turntable/setpoint",
                json!({"speed_rpm": 20}),
            )
            .await;
        assert_eq!(r.headers.get("retry-after").unwrap(), "1");
        r.expect_problem(409, "drive-busy");

        // Address setting without confirming a single drive: 409.
        api.post("/api/v1/buses/sim/address", json!({"address": 9}))
            .await
            .expect_problem(409, "confirmation-required");
        assert!(sim.drive(9).is_none());
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bus_and_drive_failures_have_their_own_status() {
    tokio::time::timeout(LIMIT, async {
        // An uncalibrated simulator, a drive polled once a minute, and a
        // second bus whose adapter is not there.
        let text = ConfigBuilder::four_drives()
            .with_bus("sim", |b| {
                b.sim("calibrated = false")
                    .drive_keys("feeder", "poll_interval_ms = 60000")
            })
            .bus("line2", |b| {
                b.port("/dev/drivegate-test-no-such-adapter")
                    .drive(1, "press")
            })
            .toml();
        let d = TestDaemon::start_no_wait(&text).await;
        let sim = d.sim();
        eventually(
            Duration::from_secs(10),
            "the simulated drives online",
            || {
                d.plant.buses()[0]
                    .handle
                    .drives()
                    .iter()
                    .all(|s| s.status.is_some())
                    .then_some(())
            },
        )
        .await;
        let api = Api::new(d.http, None);

        // Bus down: 503 with Retry-After; not ready.
        let line2 = &d.plant.buses()[1].handle;
        eventually(Duration::from_secs(5), "line2 down", || {
            matches!(
                line2.port_state(),
                drivegate::bus::handle::PortState::Down { .. }
            )
            .then_some(())
        })
        .await;
        let r = api
            .post_empty("/api/v1/drives/press/commands/activate")
            .await;
        assert_eq!(r.headers.get("retry-after").unwrap(), "5");
        r.expect_problem(503, "bus-down");
        let bus = api.get("/api/v1/buses/line2").await.expect(200);
        assert_eq!(bus["state"], "down");
        assert!(
            bus["reason"].as_str().unwrap().contains("no-such-adapter"),
            "{bus:#}"
        );
        let ready = api.get("/readyz").await;
        assert_eq!(ready.status, 503);
        assert!(
            ready.body["reasons"][0].as_str().unwrap().contains("line2"),
            "{:#}",
            ready.body
        );
        // With two buses a unit number is ambiguous: names are needed.
        api.get("/api/v1/drives/1")
            .await
            .expect_problem(404, "unknown-drive");

        // The drive refuses (fine-tuning before calibration, 0x04): 502.
        let p = api
            .post_empty("/api/v1/drives/conveyor/commands/fine-tune")
            .await
            .expect_problem(502, "drive-refused");
        assert_eq!(p["exception_code"], 4);

        // A drive that stops answering while it looks online: 504.
        sim.set_silent(4, true);
        let p = api
            .post_empty("/api/v1/drives/feeder/commands/activate")
            .await
            .expect_problem(504, "drive-timeout");
        assert!(
            p["detail"].as_str().unwrap().contains("did not answer"),
            "{p:#}"
        );
        // A drive known to be offline: 503.
        sim.set_silent(2, true);
        eventually(Duration::from_secs(10), "the lift offline", || {
            (d.plant.buses()[0].handle.drive(2)?.link == Link::Offline).then_some(())
        })
        .await;
        api.post_empty("/api/v1/drives/lift/commands/activate")
            .await
            .expect_problem(503, "drive-offline");

        // Corrupted replies only: 502 bad reply.
        sim.set_fault_rates(FaultRates {
            crc_error_rate: 1.0,
            ..FaultRates::default()
        })
        .unwrap();
        api.post_empty("/api/v1/drives/turntable/commands/activate")
            .await
            .expect_problem(502, "drive-bad-reply");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_bus_queue_is_429_with_retry_after() {
    tokio::time::timeout(LIMIT, async {
        let text = ConfigBuilder::four_drives()
            .with_bus("sim", |b| {
                b.keys("queue_capacity = 4\nqueue_per_client = 2")
            })
            .toml();
        let d = TestDaemon::start(&text).await;
        let api = Api::new(d.http, None);
        let reads = (0..24).map(|_| {
            let api = api.clone();
            tokio::spawn(async move { api.get("/api/v1/drives/conveyor/status?fresh=true").await })
        });
        let replies = futures_util::future::join_all(reads).await;
        let mut busy = 0;
        for r in replies {
            let r = r.unwrap();
            match r.status {
                200 => {}
                429 => {
                    assert_eq!(r.headers.get("retry-after").unwrap(), "1");
                    r.expect_problem(429, "bus-busy");
                    busy += 1;
                }
                other => panic!("unexpected {other}: {:#}", r.body),
            }
        }
        assert!(busy > 0, "24 concurrent reads never filled a queue of 2");
        assert!(d.plant.buses()[0].handle.stats().busy_rejections > 0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
