//! Settings as a document, over real HTTP against the daemon on the
//! simulator: copied from one drive to another, a dry run, a refused
//! document, a save while the motor turns; and declared settings: the
//! drift of a drive that comes back with factory settings, reported, and
//! applied with `apply_settings = "on-drift"` once the motor stands still.

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::support::api::{Api, Ws, connect, wait_for, ws_command};
use crate::support::config::ConfigBuilder;
use crate::support::metrics::exported;
use crate::support::{FOUR_DRIVES, TestDaemon, bounded, eventually};

const LIMIT: Duration = Duration::from_secs(60);

/// The writable part of a settings document, to compare two drives.
fn writable(doc: &Value) -> Value {
    json!({
        "protection": {
            "limit_counts": doc["protection"]["limit_counts"],
            "stall_ms": doc["protection"]["stall_ms"],
        },
        "speed_ramp": doc["speed_ramp"],
        "position_ramp": doc["position_ramp"],
        "inertia_ratio": doc["inertia_ratio"],
        "rs485_control": doc["rs485_control"],
    })
}

/// The setting `key` of a diff.
fn setting<'a>(diff: &'a Value, key: &str) -> &'a Value {
    diff["settings"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["setting"] == key)
        .unwrap_or_else(|| panic!("no {key} in {diff:#}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_document_copied_from_one_drive_to_another_leaves_no_difference() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        // The conveyor tuned for its line (a part of a document is one too).
        let tuned = api
            .put(
                "/api/v1/drives/conveyor/settings",
                json!({
                    "protection": {"limit_a": 10.0, "stall_ms": 500},
                    "speed_ramp": {"alpha": 5000},
                    "position_ramp": {"alpha": 200},
                    "inertia_ratio": 5,
                }),
            )
            .await
            .expect(200);
        assert_eq!(tuned["complete"], true);
        assert_eq!(tuned["changed"], 5, "{tuned:#}");
        let limit = setting(&tuned, "protection.limit_a");
        assert_eq!(
            (&limit["before"], &limit["after"], &limit["unit"]),
            (&json!(12.0), &json!(10.0), &json!("A"))
        );
        assert_eq!(
            (&limit["raw_before"], &limit["raw_after"], &limit["result"]),
            (&json!(1536), &json!(1280), &json!("written"))
        );
        let conveyor = sim.drive(1).unwrap();
        assert_eq!(
            (
                conveyor.settings.stall_current,
                conveyor.settings.inertia_ratio
            ),
            (1280, 5)
        );
        // Saved as a file, the console's way.
        let file = api.get("/api/v1/drives/conveyor/settings?download=1").await;
        assert_eq!(
            file.headers.get("content-disposition").unwrap(),
            "attachment; filename=\"conveyor-settings.json\""
        );
        let file = file.expect(200);
        // The same file put on the lift: every writable setting of it.
        let copied = api
            .put("/api/v1/drives/lift/settings", file.clone())
            .await
            .expect(200);
        assert_eq!(copied["drive"], "lift");
        assert_eq!(copied["settings"].as_array().unwrap().len(), 6);
        assert_eq!(setting(&copied, "inertia_ratio")["result"], "written");
        assert_eq!(setting(&copied, "rs485_control")["result"], "unchanged");
        assert_eq!(setting(&copied, "rs485_control")["changed"], false);
        let lift = api.get("/api/v1/drives/lift/settings").await.expect(200);
        assert_eq!(writable(&lift), writable(&file));
        // The diff of the conveyor's document against the lift is empty.
        let again = api
            .put("/api/v1/drives/lift/settings?dry_run=true", file)
            .await
            .expect(200);
        assert_eq!(
            (&again["changed"], &again["dry_run"]),
            (&json!(0), &json!(true))
        );
        assert!(
            again["settings"]
                .as_array()
                .unwrap()
                .iter()
                .all(|s| s["result"] == "unchanged"),
            "{again:#}"
        );
        assert_eq!(
            sim.drive(2).unwrap().settings,
            sim.drive(1).unwrap().settings
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dry_run_or_a_refused_value_writes_nothing() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let before = api.get("/api/v1/drives/feeder/settings").await.expect(200);

        let dry = api
            .put(
                "/api/v1/drives/feeder/settings?dry_run=true",
                json!({"inertia_ratio": 9, "speed_ramp": {"alpha": 500000}}),
            )
            .await
            .expect(200);
        assert_eq!((&dry["dry_run"], &dry["changed"]), (&json!(true), &json!(1)));
        let inertia = setting(&dry, "inertia_ratio");
        assert_eq!(
            (&inertia["before"], &inertia["after"], &inertia["result"]),
            (&json!(1.0), &json!(9.0), &json!("would-write"))
        );
        assert_eq!(setting(&dry, "speed_ramp.alpha")["result"], "unchanged");
        // The stream's op runs the same code.
        let mut ws = connect(d.http, "", None).await;
        let reply = ws_command(
            &mut ws,
            1,
            "settings",
            "feeder",
            json!({"inertia_ratio": 9, "dry_run": true}),
        )
        .await;
        assert_eq!(reply["ok"], true, "{reply:#}");
        assert_eq!(
            reply["result"]["settings"],
            json!([setting(&dry, "inertia_ratio")])
        );
        assert_eq!(sim.drive(4).unwrap().settings.inertia_ratio, 1);
        let after = api.get("/api/v1/drives/feeder/settings").await.expect(200);
        assert_eq!(writable(&after), writable(&before));

        // One valid value and one out of range: neither is written, and
        // the refusal names the range.
        let p = api
            .put(
                "/api/v1/drives/feeder/settings",
                json!({"inertia_ratio": 5, "protection": {"stall_ms": 70000}}),
            )
            .await
            .expect_problem(422, "out-of-range");
        assert_eq!(
            p["valid_range"],
            json!({"min": 0.0, "max": 60000.0, "unit": "ms"})
        );
        assert!(
            p["detail"]
                .as_str()
                .unwrap()
                .contains("nothing was written"),
            "{p:#}"
        );
        assert_eq!(p["invalid_settings"][0]["setting"], "protection.stall_ms");
        // Every refused value is named, each with its range.
        let p = api
            .put(
                "/api/v1/drives/feeder/settings",
                json!({"inertia_ratio": 0, "protection": {"stall_ms": 70000}, "speed_ramp": {"alpha": 1000}}),
            )
            .await
            .expect_problem(422, "out-of-range");
        let refused: Vec<_> = p["invalid_settings"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| (r["setting"].clone(), r["valid_range"]["max"].clone()))
            .collect();
        assert_eq!(
            refused,
            [
                (json!("protection.stall_ms"), json!(60000.0)),
                (json!("inertia_ratio"), json!(65535.0)),
            ]
        );
        let feeder = sim.drive(4).unwrap();
        assert_eq!(
            (
                feeder.settings.inertia_ratio,
                feeder.settings.stall_duration_ms,
                feeder.settings.speed_alpha
            ),
            (1, 3000, 500_000)
        );
        // Unknown keys are refused too (a typo must not pass unnoticed).
        api.put("/api/v1/drives/feeder/settings", json!({"inertia": 5}))
            .await
            .expect_problem(400, "invalid-request");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_save_is_refused_while_the_motor_turns() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        api.activate_in("turntable", "speed").await;
        api.put(
            "/api/v1/drives/turntable/setpoint",
            json!({"speed_rpm": 100}),
        )
        .await
        .expect(200);
        eventually(Duration::from_secs(10), "the turntable turning", || {
            (sim.drive(3)?.speed_rpm > 50.0).then_some(())
        })
        .await;
        let p = api
            .put(
                "/api/v1/drives/turntable/settings",
                json!({"inertia_ratio": 3, "speed_ramp": {"alpha": 1000}, "save": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        assert!(p["detail"].as_str().unwrap().contains("flash"), "{p:#}");
        // Nothing written, not even to RAM.
        let turntable = sim.drive(3).unwrap();
        assert_eq!(
            (
                turntable.settings.inertia_ratio,
                turntable.settings.speed_alpha,
                turntable.flash.settings.inertia_ratio,
                turntable.saves_while_moving
            ),
            (1, 500_000, 1, 0)
        );
        // Not saving, the same document is a setting like any other.
        let r = api
            .put(
                "/api/v1/drives/turntable/settings",
                json!({"inertia_ratio": 3, "speed_ramp": {"alpha": 1000}}),
            )
            .await
            .expect(200);
        assert_eq!(r["changed"], 2);
        assert_eq!(sim.drive(3).unwrap().flash.settings.inertia_ratio, 1);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_that_stops_answering_part_way_is_reported_setting_by_setting() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        // The feeder carries out the first write (protection), then is
        // silent.
        sim.silence_after_writes(4, 1);
        let p = api
            .put(
                "/api/v1/drives/feeder/settings",
                json!({
                    "protection": {"stall_ms": 500},
                    "speed_ramp": {"alpha": 5000},
                    "inertia_ratio": 5,
                }),
            )
            .await
            .expect_problem(504, "drive-timeout");
        assert!(
            p["detail"].as_str().unwrap().contains("only in part"),
            "{p:#}"
        );
        let report = &p["settings_report"];
        assert_eq!(report["complete"], false);
        let result = |key| setting(report, key)["result"].clone();
        assert_eq!(result("protection.stall_ms"), "written");
        assert_eq!(result("speed_ramp.alpha"), "failed");
        assert!(
            setting(report, "speed_ramp.alpha")["detail"]
                .as_str()
                .unwrap()
                .contains("did not answer"),
            "{report:#}"
        );
        assert_eq!(result("inertia_ratio"), "not-sent");
        // The read-back failed too, and says so.
        assert!(report["read_back_error"].is_string(), "{report:#}");
        sim.set_silent(4, false);
        let feeder = sim.drive(4).unwrap();
        assert_eq!(
            (
                feeder.settings.stall_duration_ms,
                feeder.settings.speed_alpha,
                feeder.settings.inertia_ratio
            ),
            (500, 500_000, 1)
        );
        d.stop().await;
    })
    .await;
}

/// The lift declares its inertia and speed ramp; offline drives are
/// probed often, so a replacement is seen soon.
fn declared(apply: &str) -> String {
    ConfigBuilder::four_drives()
        .with_bus("sim", |b| {
            b.keys("offline_backoff_ms = 100\noffline_backoff_max_ms = 200")
                .drive_keys(
                    "lift",
                    &format!(
                        "settings = {{ apply_settings = \"{apply}\", inertia_ratio = 5, speed_ramp = {{ alpha = 5000 }} }}"
                    ),
                )
        })
        .toml()
}

/// Waits until the lift's declared settings are in `state`, by the API.
async fn lift_state(api: &Api, state: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let v = api.get("/api/v1/drives/lift").await.expect(200);
        if v["declared_settings"]["state"] == state {
            return v["declared_settings"].clone();
        }
        assert!(
            Instant::now() < deadline,
            "the lift's declared settings never came to {state}: {v:#}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Takes the lift off the bus until the stream says it is offline, puts a
/// drive fresh from the factory in its place, and lets it answer.
async fn replace_the_lift(d: &TestDaemon, ws: &mut Ws) {
    d.sim().set_silent(2, true);
    wait_for(ws, Duration::from_secs(20), "the lift offline", |v| {
        v["type"] == "offline" && v["drive"] == "lift"
    })
    .await;
    d.sim().replace(2).unwrap();
    d.sim().set_silent(2, false);
}

fn drift_of(declared: &Value) -> Vec<(String, Value, Value)> {
    declared["differences"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            (
                s["setting"].as_str().unwrap().to_string(),
                s["drive"].clone(),
                s["declared"].clone(),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drift_is_reported_when_a_drive_comes_back_with_factory_settings() {
    bounded(LIMIT * 2, async {
        let d = TestDaemon::start(&declared("never")).await;
        let api = Api::new(d.http, None);
        // At start the lift holds its factory settings: a drift, reported
        // and left alone.
        let state = lift_state(&api, "drift").await;
        assert_eq!(state["apply_settings"], "never");
        let factory = vec![
            (
                "speed_ramp.alpha".to_string(),
                json!(500000.0),
                json!(5000.0),
            ),
            ("inertia_ratio".to_string(), json!(1.0), json!(5.0)),
        ];
        assert_eq!(drift_of(&state), factory);
        assert_eq!(d.sim().drive(2).unwrap().settings.inertia_ratio, 1);
        let series = "drivegate_drive_settings_drift{bus=\"sim\",unit=\"2\",name=\"lift\"}";
        assert_eq!(exported(&d.metrics.render(), series), 1.0);
        // Drives without a declaration have no state.
        let conveyor = api.get("/api/v1/drives/conveyor").await.expect(200);
        assert!(conveyor.get("declared_settings").is_none(), "{conveyor:#}");
        api.get("/api/v1/drives/conveyor/settings/declared")
            .await
            .expect_problem(404, "not-found");

        // The declaration, put on the drive as a document: no drift.
        let declaration = api
            .get("/api/v1/drives/lift/settings/declared")
            .await
            .expect(200);
        assert_eq!(declaration["inertia_ratio"], 5);
        api.put("/api/v1/drives/lift/settings", declaration)
            .await
            .expect(200);
        let state = lift_state(&api, "match").await;
        assert_eq!(state["drift"], false);
        assert_eq!(exported(&d.metrics.render(), series), 0.0);

        // Replaced by a drive from the factory: drift, on the stream.
        let mut ws = connect(d.http, "?drives=lift", None).await;
        replace_the_lift(&d, &mut ws).await;
        let news = wait_for(&mut ws, Duration::from_secs(20), "the drift", |v| {
            v["type"] == "settings-drift" && v["drift"] == true
        })
        .await;
        assert_eq!(news["drive"], "lift");
        assert_eq!(news["state"], "drift");
        assert_eq!(drift_of(&news), factory);
        assert_eq!(lift_state(&api, "drift").await["drift"], true);
        assert_eq!(exported(&d.metrics.render(), series), 1.0);
        // Reported only: the new drive keeps its factory settings.
        assert_eq!(d.sim().drive(2).unwrap().settings.inertia_ratio, 1);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drift_is_applied_on_drift_once_the_motor_stands_still() {
    bounded(LIMIT * 2, async {
        let d = TestDaemon::start(&declared("on-drift")).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        // At start: found, applied, read back.
        lift_state(&api, "match").await;
        let lift = sim.drive(2).unwrap();
        assert_eq!(
            (lift.settings.inertia_ratio, lift.settings.speed_alpha),
            (5, 5000)
        );
        // Never to flash unless declared.
        assert_eq!(lift.flash.settings.inertia_ratio, 1);

        // The lift runs with other settings than declared when it comes
        // back: they are written only once it stands still.
        let mut ws = connect(d.http, "?drives=lift", None).await;
        api.activate_in("lift", "speed").await;
        api.put("/api/v1/drives/lift/setpoint", json!({"speed_rpm": 60}))
            .await
            .expect(200);
        eventually(Duration::from_secs(10), "the lift turning", || {
            (sim.drive(2)?.speed_rpm > 30.0).then_some(())
        })
        .await;
        api.put("/api/v1/drives/lift/settings", json!({"inertia_ratio": 2}))
            .await
            .expect(200);
        sim.set_silent(2, true);
        wait_for(&mut ws, Duration::from_secs(20), "the lift offline", |v| {
            v["type"] == "offline" && v["drive"] == "lift"
        })
        .await;
        sim.set_silent(2, false);
        let waiting = wait_for(&mut ws, Duration::from_secs(20), "the wait", |v| {
            v["type"] == "settings-drift" && v["state"] == "waiting-for-standstill"
        })
        .await;
        assert_eq!(
            drift_of(&waiting),
            [("inertia_ratio".to_string(), json!(2.0), json!(5.0))]
        );
        assert_eq!(sim.drive(2).unwrap().settings.inertia_ratio, 2);
        api.put("/api/v1/drives/lift/setpoint", json!({"speed_rpm": 0}))
            .await
            .expect(200);
        let applied = wait_for(&mut ws, Duration::from_secs(20), "the apply", |v| {
            v["type"] == "settings-applied"
        })
        .await;
        assert_eq!(applied["who"], "declared-settings");
        assert_eq!(applied["complete"], true);
        assert_eq!(setting(&applied, "inertia_ratio")["result"], "written");
        assert!(sim.drive(2).unwrap().speed_rpm.abs() < 1.0);
        wait_for(&mut ws, Duration::from_secs(20), "the match", |v| {
            v["type"] == "settings-drift" && v["state"] == "match"
        })
        .await;
        assert_eq!(sim.drive(2).unwrap().settings.inertia_ratio, 5);

        // A replacement from the factory is set up as declared.
        replace_the_lift(&d, &mut ws).await;
        wait_for(&mut ws, Duration::from_secs(20), "the new drive set", |v| {
            v["type"] == "settings-applied" && v["who"] == "declared-settings"
        })
        .await;
        let lift = sim.drive(2).unwrap();
        assert_eq!(
            (lift.settings.inertia_ratio, lift.settings.speed_alpha),
            (5, 5000)
        );
        d.stop().await;
    })
    .await;
}
