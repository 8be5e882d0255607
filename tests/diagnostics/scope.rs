//! The scope against the daemon on the simulator, over real HTTP, Modbus TCP
//! and WebSocket sockets: each trigger fires at the right sample (a speed
//! step, a stall, a write from Modbus TCP), the pre-trigger buffer holds
//! what came before, the CSV parses with its columns and units, one capture
//! per bus, roles, limits, and the progress on the stream.

use std::time::Duration;

use crate::support::api::{Api, connect, wait_for};
use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::csv::csv_fields;
use crate::support::modbus_tcp::Raw;
use crate::support::{FOUR_DRIVES, TestDaemon};
use serde_json::{Value, json};

const LIMIT: Duration = Duration::from_secs(45);
const SCOPE: &str = "/api/v1/buses/sim/scope";

/// Waits until the capture reaches `state` (or any end if `None`) and
/// returns its result.
async fn wait_state(api: &Api, want: &str) -> Value {
    let start = std::time::Instant::now();
    loop {
        let scope = api.get(SCOPE).await.expect(200);
        let state = scope["capture"]["state"].as_str().unwrap_or("").to_string();
        if state == want {
            return api.get(&format!("{SCOPE}/result")).await.expect(200);
        }
        assert!(
            !matches!(
                state.as_str(),
                "complete" | "incomplete" | "timed-out" | "cancelled"
            ) || state == want,
            "the capture ended {state}, not {want}: {scope:#}"
        );
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "no {want} capture: {scope:#}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Index of the first sample at or after the trigger.
fn trigger_index(trace: &Value) -> usize {
    floats(&trace["t_s"])
        .iter()
        .position(|&t| t >= 0.0)
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_speed_step_triggers_at_the_first_sample_through_the_level() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        api.activate_in("conveyor", "speed").await;
        let armed = api
            .post(
                SCOPE,
                json!({
                    "drives": ["conveyor"],
                    "fields": ["speed_rpm", "current_a"],
                    "trigger": {"type": "rising", "drive": "conveyor", "field": "speed_rpm", "level": 50},
                    "pre_trigger": {"samples": 20},
                    "length": {"samples": 100}
                }),
            )
            .await
            .expect(201);
        assert_eq!(armed["state"], "armed");
        assert_eq!(armed["drives"], json!(["conveyor"]));
        assert_eq!(armed["trigger"]["kind"], "rising");
        // The pre-trigger buffer fills while the drive stands.
        loop {
            let s = api.get(SCOPE).await.expect(200);
            if s["capture"]["pre_trigger_samples"] == 20 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 200}),
        )
        .await
        .expect(200);
        let result = wait_state(&api, "complete").await;
        assert_eq!(result["trigger"]["fired"], true);
        assert_eq!(result["pre_trigger_samples"], 20);
        assert_eq!(result["post_trigger_samples"], 100);
        let trace = &result["traces"][0];
        assert_eq!(trace["drive"], "conveyor");
        assert_eq!(trace["samples"], 120);
        let t = floats(&trace["t_s"]);
        let speed = floats(&trace["values"]["speed_rpm"]);
        let at = trigger_index(trace);
        assert_eq!(at, 20, "the trigger sample follows the 20 pre-trigger samples");
        assert_eq!(t[at], 0.0);
        assert!(speed[at] >= 50.0, "{}", speed[at]);
        assert!(
            speed[..at].iter().all(|&s| s < 50.0),
            "before the trigger the drive was below the level: {:?}",
            &speed[..at]
        );
        // The wire time of every sample, in order.
        assert!(t.windows(2).all(|w| w[0] < w[1]), "{t:?}");
        let wall: Vec<u64> = trace["time_us"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        let trigger_us = wall[at] as f64;
        for (i, w) in wall.iter().enumerate() {
            assert!(((*w as f64 - trigger_us) / 1e6 - t[i]).abs() < 2e-6);
        }
        assert!(result["trigger"]["what"]
            .as_str()
            .unwrap()
            .contains("crossing 50"));
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stall_triggers_with_the_time_before_it() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        // A low current limit and a short stall time, then a torque above it.
        api.put(
            "/api/v1/drives/turntable/protection",
            json!({"limit_a": 1.0, "stall_ms": 100}),
        )
        .await
        .expect(200);
        api.activate_in("turntable", "torque").await;
        api.post(
            SCOPE,
            json!({
                "drives": ["turntable", "feeder"],
                "trigger": {"type": "stall", "drive": "turntable"},
                "pre_trigger": {"seconds": 0.3},
                "length": {"samples": 30}
            }),
        )
        .await
        .expect(201);
        tokio::time::sleep(Duration::from_millis(100)).await;
        api.put(
            "/api/v1/drives/turntable/setpoint",
            json!({"torque_a": 3.0}),
        )
        .await
        .expect(200);
        let result = wait_state(&api, "complete").await;
        assert_eq!(result["trigger"]["what"], "the drive stalled");
        // Every field by default, each with its unit.
        let columns: Vec<&str> = result["columns"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            columns,
            [
                "speed_rpm",
                "angle_deg",
                "turns",
                "current_a",
                "voltage_v",
                "temperature_c",
                "active",
                "stalled",
                "mode",
                "fault"
            ]
        );
        let turntable = &result["traces"][0];
        assert_eq!(turntable["drive"], "turntable");
        let stalled = floats(&turntable["values"]["stalled"]);
        let current = floats(&turntable["values"]["current_a"]);
        let t = floats(&turntable["t_s"]);
        let at = trigger_index(turntable);
        assert_eq!(t[at], 0.0);
        assert_eq!(stalled[at], 1.0, "the trigger sample shows the stall");
        assert!(at > 0 && stalled[..at].iter().all(|&s| s == 0.0));
        // The pre-trigger shows the current above the limit before the stall.
        assert!(current[..at].iter().any(|&a| a > 1.0), "{current:?}");
        assert!(t[0] >= -0.3 - 1e-6, "{}", t[0]);
        // Both drives: 30 samples each after the trigger.
        let feeder = &result["traces"][1];
        assert_eq!(feeder["drive"], "feeder");
        let after = |trace: &Value| floats(&trace["t_s"]).iter().filter(|&&t| t >= 0.0).count();
        assert_eq!((after(turntable), after(feeder)), (30, 30));
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_write_from_modbus_tcp_triggers_and_names_its_client() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        api.post(
            SCOPE,
            json!({
                "drives": ["feeder"],
                "fields": ["active"],
                "trigger": {"type": "write", "drive": "feeder"},
                "pre_trigger": {"samples": 10},
                "length": {"samples": 20}
            }),
        )
        .await
        .expect(201);
        loop {
            let s = api.get(SCOPE).await.expect(200);
            if s["capture"]["pre_trigger_samples"] == 10 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        // A read from Modbus TCP is no write; polls are none either.
        let mut tcp = Raw::connect(d.modbus_tcp.unwrap()).await;
        let read = tcp.ask_as(7, 4, &[0x03, 0x00, 0xC0, 0x00, 0x07]).await;
        assert_eq!(read[..2], [0x03, 14]);
        assert_eq!(
            api.get(SCOPE).await.expect(200)["capture"]["state"],
            "armed"
        );
        // CONFIG = activate (manual 1.3), transaction 0x1234.
        let local = tcp.stream.local_addr().unwrap();
        let echo = tcp.ask_as(0x1234, 4, &[0x06, 0x00, 0x02, 0x00, 0x00]).await;
        assert_eq!(echo, [0x06, 0x00, 0x02, 0x00, 0x00]);
        let result = wait_state(&api, "complete").await;
        let trigger = &result["trigger"];
        assert_eq!(trigger["kind"], "write");
        let source = trigger["source"].as_str().unwrap();
        assert_eq!(source, format!("Modbus TCP {local} (transaction 4660)"));
        let trace = &result["traces"][0];
        let t = floats(&trace["t_s"]);
        let active = floats(&trace["values"]["active"]);
        let at = trigger_index(trace);
        assert_eq!(at, 10, "ten samples before the write");
        assert!(t[..at].iter().all(|&t| t < 0.0));
        assert!(active[..at].iter().all(|&a| a == 0.0), "{active:?}");
        // The first sample after the write is later than it: the drive read
        // its status after it had the command.
        assert!(t[at] > 0.0);
        assert!(active[at..].iter().all(|&a| a == 1.0), "{active:?}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn csv_result_one_capture_per_bus_and_the_stream() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        // Nothing yet.
        let scope = api.get(SCOPE).await.expect(200);
        assert_eq!(scope["capture"], Value::Null);
        assert!(scope["wire_rate_hz"].as_f64().unwrap() > 170.0);
        api.get(&format!("{SCOPE}/result"))
            .await
            .expect_problem(404, "no-capture");
        api.post_empty(&format!("{SCOPE}/trigger"))
            .await
            .expect_problem(404, "no-capture");

        let manual = json!({
            "drives": ["lift", "conveyor"],
            "fields": ["speed_rpm", "current_a", "temperature_c", "angle_deg"],
            "trigger": {"type": "manual"},
            "pre_trigger": {"samples": 5},
            "length": {"seconds": 0.5}
        });
        let armed = api.post(SCOPE, manual.clone()).await.expect(201);
        let id = armed["id"].as_u64().unwrap();
        // One capture per bus.
        let busy = api
            .post(SCOPE, manual.clone())
            .await
            .expect_problem(409, "scope-busy");
        assert!(
            busy["detail"]
                .as_str()
                .unwrap()
                .contains("one capture per bus")
        );
        // The stream tells it was armed.
        let m = wait_for(&mut ws, Duration::from_secs(5), "the armed capture", |m| {
            m["type"] == "scope"
        })
        .await;
        assert_eq!(
            (m["id"].as_u64(), m["state"].as_str()),
            (Some(id), Some("armed"))
        );
        // Trigger once the pre-trigger buffer holds its 5 samples of each
        // drive (polled in turn, so 10 in all).
        loop {
            let scope = api.get(SCOPE).await.expect(200);
            if scope["capture"]["pre_trigger_samples"]
                .as_u64()
                .unwrap_or(0)
                >= 10
            {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let triggered = api
            .post_empty(&format!("{SCOPE}/trigger"))
            .await
            .expect(200);
        assert_eq!(triggered["state"], "triggered");
        // Without tokens, a client is its address.
        let source = triggered["trigger"]["source"].as_str().unwrap();
        assert!(source.starts_with("HTTP 127.0.0.1:"), "{source}");
        api.post_empty(&format!("{SCOPE}/trigger"))
            .await
            .expect_problem(409, "capture-not-running");
        let m = wait_for(
            &mut ws,
            Duration::from_secs(5),
            "the end on the stream",
            |m| m["type"] == "scope" && m["state"] == "complete",
        )
        .await;
        assert_eq!(m["trigger"]["fired"], true);
        let result = wait_state(&api, "complete").await;
        api.delete(SCOPE)
            .await
            .expect_problem(409, "capture-not-running");

        // The CSV: header with the units in the names, one row per sample.
        let csv = api
            .raw(|c| c.get(format!("http://{}{SCOPE}/result.csv", d.http)))
            .await;
        assert_eq!(csv.status, 200);
        assert!(csv.content_type().starts_with("text/csv"));
        let text = reqwest::get(format!("http://{}{SCOPE}/result.csv", d.http))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        let mut lines = text.lines();
        let header = csv_fields(lines.next().unwrap());
        assert_eq!(
            header,
            [
                "time",
                "t_s",
                "drive",
                "unit",
                "speed_rpm",
                "current_a",
                "temperature_c",
                "angle_deg"
            ]
        );
        let rows: Vec<Vec<String>> = lines.map(csv_fields).collect();
        let total = result["pre_trigger_samples"].as_u64().unwrap()
            + result["post_trigger_samples"].as_u64().unwrap();
        assert_eq!(rows.len() as u64, total);
        let mut last_t = f64::MIN;
        for row in &rows {
            assert_eq!(row.len(), header.len(), "{row:?}");
            assert!(row[0].ends_with('Z') && row[0].len() == 27, "{}", row[0]);
            let t: f64 = row[1].parse().unwrap();
            assert!(t >= last_t && t < 0.5 + 1e-6);
            last_t = t;
            assert!(matches!(
                (row[2].as_str(), row[3].as_str()),
                ("lift", "2") | ("conveyor", "1")
            ));
            for value in &row[4..] {
                let _: f64 = value.parse().unwrap();
            }
            let temperature: f64 = row[6].parse().unwrap();
            assert!((0.0..100.0).contains(&temperature), "°C: {temperature}");
        }
        // Each drive: 5 before the trigger.
        for trace in result["traces"].as_array().unwrap() {
            let t = floats(&trace["t_s"]);
            assert_eq!(t.iter().filter(|&&t| t < 0.0).count(), 5);
        }

        // Cancel: it keeps what it holds.
        api.post(SCOPE, manual).await.expect(201);
        let cancelled = api.delete(SCOPE).await.expect(200);
        assert_eq!(cancelled["state"], "cancelled");
        assert_eq!(
            api.get(&format!("{SCOPE}/result")).await.expect(200)["state"],
            "cancelled"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_captures_are_refused_with_what_would_fit_and_viewers_may_not_arm() {
    bounded(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .http_token("panel", "viewer", "view-token")
            .http_token("shift", "operator", "operate-token")
            .section("scope", "max_samples = 2000")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let viewer = Api::new(d.http, Some("view-token"));
        let operator = viewer.with_token(Some("operate-token"));
        let body = json!({
            "drives": ["conveyor"],
            "trigger": {"type": "immediate"},
            "length": {"samples": 10}
        });
        viewer.post(SCOPE, body.clone()).await.expect_problem(403, "forbidden");
        viewer.get(SCOPE).await.expect(200);
        // Too long for max_samples: the range and what fits.
        let p = operator
            .post(
                SCOPE,
                json!({"drives": ["conveyor"], "trigger": {"type": "manual"}, "length": {"seconds": 60}}),
            )
            .await
            .expect_problem(422, "out-of-range");
        assert_eq!(p["valid_range"]["max"], 2000.0);
        assert!(p["detail"].as_str().unwrap().contains("[scope] max_samples"));
        // A trigger on a drive that is not captured.
        operator
            .post(
                SCOPE,
                json!({"drives": ["conveyor"], "trigger": {"type": "stall", "drive": "lift"}, "length": {"samples": 10}}),
            )
            .await
            .expect_problem(400, "invalid-request");
        // Neither samples nor seconds; an unknown field name.
        operator
            .post(SCOPE, json!({"drives": ["conveyor"], "trigger": {"type": "manual"}, "length": {}}))
            .await
            .expect_problem(400, "invalid-request");
        operator
            .post(
                SCOPE,
                json!({"drives": ["conveyor"], "fields": ["rpm"], "trigger": {"type": "manual"}, "length": {"samples": 1}}),
            )
            .await
            .expect_problem(400, "invalid-request");
        operator
            .post("/api/v1/buses/nope/scope", body.clone())
            .await
            .expect_problem(404, "unknown-bus");
        // An immediate capture by the operator: the scope's polls carry
        // its source in the monitor.
        let armed = operator.post(SCOPE, body).await.expect(201);
        assert_eq!(armed["trigger"]["fired"], true);
        wait_state(&operator, "complete").await;
        let frames = viewer
            .get("/api/v1/buses/sim/monitor/frames?source=scope&limit=10")
            .await
            .expect(200);
        let frames = frames["frames"].as_array().unwrap();
        assert!(!frames.is_empty());
        assert!(frames.iter().all(|f| f["unit"] == 1 && f["source"] == "scope"));
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_other_drives_keep_their_floor_rate_and_commands_go_through() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&ConfigBuilder::four_drives().section("scope", "floor_rate_hz = 5").toml()).await;
        let api = Api::new(d.http, None);
        let armed = api
            .post(
                SCOPE,
                json!({"drives": ["conveyor"], "trigger": {"type": "immediate"}, "length": {"seconds": 3.0}}),
            )
            .await
            .expect(201);
        assert_eq!(armed["state"], "triggered");
        // A command to another drive goes through meanwhile.
        api.command("lift", "activate").await;
        let result = wait_state(&api, "complete").await;
        let trace = &result["traces"][0];
        let times: Vec<u64> = trace["time_us"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        let (start, end) = (times[0], *times.last().unwrap());
        // The status reads in the capture's time, in the order the bus
        // thread sent them (the monitor's request frames).
        let frames = api
            .get("/api/v1/buses/sim/monitor/frames?outcome=sent&function=3&limit=100000")
            .await
            .expect(200);
        let reads: Vec<(u64, String, u64)> = frames["frames"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|f| {
                let t = f["time_us"].as_u64().unwrap();
                t >= start && t <= end
            })
            .map(|f| {
                (
                    f["unit"].as_u64().unwrap(),
                    f["source"].as_str().unwrap().to_string(),
                    f["time_us"].as_u64().unwrap(),
                )
            })
            .collect();
        // The captured drive's polls are the scope's, the others' the
        // poller's.
        assert!(reads.iter().all(|(u, s, _)| (*u == 1) == (s == "scope")), "{reads:?}");
        // The floor, in bus work rather than in time (which a loaded
        // machine stretches): between two polls of another drive, the
        // captured drive gets at most about one floor period's worth of
        // reads (200 ms / 5.8 ms, less the other drives' turns), never the
        // whole bus for longer. (A low floor, so that the captured drive
        // still has most of the bus on a machine that slows the wire's
        // work several times over.)
        let captured = reads.iter().filter(|(u, _, _)| *u == 1).count();
        for unit in [2, 3, 4] {
            let positions: Vec<usize> = reads
                .iter()
                .enumerate()
                .filter(|(_, (u, _, _))| *u == unit)
                .map(|(i, _)| i)
                .collect();
            assert!(positions.len() >= 5, "unit {unit}: {} polls", positions.len());
            let longest = positions
                .windows(2)
                .map(|w| reads[w[0] + 1..w[1]].iter().filter(|(u, _, _)| *u == 1).count())
                .max()
                .unwrap();
            assert!(longest <= 40, "unit {unit} waited for {longest} reads of the captured drive");
            // ...and no more often than the floor needs: one read per
            // 200 ms on average by the bus's own clock, which a loaded
            // machine slows but does not speed up (a command's own read
            // may come between: 15 % off); the captured drive has the rest.
            let times: Vec<u64> = positions.iter().map(|&i| reads[i].2).collect();
            let mean = (times[times.len() - 1] - times[0]) / (times.len() as u64 - 1);
            assert!(
                mean >= 170_000,
                "unit {unit} polled every {mean} us on average: more often than the 200 ms floor"
            );
            assert!(
                positions.len() < captured,
                "unit {unit}: {} polls, the captured drive {captured}",
                positions.len()
            );
        }
        d.stop().await;
    })
    .await;
}
