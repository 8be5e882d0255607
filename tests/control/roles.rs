//! Roles for Modbus TCP clients by network: a plant lets the PLC network
//! run the drives without letting it re-address or re-tune them. The test
//! client comes from 127.0.0.1; each daemon gives that network another
//! role. Checked with raw frames, pymodbus and mbpoll.

use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::modbus_tcp::{Raw, four_drives_with, mbpoll, pymodbus, read, write};

const LIMIT: Duration = Duration::from_secs(60);
const CONFIG: u16 = 0x0002;

fn with_role(role: &str) -> String {
    four_drives_with(&format!(
        "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"{role}\""
    ))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_network_runs_the_drives_but_cannot_commission_them() {
    tokio::time::timeout(LIMIT, async {
        // 127.0.0.0/8 is also in the default allowed_networks (admin): the
        // more specific entry decides.
        let d = TestDaemon::start(&with_role("operator")).await;
        let addr = d.modbus_tcp.unwrap();
        let before = d.sim().drive(3).unwrap();
        let mut plc = Raw::connect(addr).await;

        // Operator work: activate, speed mode, a setpoint, the brake, a
        // fault reset; reads of course.
        for (register, value) in [
            (CONFIG, 0x0),
            (CONFIG, 0xA),
            (0x0006, 120),
            (CONFIG, 0x5),
            (CONFIG, 0x8),
        ] {
            let pdu = write(register, value);
            assert_eq!(plc.ask(3, &pdu).await, pdu, "0x{register:04X} = {value}");
        }
        let out = pymodbus(addr, &["write", "3", "0x06", "50"]).await;
        assert_eq!(out["written"], true, "{out}");
        assert_eq!(plc.ask(3, &read(0xC0, 7)).await.len(), 16);

        // Commissioning is refused with 0x01: protection (a block), a save
        // flag, a ramp half, inertia, RS-485 control, the address,
        // calibration, factory reset, and writes the core cannot decode (a
        // coil, a register outside the table).
        let out = pymodbus(addr, &["write-multiple", "3", "0x0C", "400,2500,0"]).await;
        assert_eq!(out["exception"], 1, "{out}");
        for (register, value) in [
            (0x001C, 1),
            (0x001A, 9),
            (0x0024, 3),
            (0x00BE, 0),
            (0x0000, 9),
            (CONFIG, 0x2),
            (CONFIG, 0x6),
            (0x0004, 1),
        ] {
            assert_eq!(
                plc.ask(3, &write(register, value)).await,
                [0x86, 0x01],
                "0x{register:04X} = {value}"
            );
        }
        assert_eq!(
            plc.ask(3, &[0x05, 0x00, 0x01, 0xFF, 0x00]).await,
            [0x85, 0x01]
        );
        let (ok, text) = mbpoll(addr, &["-a", "3", "-0", "-r", "36", "-t", "4"], &["4"]).await;
        assert!(!ok && text.contains("Illegal function"), "{text}");

        let after = d.sim().drive(3).unwrap();
        assert_eq!(
            (after.settings, after.flash.settings, after.flash.address),
            (before.settings, before.flash.settings, 3)
        );
        assert_eq!(
            (after.address, after.procedure, after.rs485_control),
            (3, None, true)
        );
        assert_eq!(after.setpoints.speed_rpm, 50);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_network_only_reads() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&with_role("viewer")).await;
        let addr = d.modbus_tcp.unwrap();
        let (ok, text) = mbpoll(
            addr,
            &["-a", "2", "-0", "-r", "192", "-c", "7", "-t", "4"],
            &[],
        )
        .await;
        assert!(ok, "{text}");
        let (ok, text) = mbpoll(addr, &["-a", "2", "-0", "-r", "2", "-t", "4"], &["5"]).await;
        assert!(!ok && text.contains("Illegal function"), "{text}");
        let out = pymodbus(addr, &["write", "2", "0x06", "100"]).await;
        assert_eq!(out["exception"], 1, "{out}");
        let lift = d.sim().drive(2).unwrap();
        assert!(!lift.braking);
        assert_eq!(lift.setpoints.speed_rpm, 0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_only_still_makes_everybody_a_viewer() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with("read_only = true")).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        assert_eq!(c.ask(1, &write(CONFIG, 0x5)).await, [0x86, 0x01]);
        assert_eq!(c.ask(1, &read(0xC0, 7)).await.len(), 16);
        assert!(!d.sim().drive(1).unwrap().braking);
        let metrics = reqwest::get(format!("http://{}/metrics", d.http))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        assert_eq!(
            crate::support::metrics::metric(
                &metrics,
                "drivegate_modbus_tcp_requests_total{function=\"0x06\",outcome=\"read_only\"}"
            ),
            1.0,
            "{metrics}"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_role_in_the_network_config_conflicting_with_read_only_stops_the_start() {
    let e = drivegate::config::Config::parse(
        &four_drives_with(
            "read_only = true\n[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"admin\"",
        ),
        "t.toml",
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("read_only = true makes every client a viewer"),
        "{e}"
    );
}
