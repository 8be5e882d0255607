//! A configured drive that never answers, on the simulator through a real
//! pty: it is probed with one attempt at a time, each costing the shortest
//! reply timeout and the time a status reply would take, never a retry and
//! never the configured timeout; the other drives' clients never fail.

use std::time::Duration;

use crate::support::{TestDaemon, eventually};
use drivegate::bus::cache::Link;
use tokio_modbus::client::Reader;
use tokio_modbus::{Slave, client::tcp};

/// Four drives and a fifth that is off, polled every 200 ms; a timeout
/// long enough that the machine's scheduling is small beside it.
const CONFIG: &str = r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
listen = "127.0.0.1:0"
[[bus]]
name = "line"
port = "sim"
response_timeout_ms = 300
retries = 1
poll_interval_ms = 200
offline_after = 3
offline_backoff_ms = 200
offline_backoff_max_ms = 400
[bus.sim]
turnaround_ms = 0.5
[bus.sim.faults]
silent_units = [5]
[[bus.drive]]
unit = 1
name = "d1"
[[bus.drive]]
unit = 2
name = "d2"
[[bus.drive]]
unit = 3
name = "d3"
[[bus.drive]]
unit = 4
name = "d4"
[[bus.drive]]
unit = 5
name = "dead"
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_drive_is_probed_with_single_short_attempts() {
    let d = TestDaemon::start_no_wait(CONFIG).await;
    let bus = d.plant.buses()[0].handle.clone();
    // A client reading the live drives all along.
    let addr = d.modbus_tcp.unwrap();
    let client = tokio::spawn(async move {
        let mut answered = 0;
        for i in 0..150u16 {
            let mut ctx = tcp::connect_slave(addr, Slave((i % 4) as u8 + 1))
                .await
                .unwrap();
            let regs = ctx
                .read_holding_registers(0x00C0, 7)
                .await
                .unwrap()
                .unwrap();
            assert_eq!(regs.len(), 7);
            answered += 1;
        }
        answered
    });
    // It goes offline after three failed polls and is probed on.
    let dead = eventually(
        Duration::from_secs(20),
        "six probes of the dead drive",
        || bus.drive(5).filter(|s| s.consecutive_failures >= 6),
    )
    .await;
    assert_eq!(dead.link, Link::Offline);
    assert!(dead.status.is_none());
    assert_eq!(client.await.unwrap(), 150, "the live drives never failed");

    // One attempt per probe: the simulator heard exactly as many requests
    // for unit 5 as the poller made (a retry would be a second one), seen
    // between two probes (one under way has reached the simulator before
    // its failure is recorded).
    let probes = eventually(
        Duration::from_secs(20),
        "a moment between two probes with one request per probe",
        || {
            let before = bus.drive(5)?.consecutive_failures;
            let unanswered = d.sim().stats().unanswered;
            let after = bus.drive(5)?.consecutive_failures;
            (before == after && unanswered == u64::from(after)).then_some(after)
        },
    )
    .await;
    let stats = bus.stats();
    // A drive never heard is probed with the shortest reply timeout (the
    // floor), doubled per silent probe up to the 300 ms ceiling, with one
    // attempt and a guard of what a status reply takes: no transaction
    // reached 500 ms (a retry would be 600, a guard as long as the timeout
    // 600, both 1200).
    let durations = &stats.transaction_duration;
    let upto_half_second = durations.bounds.iter().position(|&b| b == 0.5).unwrap();
    assert_eq!(
        durations.cumulative[upto_half_second], durations.count,
        "{durations:?}"
    );
    // Each still waited that floor and the time a status reply would take.
    let line = drivegate::modbus::timing::LineTiming::new_8n1(115_200);
    let floor = drivegate::bus::master::DEFAULT_REPLY_TIMEOUT_FLOOR + line.wire_time(8 + 19);
    assert!(durations.sum >= floor.as_secs_f64() * f64::from(probes));
    // Its probes never waited as long as the ceiling: the gauge says so.
    let timeout = stats.drives[&5].reply_timeout;
    assert_eq!(
        timeout,
        Duration::from_millis(300),
        "not learned: never answered"
    );
    // The other drives answer.
    for unit in 1..=4 {
        assert_eq!(bus.drive(unit).unwrap().link, Link::Online);
    }
    d.stop().await;
}
