//! Every command over real HTTP against the daemon on the simulator, checked
//! against the simulated drive's truth: activation, modes, setpoints (the
//! motor reaches them), brake, set-zero, calibration, fine-tuning, the
//! resets, protection, ramps (by alpha and by time), inertia, saves to flash
//! and RS-485 control.

use std::time::{Duration, Instant};

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::drive::{Fault, Mode};
use drivegate::sim::model::Procedure;
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(40);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn activate_mode_setpoint_and_the_motor_follows() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();

        // Activate: the reply says what was written, the drive is active.
        let r = api.command("conveyor", "activate").await;
        assert_eq!(r["command"], "activate");
        assert_eq!(r["written"][0]["register"], "CONFIG");
        assert_eq!(r["written"][0]["raw"], 0);
        assert_eq!(r["priority"], "command");
        assert!(sim.drive(1).unwrap().active);

        // Speed mode, 100 rpm: the status shows the motor reach it.
        let r = api
            .put("/api/v1/drives/conveyor/mode", json!({"mode": "speed"}))
            .await
            .expect(200);
        assert_eq!(r["written"][0]["raw"], 0xA);
        assert_eq!(sim.drive(1).unwrap().mode, Mode::Speed);
        let r = api
            .put(
                "/api/v1/drives/conveyor/setpoint",
                json!({"speed_rpm": 100}),
            )
            .await
            .expect(200);
        assert_eq!(r["written"][0]["register"], "SPEED_REF");
        assert_eq!(
            (
                r["written"][0]["value"].as_f64(),
                r["written"][0]["raw"].as_i64()
            ),
            (Some(100.0), Some(100))
        );
        assert_eq!(r["written"][0]["unit"], "rpm");
        assert!(r["lease"].is_null());
        assert_eq!(sim.drive(1).unwrap().setpoints.speed_rpm, 100);
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let s = api.get("/api/v1/drives/conveyor/status").await.expect(200);
            if (s["speed_rpm"].as_i64().unwrap() - 100).abs() <= 2 {
                assert_eq!(s["mode"], "speed");
                assert_eq!(s["active"], true);
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the motor did not reach 100 rpm: {s:#}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }

        // Brake: emergency priority, the motor stops and is held.
        let r = api.command("conveyor", "brake").await;
        assert_eq!(r["priority"], "emergency");
        assert_eq!(r["written"][0]["raw"], 5);
        assert!(sim.drive(1).unwrap().braking);
        eventually(Duration::from_secs(5), "the motor to stop", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;

        // Position mode on the turntable: 90 degrees.
        api.activate_in("turntable", "position").await;
        let r = api
            .put(
                "/api/v1/drives/turntable/setpoint",
                json!({"position_deg": 90.0}),
            )
            .await
            .expect(200);
        assert_eq!(
            (
                r["written"][0]["register"].as_str(),
                r["written"][0]["raw"].as_i64()
            ),
            (Some("POSITION_REF"), Some(9000))
        );

        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let s = api.get("/api/v1/drives/turntable/status").await.expect(200);
            if (s["angle_deg"].as_f64().unwrap() - 90.0).abs() < 0.5 {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the turntable did not reach 90 deg: {s:#}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // Set zero: here is the new 0.
        api.command("turntable", "set-zero").await;
        let s = eventually(
            Duration::from_secs(3),
            "angle near 0 after set-zero",
            || {
                let s = d.plant.buses()[0].handle.drive(3)?.status?;
                (s.angle_deg().abs() < 0.5).then_some(s)
            },
        )
        .await;
        assert_eq!(s.mode(), Mode::Position);

        // Torque mode on the feeder: amps and raw counts.
        api.activate_in("feeder", "torque").await;
        let r = api
            .put("/api/v1/drives/feeder/setpoint", json!({"torque_a": 0.5}))
            .await
            .expect(200);
        assert_eq!(
            (
                r["written"][0]["raw"].as_i64(),
                r["written"][0]["unit"].as_str()
            ),
            (Some(64), Some("A"))
        );
        assert_eq!(sim.drive(4).unwrap().setpoints.current_counts, 64);
        api.put(
            "/api/v1/drives/feeder/setpoint",
            json!({"torque_counts": -32}),
        )
        .await
        .expect(200);
        assert_eq!(sim.drive(4).unwrap().setpoints.current_counts, -32);
        api.put(
            "/api/v1/drives/feeder/setpoint",
            json!({"torque_counts": 0}),
        )
        .await
        .expect(200);

        // A speed setpoint in position mode is stored for when the mode
        // changes; the turntable holds its position meanwhile.
        api.put(
            "/api/v1/drives/turntable/setpoint",
            json!({"speed_rpm": 10}),
        )
        .await
        .expect(200);
        assert_eq!(sim.drive(3).unwrap().setpoints.speed_rpm, 10);
        assert_eq!(sim.drive(3).unwrap().mode, Mode::Position);

        // Deactivate: no more setpoints.
        api.command("conveyor", "deactivate").await;
        assert!(!sim.drive(1).unwrap().active);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ramp_set_by_time_shapes_the_move() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();

        // 1 s to 200 rpm on the conveyor (gear 3.75): formula (2) gives alpha.
        let r = api
            .put(
                "/api/v1/drives/conveyor/ramps/speed",
                json!({"time_s": 1.0, "step_rpm": 200}),
            )
            .await
            .expect(200);
        let alpha = r["alpha"].as_u64().unwrap();
        let expected = (4.0 * 3.75 * 200.0 / 9.55_f64 / 1.0).round() as u64;
        assert_eq!(alpha, expected);
        assert!((r["time_s"].as_f64().unwrap() - 1.0).abs() < 0.01, "{r:#}");
        assert_eq!(r["gear_ratio"], 3.75);
        assert_eq!(r["saved"], false);
        let w = r["written"].as_array().unwrap();
        assert_eq!(w.len(), 3);
        assert_eq!(w[0]["register"], "SPEED_TD_R_HIGH");
        assert_eq!(w[1]["raw"].as_u64(), Some(alpha & 0xFFFF));
        assert_eq!(sim.drive(1).unwrap().settings.speed_alpha, alpha as u32);
        assert_ne!(
            sim.drive(1).unwrap().flash.settings.speed_alpha,
            alpha as u32
        );

        api.activate_in("conveyor", "speed").await;
        let start = Instant::now();
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 200}),
        )
        .await
        .expect(200);
        eventually(Duration::from_secs(6), "the conveyor at 195 rpm", || {
            (sim.drive(1)?.speed_rpm >= 195.0).then_some(())
        })
        .await;
        let took = start.elapsed();
        // The ramp cannot be faster than what was asked (lower bound only).
        assert!(
            took >= Duration::from_millis(800),
            "reached 195 rpm after {took:?}"
        );

        // Position ramp by alpha, with the step to get its time.
        let r = api
            .put(
                "/api/v1/drives/turntable/ramps/position",
                json!({"alpha": 200, "step_deg": 180}),
            )
            .await
            .expect(200);
        assert_eq!(r["alpha"], 200);
        assert!(
            (r["time_s"].as_f64().unwrap() - 0.2507).abs() < 0.001,
            "{r:#}"
        );
        assert_eq!(sim.drive(3).unwrap().settings.position_alpha, 200);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn settings_are_written_saved_and_factory_reset() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();

        // Protection in amps, saved (the motor stands still).
        let r = api
            .put(
                "/api/v1/drives/lift/protection",
                json!({"limit_a": 10.0, "stall_ms": 2000, "save": true}),
            )
            .await
            .expect(200);
        assert_eq!(r["saved"], true);
        let raws: Vec<i64> = r["written"]
            .as_array()
            .unwrap()
            .iter()
            .map(|w| w["raw"].as_i64().unwrap())
            .collect();
        assert_eq!(raws, [1280, 2000, 1]);
        let lift = sim.drive(2).unwrap();
        assert_eq!(
            (lift.settings.stall_current, lift.settings.stall_duration_ms),
            (1280, 2000)
        );
        assert_eq!(lift.flash.settings.stall_current, 1280);
        // ... and in raw counts, not saved.
        api.put(
            "/api/v1/drives/lift/protection",
            json!({"limit_counts": 1000, "stall_ms": 500}),
        )
        .await
        .expect(200);
        let lift = sim.drive(2).unwrap();
        assert_eq!(lift.settings.stall_current, 1000);
        assert_eq!(lift.flash.settings.stall_current, 1280);

        // Speed ramp by alpha, saved; inertia, saved.
        api.put(
            "/api/v1/drives/lift/ramps/speed",
            json!({"alpha": 5000, "save": true}),
        )
        .await
        .expect(200);
        let r = api
            .put(
                "/api/v1/drives/lift/inertia",
                json!({"ratio": 5, "save": true}),
            )
            .await
            .expect(200);
        assert_eq!(r["written"][0]["register"], "INERTIA_RATIO");
        let lift = sim.drive(2).unwrap();
        assert_eq!(
            (
                lift.flash.settings.speed_alpha,
                lift.flash.settings.inertia_ratio
            ),
            (5000, 5)
        );
        assert_eq!(lift.saves_while_moving, 0);

        // RS-485 control off and on.
        let r = api
            .put(
                "/api/v1/drives/lift/rs485-control",
                json!({"enabled": false}),
            )
            .await
            .expect(200);
        assert_eq!(
            (
                r["written"][0]["register"].as_str(),
                r["written"][0]["raw"].as_i64()
            ),
            (Some("USE_485_CONTROL"), Some(0))
        );
        assert!(!sim.drive(2).unwrap().rs485_control);
        api.put(
            "/api/v1/drives/lift/rs485-control",
            json!({"enabled": true}),
        )
        .await
        .expect(200);
        assert!(sim.drive(2).unwrap().rs485_control);

        // Factory reset restores ramps, protection and inertia, in flash too.
        let r = api.command("lift", "factory-reset").await;
        assert_eq!(r["written"][0]["raw"], 6);
        let lift = sim.drive(2).unwrap();
        assert_eq!(lift.settings, drivegate::sim::model::Settings::FACTORY);
        assert_eq!(
            lift.flash.settings,
            drivegate::sim::model::Settings::FACTORY
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calibration_fine_tuning_and_the_resets() {
    tokio::time::timeout(LIMIT, async {
        let config = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.sim("calibrated = false"))
            .toml();
        let d = TestDaemon::start(&config).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();

        let s = api.get("/api/v1/drives/lift/status").await.expect(200);
        assert_eq!(s["calibrated"], false);
        let r = api.command("lift", "calibrate").await;
        assert!(r["note"].as_str().unwrap().contains("4 s"));
        assert_eq!(
            sim.drive(2).unwrap().procedure,
            Some(Procedure::Calibrating)
        );
        // The calibrated flag shows in the status when it is done (about 4 s).
        eventually(Duration::from_secs(10), "calibrated flag", || {
            let s = d.plant.buses()[0].handle.drive(2)?.status?;
            s.calibrated().then_some(())
        })
        .await;
        // Fine-tuning, like calibration, needs the motor standing still:
        // calibration's last nudge settles first.
        eventually(Duration::from_secs(10), "the lift standing", || {
            let s = d.plant.buses()[0].handle.drive(2)?.status?;
            (s.speed_rpm == 0).then_some(())
        })
        .await;
        api.command("lift", "fine-tune").await;
        assert_eq!(sim.drive(2).unwrap().procedure, Some(Procedure::FineTuning));

        // A fault, its cause removed, then a fault reset clears it.
        sim.inject_fault(1, Fault::Encoder).unwrap();
        eventually(Duration::from_secs(3), "the encoder fault", || {
            let s = d.plant.buses()[0].handle.drive(1)?.status?;
            (s.fault() == Fault::Encoder).then_some(())
        })
        .await;
        sim.clear_fault(1).unwrap();
        api.command("conveyor", "fault-reset").await;
        assert_eq!(sim.drive(1).unwrap().fault, Fault::None);

        // A soft reset reboots the drive; it answers again afterwards.
        let r = api.command("feeder", "soft-reset").await;
        assert!(r["note"].as_str().unwrap().contains("restarts"));
        let fresh = async {
            loop {
                let r = api.get("/api/v1/drives/feeder/status?fresh=true").await;
                if r.status == 200 {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        };
        tokio::time::timeout(Duration::from_secs(5), fresh)
            .await
            .expect("the feeder answers after its reset");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
