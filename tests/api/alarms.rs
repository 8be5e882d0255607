//! Alarms through the API on the simulator: a drive that goes silent
//! raises an `offline` alarm (on the stream and in `GET /api/v1/alarms`,
//! with the manual's help), a viewer may not acknowledge it, an operator
//! does (audited, on the stream), and the alarm, acknowledged, is still
//! there after the daemon restarts on the same `[safety] state_dir`, where
//! the drive answering again clears it; a save refused while the motor
//! turns becomes a `refused-write` alarm, repeats count on it, and the
//! stream's `alarm-ack` acknowledges it; a drive's fault is an alarm with
//! the manual's help, cleared by a fault reset; a drive that never answered
//! since its bus opened is a `never-answered` alarm naming the baud rate
//! and the unit address (not `offline`), once while it lasts (a bus down
//! and back in between included), cleared when it answers, and none for a
//! drive on a bus whose port is down.

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::support::TestDaemon;
use crate::support::api::{Api, connect, send_json, wait_for};
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::metric;
use crate::support::sim_process::ExternalSim;
use crate::support::wait::{bounded, eventually};

const LIMIT: Duration = Duration::from_secs(90);
/// Longest wait for an event the design says must come.
const EVENT: Duration = Duration::from_secs(20);

fn config(state_dir: &std::path::Path) -> String {
    ConfigBuilder::four_drives()
        .http_token("panel", "operator", "panel-token")
        .http_token("wall", "viewer", "wall-token")
        .section(
            "safety",
            &format!("state_dir = \"{}\"", state_dir.display()),
        )
        .toml()
}

/// The alarms of `drive` of the given kind, newest first.
async fn alarms_of(api: &Api, drive: &str, kind: &str) -> Vec<Value> {
    let list = api
        .get(&format!("/api/v1/alarms?drive={drive}"))
        .await
        .expect(200);
    list["alarms"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["kind"] == kind)
        .cloned()
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_offline_drive_raises_an_alarm_acknowledged_and_kept_across_a_restart() {
    capture_logs();
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let toml = config(&dir.path().join("state"));
        let d = TestDaemon::start(&toml).await;
        let operator = Api::new(d.http, Some("panel-token"));
        let viewer = Api::new(d.http, Some("wall-token"));
        let mut ws = connect(d.http, "", Some("wall-token")).await;
        send_json(
            &mut ws,
            json!({"type": "subscribe", "drives": ["conveyor"]}),
        )
        .await;
        wait_for(&mut ws, EVENT, "the subscription", |m| {
            m["type"] == "subscribed"
        })
        .await;

        // The lift goes silent: an offline alarm, to every client (this
        // one follows only the conveyor).
        d.sim().set_silent(2, true);
        let raised = wait_for(&mut ws, EVENT, "the lift's offline alarm", |m| {
            m["type"] == "alarm-raised" && m["alarm"]["drive"] == "lift"
        })
        .await;
        let alarm = &raised["alarm"];
        assert_eq!(alarm["kind"], "offline", "{raised:#}");
        assert_eq!(
            (alarm["bus"].as_str(), alarm["active"].as_bool()),
            (Some("sim"), Some(true))
        );
        assert!(
            alarm["text"]
                .as_str()
                .unwrap()
                .contains("stopped answering"),
            "{alarm:#}"
        );
        assert!(
            alarm["help"].as_str().unwrap().contains("manual 1.2"),
            "{alarm:#}"
        );
        assert!(alarm["raised_at"].as_str().unwrap().ends_with('Z'));
        assert_eq!(alarm["acknowledged"], false);
        let id = alarm["id"].as_u64().unwrap();

        // Listed, filtered, and counted.
        let list = viewer
            .get("/api/v1/alarms?active=true&unacknowledged=true")
            .await
            .expect(200);
        assert!(
            list["alarms"]
                .as_array()
                .unwrap()
                .iter()
                .any(|a| a["id"] == id),
            "{list:#}"
        );
        assert!(list["unacknowledged"].as_u64().unwrap() >= 1);
        assert_eq!(list["kept_at_most"], 500);
        let other = viewer.get("/api/v1/alarms?drive=feeder").await.expect(200);
        assert!(
            other["alarms"]
                .as_array()
                .unwrap()
                .iter()
                .all(|a| a["drive"] == "feeder")
        );
        let text = d.metrics.render();
        assert_eq!(
            metric(&text, "drivegate_alarms_active{kind=\"offline\"}"),
            1.0
        );
        viewer
            .get("/api/v1/alarms?since=yesterday")
            .await
            .expect_problem(400, "invalid-request");

        // A viewer may not acknowledge; an operator does, once.
        let p = viewer
            .post_empty(&format!("/api/v1/alarms/{id}/ack"))
            .await
            .expect_problem(403, "forbidden");
        assert!(
            p["detail"].as_str().unwrap().contains("operator role"),
            "{p:#}"
        );
        assert_eq!(
            alarms_of(&viewer, "lift", "offline").await[0]["acknowledged"],
            false
        );
        let acked = operator
            .post_empty(&format!("/api/v1/alarms/{id}/ack"))
            .await
            .expect(200);
        assert_eq!(
            (acked["id"].as_u64(), acked["acknowledged_by"].as_str()),
            (Some(id), Some("panel"))
        );
        assert_eq!(acked["active"], true, "the drive is still silent");
        let news = wait_for(&mut ws, EVENT, "the acknowledgement", |m| {
            m["type"] == "alarm-acknowledged"
        })
        .await;
        assert_eq!(news["alarm"], acked);
        operator
            .post_empty("/api/v1/alarms/999999/ack")
            .await
            .expect_problem(404, "not-found");
        assert!(
            log_text().contains(&format!("alarm={id}")),
            "the acknowledgement is audited"
        );
        let text = d.metrics.render();
        assert_eq!(metric(&text, "drivegate_alarms_unacknowledged "), 0.0);
        assert!(metric(&text, "drivegate_alarm_file_bytes ") > 12.0);

        // A restart on the same state directory: the alarm is there,
        // acknowledged; the drive answers the new daemon, which clears it.
        d.stop().await;
        let d = TestDaemon::start(&toml).await;
        let viewer = Api::new(d.http, Some("wall-token"));
        let again = &alarms_of(&viewer, "lift", "offline").await;
        assert_eq!(again.len(), 1, "{again:#?}");
        let kept = &again[0];
        assert_eq!(kept["id"].as_u64(), Some(id));
        assert_eq!(kept["raised_at"], acked["raised_at"]);
        assert_eq!(kept["acknowledged_by"], "panel");
        assert_eq!(kept["acknowledged_at"], acked["acknowledged_at"]);
        let start = Instant::now();
        let cleared = loop {
            let a = alarms_of(&viewer, "lift", "offline").await.remove(0);
            if a["active"] == false {
                break a;
            }
            assert!(start.elapsed() < EVENT, "the alarm did not clear: {a:#}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert!(cleared["cleared_at"].as_str().unwrap() > cleared["raised_at"].as_str().unwrap());
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_save_refused_while_the_motor_turns_is_an_alarm_that_counts_repeats() {
    bounded(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .http_token("panel", "operator", "panel-token")
            .http_token("setter", "admin", "setter-token")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let admin = Api::new(d.http, Some("setter-token"));
        let mut ws = connect(d.http, "", Some("panel-token")).await;
        send_json(&mut ws, json!({"type": "subscribe", "drives": "all"})).await;
        wait_for(&mut ws, EVENT, "the subscription", |m| {
            m["type"] == "subscribed"
        })
        .await;

        admin.activate_in("conveyor", "speed").await;
        admin
            .put(
                "/api/v1/drives/conveyor/setpoint",
                json!({"speed_rpm": 200}),
            )
            .await
            .expect(200);
        eventually(EVENT, "the conveyor turning", || {
            (d.sim().drive(1)?.speed_rpm > 50.0).then_some(())
        })
        .await;
        admin
            .put(
                "/api/v1/drives/conveyor/inertia",
                json!({"ratio": 2, "save": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        let raised = wait_for(&mut ws, EVENT, "the refused write's alarm", |m| {
            m["type"] == "alarm-raised" && m["alarm"]["kind"] == "refused-write"
        })
        .await;
        let alarm = &raised["alarm"];
        assert_eq!(alarm["drive"], "conveyor");
        assert_eq!(
            (alarm["active"].as_bool(), alarm["count"].as_u64()),
            (Some(false), Some(1))
        );
        let text = alarm["text"].as_str().unwrap();
        assert!(
            text.contains("setter") && text.contains("refused"),
            "{text}"
        );
        assert!(
            alarm["help"].as_str().unwrap().contains("standing still"),
            "{alarm:#}"
        );

        // The same refusal again, before anyone acknowledged: the same
        // alarm, counted.
        admin
            .put(
                "/api/v1/drives/conveyor/inertia",
                json!({"ratio": 2, "save": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        let again = wait_for(&mut ws, EVENT, "the repeat", |m| {
            m["type"] == "alarm-raised" && m["alarm"]["kind"] == "refused-write"
        })
        .await;
        assert_eq!(again["alarm"]["id"], alarm["id"]);
        assert_eq!(again["alarm"]["count"], 2);
        let list = admin
            .get("/api/v1/alarms?unacknowledged=true&drive=conveyor")
            .await
            .expect(200);
        let refused: Vec<&Value> = list["alarms"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["kind"] == "refused-write")
            .collect();
        assert_eq!(refused.len(), 1, "{list:#}");

        // Acknowledged on the stream, as over REST.
        let id = alarm["id"].as_u64().unwrap();
        send_json(
            &mut ws,
            json!({"type": "command", "id": 7, "op": "alarm-ack", "body": {"alarm": id}}),
        )
        .await;
        let reply = wait_for(&mut ws, EVENT, "the reply", |m| {
            m["type"] == "reply" && m["id"] == 7
        })
        .await;
        assert_eq!(reply["ok"], true, "{reply:#}");
        assert_eq!(reply["result"]["acknowledged_by"], "panel");
        assert_eq!(reply["result"]["count"], 2);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_fault_raises_an_alarm_with_the_manuals_help_cleared_by_a_fault_reset() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&ConfigBuilder::four_drives().toml()).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=feeder", None).await;
        d.sim()
            .inject_fault(4, drivegate::drive::Fault::OverTemperature)
            .unwrap();
        let raised = wait_for(&mut ws, EVENT, "the feeder's fault alarm", |m| {
            m["type"] == "alarm-raised" && m["alarm"]["kind"] == "fault"
        })
        .await;
        let alarm = &raised["alarm"];
        assert_eq!(
            (alarm["drive"].as_str(), alarm["code"].as_u64()),
            (Some("feeder"), Some(4))
        );
        assert!(
            alarm["text"].as_str().unwrap().contains("over-temperature"),
            "{alarm:#}"
        );
        let help = alarm["help"].as_str().unwrap();
        assert!(
            help.contains("manual 1.7") && help.contains("CONFIG 0x8"),
            "{help}"
        );
        assert_eq!(alarm["active"], true);

        // The cause removed and the fault reset: the alarm clears.
        d.sim().clear_fault(4).unwrap();
        api.post_empty("/api/v1/drives/feeder/commands/fault-reset")
            .await
            .expect(200);
        let cleared = wait_for(&mut ws, EVENT, "the fault alarm cleared", |m| {
            m["type"] == "alarm-cleared" && m["alarm"]["id"] == alarm["id"]
        })
        .await;
        assert_eq!(cleared["alarm"]["active"], false);
        let list = api.get("/api/v1/alarms?active=true").await.expect(200);
        assert_eq!(list["active"], 0, "{list:#}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_whose_adapter_is_missing_is_an_alarm() {
    bounded(LIMIT, async {
        let toml = ConfigBuilder::new()
            .bus("unplugged", |b| {
                b.port("/dev/ttyUSB-drivegate-alarm-test-missing")
                    .drive(1, "far")
            })
            .toml();
        let d = TestDaemon::start_no_wait(&toml).await;
        let api = Api::new(d.http, None);
        let start = Instant::now();
        let alarm = loop {
            let list = api.get("/api/v1/alarms?active=true").await.expect(200);
            if let Some(a) = list["alarms"]
                .as_array()
                .unwrap()
                .iter()
                .find(|a| a["kind"] == "bus-down")
            {
                break a.clone();
            }
            assert!(start.elapsed() < EVENT, "no bus-down alarm: {list:#}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert_eq!(
            (alarm["bus"].as_str(), alarm["drive"].as_str()),
            (Some("unplugged"), None)
        );
        assert!(
            alarm["text"]
                .as_str()
                .unwrap()
                .contains("ttyUSB-drivegate-alarm-test-missing"),
            "{alarm:#}"
        );
        assert!(
            alarm["help"].as_str().unwrap().contains("dialout"),
            "{alarm:#}"
        );
        d.stop().await;
    })
    .await;
}

/// The newest alarm of `drive` once one satisfies `want`, within
/// [`EVENT`].
async fn alarm_where(api: &Api, drive: &str, what: &str, want: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let list = api
            .get(&format!("/api/v1/alarms?drive={drive}"))
            .await
            .expect(200);
        if let Some(a) = list["alarms"].as_array().and_then(|l| l.first())
            && want(a)
        {
            return a.clone();
        }
        assert!(start.elapsed() < EVENT, "no {what}: {list:#}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_that_never_answered_is_an_alarm_naming_the_baud_rate_and_address() {
    bounded(LIMIT, async {
        // Line 1: the conveyor (1) answers, the belt (2) never does (as at
        // a wrong address). Line 2: its adapter is missing.
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-line1");
        let sim = ExternalSim::start(&link, "1-2", &["--silent-units", "2"]).await;
        let toml = ConfigBuilder::new()
            .bus("line1", |b| {
                // A silent drive probed often, so the test sees it probed
                // in vain after the adapter is back.
                b.port(&link.display().to_string())
                    .keys("offline_backoff_ms = 200\noffline_backoff_max_ms = 400")
                    .drive(1, "conveyor")
                    .drive(2, "belt")
            })
            .bus("line2", |b| {
                b.port("/dev/drivegate-test-no-such-adapter")
                    .drive(1, "lift")
            })
            .toml();
        let d = TestDaemon::start_no_wait(&toml).await;
        let api = Api::new(d.http, None);
        let raised = alarm_where(&api, "belt", "the belt's alarm", |a| a["active"] == true).await;
        let alarm = &raised;
        assert_eq!(alarm["kind"], "never-answered", "{raised:#}");
        assert_eq!(alarm["active"], true);
        let text = alarm["text"].as_str().unwrap();
        for words in [
            "drive belt (bus line1, unit 2) has never answered: no answer since bus line1 opened",
            "check the baud rate (the bus runs at 115200 baud) and the unit address (2)",
        ] {
            assert!(text.contains(words), "{words:?} not in {text}");
        }
        let help = alarm["help"].as_str().unwrap();
        assert!(
            help.contains("baud rate")
                && help.contains("unit address")
                && help.contains("--try-bauds"),
            "{help}"
        );
        let id = alarm["id"].as_u64().unwrap();
        let active = |d: &TestDaemon, kind: &str| {
            metric(
                &d.metrics.render(),
                &format!("drivegate_alarms_active{{kind=\"{kind}\"}}"),
            )
        };
        assert_eq!(active(&d, "never-answered"), 1.0);
        // Not also "offline": it never stopped, it never started.
        assert!(alarms_of(&api, "belt", "offline").await.is_empty());
        assert!(
            alarms_of(&api, "conveyor", "never-answered")
                .await
                .is_empty()
        );
        // The lift's bus is down: that is the bus's alarm, not the drive's.
        assert!(alarms_of(&api, "lift", "never-answered").await.is_empty());
        assert!(alarms_of(&api, "lift", "offline").await.is_empty());
        assert_eq!(active(&d, "bus-down"), 1.0);

        // The adapter unplugged and back, the belt still silent: the same
        // alarm, still active, none added.
        sim.kill().await;
        eventually(EVENT, "line1's bus-down alarm", || {
            (active(&d, "bus-down") == 2.0).then_some(())
        })
        .await;
        let sim = ExternalSim::start(&link, "1-2", &["--silent-units", "2"]).await;
        eventually(EVENT, "line1 back", || {
            (active(&d, "bus-down") == 1.0).then_some(())
        })
        .await;
        let (_, line1) = d.plant.drive("belt").unwrap();
        let polls = line1.stats().poll_failures;
        eventually(EVENT, "the belt polled in vain again", || {
            (line1.stats().poll_failures > polls + 1).then_some(())
        })
        .await;
        let belt = alarms_of(&api, "belt", "never-answered").await;
        assert_eq!(belt.len(), 1, "{belt:#?}");
        assert_eq!(
            (belt[0]["id"].as_u64(), &belt[0]["active"]),
            (Some(id), &json!(true))
        );

        // The belt answers (its address put right, here: the adapter with
        // both drives answering): the alarm clears.
        sim.kill().await;
        let _sim = ExternalSim::start(&link, "1-2", &[]).await;
        let cleared = alarm_where(&api, "belt", "the alarm cleared", |a| {
            a["id"] == id && a["active"] == false
        })
        .await;
        assert!(cleared["cleared_at"].is_string(), "{cleared:#}");
        assert_eq!(active(&d, "never-answered"), 0.0);
        assert!(alarms_of(&api, "belt", "offline").await.is_empty());
        d.stop().await;
    })
    .await;
}
