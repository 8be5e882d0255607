//! The Modbus TCP passthrough against the daemon on the simulator, through
//! third-party clients: pymodbus (PyPI) and mbpoll (Debian). What a SCADA
//! system or a PLC would do, checked against the simulated drives' truth.

use std::time::Duration;

use crate::support::bounded;
use crate::support::metrics::metric;
use crate::support::modbus_tcp::{Raw, drives, mbpoll, pymodbus, write};
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::stats::Outcome;
use serde_json::json;

/// Every test ends within this, whatever happens.
const LIMIT: Duration = Duration::from_secs(60);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_block_read_with_pymodbus_and_mbpoll() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        // 7 registers from 0x00C0: the status block, the drive's own addresses.
        let out = pymodbus(addr, &["read", "2", "0xC0", "7"]).await;
        let regs: Vec<u16> = serde_json::from_value(out["registers"].clone())
            .unwrap_or_else(|_| panic!("no registers in {out}"));
        let truth = d.sim().drive(2).unwrap().status;
        assert_eq!(regs.len(), 7);
        assert_eq!(regs[4], truth.voltage_v, "VOLT");
        assert_eq!(regs[6], truth.flags, "STATUS flags");
        assert_ne!(regs[6] & 0x40, 0, "the simulated drives start calibrated");

        // One register at 0x00C2 is ANGLE (byte addressing, no renumbering).
        let out = pymodbus(addr, &["read", "2", "0xC2", "1"]).await;
        assert_eq!(out["registers"].as_array().map(Vec::len), Some(1), "{out}");

        // mbpoll, 0-based references: 192 = 0x00C0.
        let (ok, text) = mbpoll(
            addr,
            &["-a", "2", "-0", "-r", "192", "-c", "7", "-t", "4"],
            &[],
        )
        .await;
        assert!(ok, "mbpoll failed: {text}");
        // mbpoll numbers the registers one by one: the fifth (VOLT) shows as 196.
        let volt_line = format!("[196]: \t{}", truth.voltage_v);
        assert!(text.contains(&volt_line), "no {volt_line:?} in {text}");
        // The trap the README warns of: ANGLE alone is 194 (0x00C2), and
        // 193, the label mbpoll gave the block's second word, is no
        // register (exception 0x02).
        let (ok, text) = mbpoll(
            addr,
            &["-a", "2", "-0", "-r", "194", "-c", "1", "-t", "4"],
            &[],
        )
        .await;
        assert!(ok && text.contains("[194]: \t"), "ANGLE at 194: {text}");
        let (_, text) = mbpoll(
            addr,
            &["-a", "2", "-0", "-r", "193", "-c", "1", "-t", "4"],
            &[],
        )
        .await;
        assert!(
            text.to_lowercase().contains("illegal data address"),
            "193 is no register: {text}"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn setpoint_write_and_read_back() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        // CONFIG (0x0002): activate (0x0), speed closed loop (0xA).
        assert_eq!(
            pymodbus(addr, &["write", "1", "0x0002", "0x0"]).await,
            json!({"written": true})
        );
        assert_eq!(
            pymodbus(addr, &["write", "1", "0x0002", "0xA"]).await,
            json!({"written": true})
        );
        // SPEED_REF (0x0006) = 120 rpm, read back from the drive.
        assert_eq!(
            pymodbus(addr, &["write", "1", "0x0006", "120"]).await,
            json!({"written": true})
        );
        assert_eq!(
            pymodbus(addr, &["read", "1", "0x0006", "1"]).await,
            json!({"registers": [120]})
        );
        assert_eq!(d.sim().drive(1).unwrap().setpoints.speed_rpm, 120);
        // The motor follows: SPEED (0x00C4) reaches the setpoint.
        let mut reached = false;
        for _ in 0..100 {
            let out = pymodbus(addr, &["read", "1", "0xC4", "1"]).await;
            if out == json!({"registers": [120]}) {
                reached = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(reached, "SPEED never read 120 rpm");
        // A value outside the manual's range is refused by the drive itself
        // (0x03) and passed through unchanged; nothing changes.
        let out = pymodbus(addr, &["write", "1", "0x0006", "3000"]).await;
        assert_eq!(out, json!({"exception": 3}));
        assert_eq!(d.sim().drive(1).unwrap().setpoints.speed_rpm, 120);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protection_block_write_with_function_16() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        // Manual 1.8: 0x000C count 3 = current limit, stall time, save flag.
        let out = pymodbus(addr, &["write-multiple", "3", "0x000C", "300,2000,0"]).await;
        assert_eq!(out, json!({"written": true}));
        let settings = d.sim().drive(3).unwrap().settings;
        assert_eq!(
            (settings.stall_current, settings.stall_duration_ms),
            (300, 2000)
        );
        assert_eq!(
            pymodbus(addr, &["read", "3", "0x000C", "2"]).await,
            json!({"registers": [300, 2000]})
        );
        // mbpoll writes the block too (holding registers, 0-based 12 = 0x000C).
        let (ok, text) = mbpoll(
            addr,
            &["-a", "3", "-0", "-r", "12", "-t", "4"],
            &["400", "2500", "0"],
        )
        .await;
        assert!(ok, "mbpoll failed: {text}");
        let settings = d.sim().drive(3).unwrap().settings;
        assert_eq!(
            (settings.stall_current, settings.stall_duration_ms),
            (400, 2500)
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unit_on_no_bus_is_gateway_path_unavailable() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        assert_eq!(
            pymodbus(addr, &["read", "9", "0xC0", "7"]).await,
            json!({"exception": 10})
        );
        let (ok, text) = mbpoll(addr, &["-a", "9", "-0", "-r", "192", "-c", "7"], &[]).await;
        assert!(!ok && text.contains("Gateway path unavailable"), "{text}");
        // Nothing was sent for it: a request to unit 9 would have been
        // counted unanswered by the simulated wire, and timed out.
        assert_eq!(d.sim().stats().unanswered, 0);
        let (_, bus) = d.plant.drive("conveyor").unwrap();
        assert_eq!(bus.stats().count(Outcome::Timeout), 0);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_unit_is_gateway_target_failed() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        d.sim().set_silent(4, true);
        let (_, bus) = d.plant.drive("feeder").unwrap();
        let timeouts = bus.stats().count(Outcome::Timeout);
        assert_eq!(
            pymodbus(addr, &["read", "4", "0xC0", "7"]).await,
            json!({"exception": 11})
        );
        let (ok, text) = mbpoll(addr, &["-a", "4", "-0", "-r", "192", "-c", "7"], &[]).await;
        assert!(
            !ok && text.contains("Target device failed to respond"),
            "{text}"
        );
        // The requests did go out, and timed out on the wire.
        assert!(bus.stats().count(Outcome::Timeout) >= timeouts + 2);
        // The other drives still answer.
        let out = pymodbus(addr, &["read", "1", "0xC0", "7"]).await;
        assert!(out["registers"].is_array(), "{out}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broadcast_reaches_every_drive_and_is_not_answered() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        let broadcasts = d.sim().stats().broadcasts;
        // CONFIG = activate, to unit 0.
        assert_eq!(
            pymodbus(addr, &["broadcast", "0x0002", "0"]).await,
            json!({"sent": true})
        );
        eventually(Duration::from_secs(5), "every drive active", || {
            (1..=4)
                .all(|u| d.sim().drive(u).is_some_and(|v| v.active))
                .then_some(())
        })
        .await;
        assert_eq!(d.sim().stats().broadcasts, broadcasts + 1);
        // No reply came back (raw client: the next reply is for the next request).
        let mut raw = Raw::connect(addr).await;
        raw.send(0x0101, 0, &write(0x0002, 1)).await;
        let reply = raw
            .ask(1, &crate::support::modbus_tcp::read(0x0006, 1))
            .await;
        assert_eq!(reply, [0x03, 2, 0, 0]);
        eventually(Duration::from_secs(5), "every drive inactive", || {
            (1..=4)
                .all(|u| d.sim().drive(u).is_some_and(|v| !v.active))
                .then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_two_clients_at_once_each_get_their_own_replies() {
    bounded(LIMIT, async {
        // One SCADA host with a connection per drive: more than the default
        // share of one address (a quarter of max_connections).
        let d = TestDaemon::start(&drives(8, "max_connections_per_address = 32", "")).await;
        let addr = d.modbus_tcp.unwrap();
        // 32 pymodbus connections at once; each owns one register of one of
        // the 8 drives, writes values only it writes, reads them back and
        // reads status blocks of its own length: a reply delivered to the
        // wrong request would show.
        let out = pymodbus(addr, &["swarm", "32", "5", "8"]).await;
        assert_eq!(out["mismatches"], json!([]), "{out}");
        assert_eq!(out["checked"], json!(32 * 5 * 3), "{out}");
        let text = d.metrics.render();
        let ok = metric(
            &text,
            "drivegate_modbus_tcp_requests_total{function=\"0x03\",outcome=\"ok\"}",
        ) + metric(
            &text,
            "drivegate_modbus_tcp_requests_total{function=\"0x06\",outcome=\"ok\"}",
        );
        assert_eq!(ok, (32 * 5 * 3) as f64, "{text}");
        assert_eq!(
            metric(&text, "drivegate_modbus_tcp_connections_accepted_total"),
            32.0
        );
        assert_eq!(d.sim().stats().gap_violations, 0);
        d.stop().await;
    })
    .await;
}
