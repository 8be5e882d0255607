//! The bus engine against the built-in simulator through a real pty:
//! polling, commands, priorities, offline drives, unplug and replug.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::time::Duration;

use common::{FOUR_DRIVES, TestDaemon};
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drives_are_polled_and_commands_confirmed() {
    let d = TestDaemon::start(FOUR_DRIVES).await;
    let (drive, bus) = d.plant.drive("conveyor").unwrap();
    let unit = drive.unit;
    let reply = bus
        .execute(
            unit,
            &DriveRequest::Config(ConfigCommand::Activate),
            JobOptions::default(),
        )
        .await
        .unwrap();
    assert_eq!(reply, DriveReply::Confirmed);
    bus.execute(
        unit,
        &DriveRequest::Config(ConfigCommand::SpeedMode),
        JobOptions::default(),
    )
    .await
    .unwrap();
    bus.execute(
        unit,
        &DriveRequest::Speed { rpm: 100 },
        JobOptions::default(),
    )
    .await
    .unwrap();
    let status = common::eventually(Duration::from_secs(5), "speed near 100 rpm", || {
        bus.drive(unit)
            .and_then(|s| s.status)
            .filter(|s| (s.speed_rpm - 100).abs() <= 2)
    })
    .await;
    assert!(status.active());
    let stats = bus.stats();
    assert!(stats.polls > 10, "{stats:?}");
    assert_eq!(d.sim().stats().gap_violations, 0);
    d.stop().await;
}
