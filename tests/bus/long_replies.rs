//! Long replies at low baud rates, through the whole daemon: a meter-like
//! device of the simulator (unit 100) beside a drive, on a bus at 9600 or
//! 19200 baud with a 120 ms response timeout, read over Modbus TCP up to the
//! longest frame (125 registers: 255 bytes, 266 ms on the wire at 9600 baud,
//! 133 ms at 19200). The simulator hands each byte over at the wire's pace,
//! so the long replies (60 registers at 9600 baud: 143 ms; 125 at either
//! rate) take longer than the timeout to arrive. The timeout is above the
//! default 50 ms only so that a loaded test machine, which can hold the
//! simulator's thread for over 100 ms, cannot time out a reply before its
//! first byte: the rule under test (the timeout is the wait for the first
//! byte, the rest follows the wire) is the same at any timeout.

use std::time::{Duration, Instant};

use crate::support::{TestDaemon, eventually};
use drivegate::bus::handle::JobOptions;
use drivegate::bus::stats::Outcome;
use drivegate::modbus::timing::LineTiming;
use tokio_modbus::client::{Reader, Writer};
use tokio_modbus::{Slave, client::tcp};

fn config(baud: u32) -> String {
    format!(
        r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
listen = "127.0.0.1:0"
[[modbus_tcp.unit_map]]
units = "1"
bus = "slow"
[[modbus_tcp.unit_map]]
units = "100"
bus = "slow"
[[bus]]
name = "slow"
port = "sim"
baud = {baud}
response_timeout_ms = 120
# A fixed guard keeps the 120 ms timeout for every read (nothing learned):
# this test is about long replies' framing, and must not see a retry that
# a starved simulator causes under a learned timeout on a loaded machine.
guard_ms = 150
retries = 1
poll_interval_ms = 500
[bus.sim]
turnaround_ms = 0.5
devices = [100]
[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reads_of_up_to_125_registers_work_at_9600_and_19200_baud() {
    for baud in [9600, 19_200] {
        let d = TestDaemon::start(&config(baud)).await;
        let bus = d.plant.buses()[0].handle.clone();
        let line = LineTiming::new_8n1(baud);
        let before = bus.stats();
        let mut meter = tcp::connect_slave(d.modbus_tcp.unwrap(), Slave(100))
            .await
            .unwrap();
        for (start, count) in [(0u16, 1u16), (0x0100, 20), (0x2000, 60), (0xFF00, 125)] {
            let sent = Instant::now();
            let registers = meter
                .read_holding_registers(start, count)
                .await
                .unwrap()
                .unwrap_or_else(|e| panic!("{baud} baud, {count} registers: exception {e:?}"));
            let expected: Vec<u16> = (start..start + count).collect();
            assert_eq!(registers, expected, "{baud} baud, {count} registers");
            // Request and reply took their wire time (the simulator paces
            // them); a reply longer than the 120 ms timeout went through.
            let wire = line.wire_time(8 + 5 + 2 * usize::from(count));
            assert!(sent.elapsed() >= wire, "{baud} baud, {count} registers");
        }
        // A write then a long read of what was written.
        meter
            .write_single_register(0x0010, 0xBEEF)
            .await
            .unwrap()
            .unwrap();
        let registers = meter
            .read_holding_registers(0x0000, 125)
            .await
            .unwrap()
            .unwrap();
        assert_eq!(registers[0x10], 0xBEEF);
        // Nothing failed or was retried, and the drive is still polled.
        let after = bus.stats();
        eventually(Duration::from_secs(5), "a poll", || {
            (bus.stats().polls > before.polls).then_some(())
        })
        .await;
        assert_eq!(
            after.count(Outcome::Timeout),
            before.count(Outcome::Timeout)
        );
        assert_eq!(
            after.count(Outcome::BadReply),
            before.count(Outcome::BadReply)
        );
        assert_eq!(after.retries, before.retries, "{baud} baud");
        assert_eq!(d.sim().stats().gap_violations, 0, "{baud} baud");
        // The daemon's own path too (what the API and the core use).
        let exchange = bus
            .transact(
                100,
                vec![0x03, 0x00, 0x00, 0x00, 125],
                JobOptions::default(),
            )
            .await
            .unwrap();
        assert_eq!(exchange.reply.len(), 252);
        assert_eq!(exchange.attempts, 1);
        assert!(
            exchange.on_wire >= line.wire_time(255) && exchange.on_wire < Duration::from_secs(2)
        );
        d.stop().await;
    }
}
