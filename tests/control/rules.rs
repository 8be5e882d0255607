//! The control core's rules through each face: a save to flash, a factory
//! reset, address setting and calibration are refused while the motor
//! turns, over HTTP and the stream (override `"force": true`) and over
//! Modbus TCP (exception 0x06; override `allow_saves_while_moving` of the
//! client's network), checked with raw frames, pymodbus and mbpoll; and a
//! setpoint without a lease from any face takes over from the stop of a
//! lease that ended.

use std::time::{Duration, Instant};

use crate::support::api::{Api, connect, next_json, wait_for, ws_command};
use crate::support::config::ConfigBuilder;
use crate::support::modbus_tcp::{Raw, four_drives_with, mbpoll, pymodbus, write};
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(90);
const CONFIG: u16 = 0x0002;
const SPEED_TD_R_SAVE_FLAG: u16 = 0x001C;

/// The conveyor (unit 1) turning at 200 rpm, no lease.
async fn conveyor_turning(d: &TestDaemon, api: &Api) {
    api.activate_in("conveyor", "speed").await;
    api.put(
        "/api/v1/drives/conveyor/setpoint",
        json!({"speed_rpm": 200}),
    )
    .await
    .expect(200);
    eventually(LIMIT, "the conveyor turning", || {
        (d.sim().drive(1)?.speed_rpm > 50.0).then_some(())
    })
    .await;
}

/// The conveyor standing still.
async fn conveyor_stopped(d: &TestDaemon, api: &Api) {
    api.put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": 0}))
        .await
        .expect(200);
    eventually(LIMIT, "the conveyor standing", || {
        (d.sim().drive(1)?.speed_rpm.abs() < 0.5).then_some(())
    })
    .await;
    // And the poll the still-check reads says so too.
    eventually(LIMIT, "a standstill status", || {
        let (_, bus) = d.plant.drive("conveyor").ok()?;
        (bus.drive(1)?.status?.speed_rpm == 0).then_some(())
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn writes_that_need_standstill_are_refused_over_http_and_the_stream() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        conveyor_turning(&d, &api).await;
        let before = d.sim().drive(1).unwrap();

        // HTTP: a save, calibration, factory reset, address setting.
        let p = api
            .put(
                "/api/v1/drives/conveyor/protection",
                json!({"limit_a": 8.0, "stall_ms": 2000, "save": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        let detail = p["detail"].as_str().unwrap();
        assert!(
            detail.contains("turns at")
                && detail.contains("a save to flash")
                && detail.contains("\"force\": true"),
            "{detail}"
        );
        for command in ["calibrate", "fine-tune", "factory-reset"] {
            api.post_empty(&format!("/api/v1/drives/conveyor/commands/{command}"))
                .await
                .expect_problem(409, "drive-moving");
        }
        let p = api
            .post(
                "/api/v1/buses/sim/address",
                json!({"address": 9, "only_drive_on_bus": true}),
            )
            .await
            .expect_problem(409, "drive-moving");
        assert!(
            p["detail"].as_str().unwrap().contains("address setting"),
            "{p:#}"
        );

        // The stream: the same rules, the same words.
        let mut ws = connect(d.http, "", None).await;
        let r = ws_command(
            &mut ws,
            1,
            "speed-ramp",
            "conveyor",
            json!({"alpha": 6000, "save": true}),
        )
        .await;
        assert_eq!(r["ok"], false, "{r:#}");
        assert_eq!(r["problem"]["type"], "urn:drivegate:problem:drive-moving");
        let r = ws_command(&mut ws, 2, "calibrate", "conveyor", json!({})).await;
        assert_eq!(r["problem"]["type"], "urn:drivegate:problem:drive-moving");
        let r = ws_command(&mut ws, 3, "factory-reset", "conveyor", json!({})).await;
        assert_eq!(r["problem"]["type"], "urn:drivegate:problem:drive-moving");

        // Nothing reached the drive.
        let after = d.sim().drive(1).unwrap();
        assert_eq!(after.saves_while_moving, 0);
        assert_eq!(
            (after.flash, after.settings),
            (before.flash, before.settings)
        );
        assert_eq!(after.procedure, None);
        assert_eq!(after.address, 1);

        // The override: "force": true, over HTTP and over the stream.
        api.put(
            "/api/v1/drives/conveyor/inertia",
            json!({"ratio": 4, "save": true, "force": true}),
        )
        .await
        .expect(200);
        let r = ws_command(
            &mut ws,
            4,
            "inertia",
            "conveyor",
            json!({"ratio": 5, "save": true, "force": true}),
        )
        .await;
        assert_eq!(r["ok"], true, "{r:#}");
        let after = d.sim().drive(1).unwrap();
        assert_eq!(after.saves_while_moving, 2);
        assert_eq!(after.flash.settings.inertia_ratio, 5);

        // At standstill, no override is needed.
        conveyor_stopped(&d, &api).await;
        api.put(
            "/api/v1/drives/conveyor/inertia",
            json!({"ratio": 3, "save": true}),
        )
        .await
        .expect(200);
        assert_eq!(d.sim().drive(1).unwrap().flash.settings.inertia_ratio, 3);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn writes_that_need_standstill_are_refused_over_modbus_tcp_with_0x06() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let addr = d.modbus_tcp.unwrap();
        conveyor_turning(&d, &api).await;
        let before = d.sim().drive(1).unwrap();
        let mut plc = Raw::connect(addr).await;

        // A save flag on its own, calibration, fine-tuning, factory reset,
        // and the address (manual 1.2), as single writes.
        for (register, value) in [
            (SPEED_TD_R_SAVE_FLAG, 1),
            (CONFIG, 0x2),
            (CONFIG, 0x3),
            (CONFIG, 0x6),
            (0x0000, 9),
        ] {
            assert_eq!(
                plc.ask(1, &write(register, value)).await,
                [0x86, 0x06],
                "register 0x{register:04X} = {value}"
            );
        }
        // The inertia message with its save flag, as a block (pymodbus).
        let out = pymodbus(addr, &["write-multiple", "1", "0x24", "7,1"]).await;
        assert_eq!(out["exception"], 6, "{out}");
        // The protection message with its save flag (mbpoll).
        let (ok, text) = mbpoll(
            addr,
            &["-a", "1", "-0", "-r", "12", "-t", "4"],
            &["400", "2500", "1"],
        )
        .await;
        assert!(!ok && text.to_lowercase().contains("busy"), "{text}");
        let after = d.sim().drive(1).unwrap();
        assert_eq!(after.saves_while_moving, 0);
        assert_eq!(
            (after.flash, after.settings),
            (before.flash, before.settings)
        );
        assert_eq!((after.procedure, after.address), (None, 1));

        // The same save without its flag, and a setpoint, are not refused.
        assert_eq!(plc.ask(1, &write(0x0024, 7)).await, write(0x0024, 7));
        assert_eq!(plc.ask(1, &write(0x0006, 180)).await, write(0x0006, 180));

        // At standstill the save goes through.
        conveyor_stopped(&d, &api).await;
        let out = pymodbus(addr, &["write-multiple", "1", "0x24", "6,1"]).await;
        assert_eq!(out["written"], true, "{out}");
        assert_eq!(d.sim().drive(1).unwrap().flash.settings.inertia_ratio, 6);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_network_allowed_to_save_while_moving_is_not_refused() {
    tokio::time::timeout(LIMIT, async {
        let toml = four_drives_with(
            "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"admin\"\nallow_saves_while_moving = true",
        );
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        conveyor_turning(&d, &api).await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        let save = write(SPEED_TD_R_SAVE_FLAG, 1);
        assert_eq!(plc.ask(1, &save).await, save);
        assert_eq!(d.sim().drive(1).unwrap().saves_while_moving, 1);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// FOUR_DRIVES whose offline drives are polled again only after a minute:
/// once a drive answers again, nothing but a stop's own retry timer tries
/// it, so a setpoint sent at once lands long before that.
fn slow_offline_polls() -> String {
    ConfigBuilder::four_drives()
        .with_bus("sim", |b| {
            b.keys("offline_backoff_ms = 60000\noffline_backoff_max_ms = 60000")
        })
        .toml()
}

/// The attempts of `drive`'s failing stop, from the no-lease problem (the
/// lease has ended: a renewal would otherwise keep it).
async fn failed_attempts(api: &Api, drive: &str) -> u32 {
    let p = api
        .post_empty(&format!("/api/v1/drives/{drive}/lease/renew"))
        .await
        .expect_problem(409, "no-lease");
    let detail = p["detail"].as_str().unwrap().to_string();
    detail
        .split_once(" attempt(s) failed")
        .and_then(|(head, _)| head.rsplit(' ').next()?.parse().ok())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_without_a_lease_over_http_takes_over_a_failing_stop() {
    a_setpoint_without_a_lease_takes_over_a_failing_stop("conveyor", 1, "over HTTP").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_without_a_lease_over_the_stream_takes_over_a_failing_stop() {
    a_setpoint_without_a_lease_takes_over_a_failing_stop(
        "turntable",
        3,
        "over the WebSocket stream",
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_without_a_lease_over_modbus_tcp_takes_over_a_failing_stop() {
    a_setpoint_without_a_lease_takes_over_a_failing_stop("feeder", 4, "over Modbus TCP").await;
}

/// A leased setpoint to `drive`, whose drive then stops answering: the
/// lease runs out and its stop fails again and again, until a setpoint
/// without a lease from `face` reaches the drive first.
async fn a_setpoint_without_a_lease_takes_over_a_failing_stop(drive: &str, unit: u8, face: &str) {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&slow_offline_polls()).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let mut watch = connect(d.http, "?drives=all", None).await;
        assert_eq!(next_json(&mut watch, LIMIT).await["type"], "subscribed");
        let mut ws = connect(d.http, "", None).await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;

        api.activate_in(drive, "speed").await;
        api.put(
            &format!("/api/v1/drives/{drive}/setpoint"),
            json!({"speed_rpm": 100, "lease_ms": 300}),
        )
        .await
        .expect(200);
        // The drive stops answering; the lease runs out, and its stop
        // fails again and again.
        sim.set_silent(unit, true);
        let path = format!("/api/v1/drives/{drive}");
        while !api.get(&path).await.expect(200)["lease"].is_null() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let start = Instant::now();
        while failed_attempts(&api, drive).await < 4 {
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "{drive}: the stop was not retried"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // The next try is 2 s away. The drive answers again, and a
        // setpoint without a lease reaches it first.
        sim.set_silent(unit, false);
        match face {
            "over HTTP" => {
                api.put(
                    &format!("/api/v1/drives/{drive}/setpoint"),
                    json!({"speed_rpm": 150}),
                )
                .await
                .expect(200);
            }
            "over the WebSocket stream" => {
                let r = ws_command(
                    &mut ws,
                    u64::from(unit),
                    "setpoint",
                    drive,
                    json!({"speed_rpm": 150}),
                )
                .await;
                assert_eq!(r["ok"], true, "{r:#}");
            }
            _ => {
                let pdu = write(0x0006, 150);
                assert_eq!(plc.ask(unit, &pdu).await, pdu);
            }
        }
        let settled = wait_for(&mut watch, LIMIT, "lease-stop", |v| {
            v["type"] == "lease-stop" && v["drive"] == drive
        })
        .await;
        assert_eq!(settled["stopped"], false, "{settled:#}");
        let result = settled["result"].as_str().unwrap();
        assert!(
            result.contains("a setpoint without a lease from")
                && result.contains(&format!("{face} took over")),
            "{result}"
        );
        // The stop is not tried again: the setpoint stands.
        tokio::time::sleep(Duration::from_millis(2500)).await;
        assert_eq!(sim.drive(unit).unwrap().setpoints.speed_rpm, 150, "{drive}");
        let p = api
            .post_empty(&format!("/api/v1/drives/{drive}/lease/renew"))
            .await
            .expect_problem(409, "no-lease");
        assert!(
            p["detail"].as_str().unwrap().contains("is not tried again"),
            "{p:#}"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
