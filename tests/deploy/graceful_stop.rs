//! The graceful stop (what SIGTERM runs), checked against the simulator's
//! truth: moving drives get the configured safe-stop action, standing ones
//! are left alone, no frame is cut on the wire, and new work is refused.

use std::sync::Arc;
use std::time::Duration;

use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::{TestDaemon, eventually};
use drivegate::bus::BusError;
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{ConfigCommand, DriveRequest};
use drivegate::plant::{Plant, SimRef};

const LIMIT: Duration = Duration::from_secs(30);

fn with_safety(action: &str) -> String {
    ConfigBuilder::four_drives()
        .section("safety", &format!("on_shutdown = \"{action}\""))
        .toml()
}

fn sim(plant: &Plant) -> SimRef {
    SimRef::of(plant.buses()[0].clone()).unwrap()
}

/// Starts the daemon, runs the conveyor (unit 1) at 100 rpm until the
/// simulated motor is there, and returns the daemon and its plant (kept
/// alive past the stop so the simulator can still be asked).
async fn running_conveyor(toml: &str) -> (TestDaemon, Arc<Plant>) {
    let d = TestDaemon::start(toml).await;
    let (drive, bus) = d.plant.drive("conveyor").unwrap();
    for request in [
        DriveRequest::Config(ConfigCommand::Activate),
        DriveRequest::Config(ConfigCommand::SpeedMode),
        DriveRequest::Speed { rpm: 100 },
    ] {
        bus.execute(drive.unit, &request, JobOptions::default())
            .await
            .unwrap();
    }
    let plant = d.plant.clone();
    eventually(
        Duration::from_secs(10),
        "conveyor at 100 rpm, polled",
        || {
            let truth = sim(&plant).drive(1)?;
            let polled = bus.drive(1)?.status?;
            ((truth.speed_rpm - 100.0).abs() < 2.0 && polled.speed_rpm > 90).then_some(())
        },
    )
    .await;
    (d, plant)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_speed_stops_moving_drives_and_refuses_new_work() {
    bounded(LIMIT, async {
        let (d, plant) = running_conveyor(&with_safety("zero-speed")).await;
        let lift_before = sim(&plant).drive(2).unwrap();
        d.stop().await;

        let conveyor = sim(&plant).drive(1).unwrap();
        assert_eq!(conveyor.setpoints.speed_rpm, 0, "zero speed was sent");
        assert!(!conveyor.braking);
        // The ramp brings the motor down after the daemon has gone.
        eventually(Duration::from_secs(10), "conveyor standing", || {
            (sim(&plant).drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        // A standing drive got nothing.
        let lift = sim(&plant).drive(2).unwrap();
        assert_eq!(lift.setpoints, lift_before.setpoints);
        assert_eq!(lift.mode, lift_before.mode);
        // Every frame on the wire was complete and well spaced.
        let wire = sim(&plant).stats();
        assert_eq!(wire.truncated_frames, 0, "{wire}");
        assert_eq!(wire.bad_crc_requests, 0, "{wire}");
        assert_eq!(wire.gap_violations, 0, "{wire}");
        // No new work once stopped.
        let handle = &plant.buses()[0].handle;
        let refused = handle
            .execute(1, &DriveRequest::Speed { rpm: 50 }, JobOptions::default())
            .await;
        assert!(
            matches!(refused, Err(BusError::ShuttingDown)),
            "{refused:?}"
        );
        let requests = wire.requests;
        tokio::time::sleep(Duration::from_millis(200)).await;
        assert_eq!(sim(&plant).stats().requests, requests, "the bus is quiet");
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn brake_engages_the_emergency_brake() {
    bounded(LIMIT, async {
        let (d, plant) = running_conveyor(&with_safety("brake")).await;
        d.stop().await;
        let conveyor = sim(&plant).drive(1).unwrap();
        assert!(conveyor.braking, "emergency brake engaged");
        eventually(Duration::from_secs(5), "conveyor held", || {
            (sim(&plant).drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        // Only moving drives are braked.
        assert!(!sim(&plant).drive(3).unwrap().braking);
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn none_leaves_the_drives_running() {
    bounded(LIMIT, async {
        let (d, plant) = running_conveyor(&with_safety("none")).await;
        d.stop().await;
        tokio::time::sleep(Duration::from_millis(300)).await;
        let conveyor = sim(&plant).drive(1).unwrap();
        assert_eq!(conveyor.setpoints.speed_rpm, 100);
        assert!(!conveyor.braking);
        assert!(
            (conveyor.speed_rpm - 100.0).abs() < 2.0,
            "{}",
            conveyor.speed_rpm
        );
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_started_after_its_last_poll_is_still_stopped() {
    bounded(LIMIT, async {
        // Polled once an hour: the polled copy says "standing, open loop"
        // while the motor is actually running in torque mode.
        let toml = with_safety("zero-speed")
            .replace("retries = 1", "retries = 1\npoll_interval_ms = 3600000");
        let d = TestDaemon::start(&toml).await;
        let (drive, bus) = d.plant.drive("conveyor").unwrap();
        for request in [
            DriveRequest::Config(ConfigCommand::Activate),
            DriveRequest::Config(ConfigCommand::TorqueMode),
            DriveRequest::Torque { counts: 256 },
        ] {
            bus.execute(drive.unit, &request, JobOptions::default())
                .await
                .unwrap();
        }
        let cached = bus.drive(1).unwrap().status.unwrap();
        assert_eq!(
            cached.mode(),
            drivegate::drive::Mode::OpenLoop,
            "the polled copy is stale"
        );
        let plant = d.plant.clone();
        eventually(Duration::from_secs(5), "the motor turning", || {
            (sim(&plant).drive(1)?.speed_rpm.abs() > 5.0).then_some(())
        })
        .await;
        d.stop().await;
        // The stop read the real mode and zeroed the torque setpoint.
        let truth = sim(&plant).drive(1).unwrap();
        assert_eq!(truth.setpoints.current_counts, 0, "{truth:?}");
    })
    .await;
}
