//! A write its client waited for too long is not sent. A PLC pipelines a
//! read and a speed setpoint while the wire is held longer than the bus's
//! `queue_timeout_ms`; with one request in the pipeline at a time the
//! setpoint waits in the connection's buffer, unread, behind the read.
//! Its wait counts from the moment its bytes arrived: once the wire is
//! free it is answered 0x06 (server busy: it waited too long), and the
//! drive never gets it. Before, it went to the bus queue with the whole
//! queue timeout again, and turned the motor well after its client had
//! given up on it.

use std::time::Duration;

use crate::support::bus::hold_the_wire;
use crate::support::modbus_tcp::{Raw, drives, read, write, writes_handled};
use crate::support::{TestDaemon, bounded, eventually};

const CONFIG: u16 = 0x0002;
const SPEED_REF: u16 = 0x0006;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_that_waited_past_the_queue_timeout_behind_a_full_pipeline_is_not_sent() {
    bounded(Duration::from_secs(60), async {
        // The held wire lasts one response timeout: 1.5 s, three times
        // the queue timeout.
        let d = TestDaemon::start(&drives(
            1,
            "max_pipelined = 1",
            "response_timeout_ms = 1500\nqueue_timeout_ms = 500",
        ))
        .await;
        d.wait_all_online(Duration::from_secs(10)).await;
        let bus = d.plant.buses()[0].handle.clone();
        let mut plc = Raw::connect(d.modbus_tcp.expect("Modbus TCP")).await;
        // Active, in speed mode, as the poll shows (no read before the
        // setpoint).
        assert_eq!(
            plc.ask(1, &write(CONFIG, 0x0000)).await,
            write(CONFIG, 0x0000)
        );
        assert_eq!(
            plc.ask(1, &write(CONFIG, 0x000A)).await,
            write(CONFIG, 0x000A)
        );
        eventually(Duration::from_secs(10), "the drive polled active", || {
            bus.drive(1)
                .and_then(|s| s.status)
                .is_some_and(|s| s.active())
                .then_some(())
        })
        .await;

        let before = writes_handled(&bus);
        let blocker = hold_the_wire(&bus).await;
        plc.send(1, 1, &read(0x00C0, 1)).await;
        plc.send(2, 1, &write(SPEED_REF, 100)).await;
        let (t1, _, _) = plc.recv().await.expect("the read's reply");
        let (t2, _, late) = plc.recv().await.expect("the setpoint's reply");
        assert_eq!((t1, t2), (1, 2));
        assert_eq!(late, [0x86, 0x06], "server busy: it waited too long");
        drop(blocker);
        // The drive never got it: its own setpoint, and no such frame.
        let drive = d.sim().drive(1).unwrap();
        assert_eq!(drive.setpoints.speed_rpm, 0, "{drive:?}");
        // Nor did the bus: no write went out, failed or was dropped there.
        assert_eq!(writes_handled(&bus), before);
        d.stop().await;
    })
    .await;
}
