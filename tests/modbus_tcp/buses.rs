//! One Modbus TCP listener over two simulated buses through a unit map, and
//! status reads answered from the polled copy: while fresh, never once the
//! wire is gone (an external simulator killed under a reading client).

use std::time::Duration;

use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::metrics::{counter, metric};
use crate::support::modbus_tcp::{Raw, drives, pymodbus, read, registers, write};
use crate::support::sim_process::ExternalSim;
use crate::support::{TestDaemon, eventually};
use drivegate::bus::stats::Outcome;
use drivegate::plant::SimRef;
use serde_json::json;

/// Every test ends within this, whatever happens.
const LIMIT: Duration = Duration::from_secs(60);

/// STALLED_DURATION_MS: read/write, 0..60000, harmless while standing still.
const STALL_MS: u16 = 0x000E;

/// Buses A and B, two drives each at units 1 and 2; units 1-32 go to A,
/// 101-132 to B as 1-32.
const TWO_BUSES: &str = r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
listen = "127.0.0.1:0"
broadcast_reply = true
[[modbus_tcp.unit_map]]
units = "1-32"
bus = "A"
[[modbus_tcp.unit_map]]
units = "101-132"
bus = "B"
bus_units = "1-32"

[[bus]]
name = "A"
port = "sim"
response_timeout_ms = 250
retries = 0
[bus.sim]
seed = 1
[[bus.drive]]
unit = 1
name = "a1"
[[bus.drive]]
unit = 2
name = "a2"

[[bus]]
name = "B"
port = "sim"
response_timeout_ms = 250
retries = 0
[bus.sim]
seed = 2
[[bus.drive]]
unit = 1
name = "b1"
[[bus.drive]]
unit = 2
name = "b2"
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unit_map_reaches_two_buses_through_one_listener() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(TWO_BUSES).await;
        let addr = d.modbus_tcp.unwrap();
        let sim = |bus: usize| SimRef::of(d.plant.buses()[bus].clone()).unwrap();
        // Unit 1 is A's drive 1, unit 101 is B's drive 1, unit 102 B's drive 2.
        assert_eq!(
            pymodbus(addr, &["write", "1", "0x000E", "1001"]).await,
            json!({"written": true})
        );
        assert_eq!(
            pymodbus(addr, &["write", "101", "0x000E", "2001"]).await,
            json!({"written": true})
        );
        assert_eq!(
            pymodbus(addr, &["write", "102", "0x000E", "2002"]).await,
            json!({"written": true})
        );
        assert_eq!(sim(0).drive(1).unwrap().settings.stall_duration_ms, 1001);
        assert_eq!(sim(1).drive(1).unwrap().settings.stall_duration_ms, 2001);
        assert_eq!(sim(1).drive(2).unwrap().settings.stall_duration_ms, 2002);
        assert_eq!(sim(0).drive(2).unwrap().settings.stall_duration_ms, 3000);

        let mut c = Raw::connect(addr).await;
        assert_eq!(registers(&c.ask(101, &read(STALL_MS, 1)).await), [2001]);
        assert_eq!(registers(&c.ask(1, &read(STALL_MS, 1)).await), [1001]);
        // Unmapped units: 0x0A. A mapped unit with no drive behind it: sent,
        // and 0x0B when nobody answers.
        assert_eq!(c.ask(33, &read(0xC0, 7)).await, [0x83, 0x0A]);
        assert_eq!(c.ask(100, &read(0xC0, 7)).await, [0x83, 0x0A]);
        assert_eq!(c.ask(133, &read(0xC0, 7)).await, [0x83, 0x0A]);
        assert_eq!(c.ask(105, &read(0xC0, 7)).await, [0x83, 0x0B]);
        assert_eq!(
            sim(1).stats().unanswered,
            1,
            "the read for unit 105 went to B's unit 5"
        );
        assert_eq!(sim(0).stats().unanswered, 0);
        // A broadcast goes to both buses.
        let before = (sim(0).stats().broadcasts, sim(1).stats().broadcasts);
        assert_eq!(c.ask(0, &write(0x0002, 0)).await, write(0x0002, 0));
        // The simulated drives count it when they have framed it (their own thread).
        eventually(
            Duration::from_secs(5),
            "the broadcast on both buses",
            || {
                let now = (sim(0).stats().broadcasts, sim(1).stats().broadcasts);
                (now == (before.0 + 1, before.1 + 1)).then_some(())
            },
        )
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_that_is_down_is_gateway_path_unavailable() {
    bounded(LIMIT, async {
        let toml = TWO_BUSES.replace(
            "name = \"B\"\nport = \"sim\"\nresponse_timeout_ms = 250\nretries = 0\n[bus.sim]\nseed = 2\n",
            "name = \"B\"\nport = \"/dev/drivegate-test-no-such-adapter\"\n",
        );
        let d = TestDaemon::start_no_wait(&toml).await;
        let (_, a) = d.plant.drive("a1").unwrap();
        let (_, b) = d.plant.drive("b1").unwrap();
        eventually(Duration::from_secs(5), "bus B down, bus A polling", || {
            let down = matches!(b.port_state(), drivegate::bus::handle::PortState::Down { .. });
            (down && a.drive(1).and_then(|s| s.status).is_some()).then_some(())
        })
        .await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        assert_eq!(c.ask(101, &read(0xC0, 7)).await, [0x83, 0x0A]);
        assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_reads_come_from_the_polled_copy_while_it_is_fresh() {
    bounded(LIMIT, async {
        let toml = drives(
            4,
            "[[modbus_tcp.polled_copy]]\nbus = \"sim\"\nmax_age_ms = 2000",
            "poll_interval_ms = 50",
        );
        let d = TestDaemon::start(&toml).await;
        let (_, bus) = d.plant.drive("d1").unwrap();
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let before = bus.stats();
        for i in 0..200u16 {
            let unit = (i % 4) as u8 + 1;
            let regs = registers(&c.ask(unit, &read(0xC0, 7)).await);
            assert_eq!(regs.len(), 7);
            assert_eq!(regs[4], d.sim().drive(unit).unwrap().status.voltage_v);
            // One register at 0x00C8 is VOLT, from the copy too.
            assert_eq!(registers(&c.ask(unit, &read(0xC8, 1)).await), [regs[4]]);
        }
        let after = bus.stats();
        // No read went to the bus: every 0x03 transaction was a poll.
        let reads = |s: &drivegate::bus::stats::BusStatsSnapshot| {
            s.transactions
                .get(&(0x03, Outcome::Ok))
                .copied()
                .unwrap_or(0)
        };
        let polls = after.polls - before.polls;
        let wire_reads = reads(&after) - reads(&before);
        assert!(
            wire_reads <= polls + 1,
            "{wire_reads} reads on the wire for {polls} polls"
        );
        let text = d.metrics.render();
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_requests_total{function=\"0x03\",outcome=\"cached\"}"
            ),
            400.0
        );
        // Reads outside the block go to the drive: 0x00CC count 2 runs past it.
        assert_eq!(c.ask(1, &read(0xCC, 2)).await, [0x83, 0x02]);
        // A drive that stops answering: once its copy is older than the
        // maximum age, reads go to the bus again and fail there.
        // The maximum age is 40 polls long, so a loaded machine that holds
        // the poller back does not send reads to the bus; the copy's end is
        // awaited, not timed.
        d.sim().set_silent(2, true);
        loop {
            let reply = c.ask(2, &read(0xC0, 7)).await;
            if reply == [0x83, 0x0B] {
                break;
            }
            assert_eq!(registers(&reply).len(), 7, "{reply:?}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_polled_copy_every_read_uses_the_bus() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&drives(2, "", "poll_interval_ms = 1000")).await;
        let (_, bus) = d.plant.drive("d1").unwrap();
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let before = bus.stats();
        for _ in 0..20 {
            assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
        }
        let after = bus.stats();
        let reads = |s: &drivegate::bus::stats::BusStatsSnapshot| {
            s.transactions
                .get(&(0x03, Outcome::Ok))
                .copied()
                .unwrap_or(0)
        };
        // Every read used the bus, beside every poll that succeeded (on a
        // loaded machine a poll can time out).
        let polled = (after.polls - after.poll_failures) - (before.polls - before.poll_failures);
        assert!(reads(&after) - reads(&before) >= 20 + polled);
        d.stop().await;
    })
    .await;
}

/// The copy's answers, counted by the daemon.
const CACHED: &str = "drivegate_modbus_tcp_requests_total{function=\"0x03\",outcome=\"cached\"}";

/// A status read of `unit`: its seven registers, or the exception's code.
async fn status_or_exception(c: &mut Raw, unit: u8) -> Result<Vec<u16>, u8> {
    let reply = c.ask(unit, &read(0xC0, 7)).await;
    match reply.as_slice() {
        [0x83, code] => Err(*code),
        _ => {
            let regs = registers(&reply);
            assert_eq!(regs.len(), 7, "{reply:02X?}");
            Ok(regs)
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_polled_copy_answers_nothing_once_the_wire_is_gone() {
    bounded(LIMIT, async {
        // The adapter is a process of its own, killed as an unplugged
        // adapter; the copy may be a minute old, far longer than the test:
        // only the bus's freshness can stop it answering.
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-drives");
        let sim = ExternalSim::start(&link, "1-2", &[]).await;
        let toml = ConfigBuilder::new()
            .bus("line1", |b| {
                b.port(&link.display().to_string())
                    .drive(1, "conveyor")
                    .drive(2, "belt")
            })
            .tables("[[modbus_tcp.polled_copy]]\nbus = \"line1\"\nmax_age_ms = 60000")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let bus = d.plant.buses()[0].handle.clone();
        let down = || {
            matches!(
                bus.port_state(),
                drivegate::bus::handle::PortState::Down { .. }
            )
        };
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let before = counter(&d, CACHED);
        for _ in 0..20 {
            assert!(status_or_exception(&mut c, 1).await.is_ok());
        }
        assert_eq!(counter(&d, CACHED) - before, 20.0, "read from the copy");

        // Cut: every read from the moment the bus is down is 0x0A, none
        // from the copy; the first within 3 s.
        let t0 = std::time::Instant::now();
        sim.kill().await;
        let mut cut_seen = None;
        while cut_seen.is_none() {
            let was_down = down();
            let cached = counter(&d, CACHED);
            let got = status_or_exception(&mut c, 1).await;
            if was_down {
                assert_eq!(got, Err(0x0A), "a read after the bus went down");
                assert_eq!(counter(&d, CACHED), cached, "answered from the copy");
            }
            if got == Err(0x0A) {
                cut_seen = Some(t0.elapsed());
            } else {
                assert!(got.is_ok(), "{got:?} before the cut was seen");
                assert!(
                    t0.elapsed() < Duration::from_secs(3),
                    "still answered 3 s after the cut"
                );
            }
        }
        eprintln!(
            "polled copy: 0x0A {} ms after the cut",
            cut_seen.unwrap().as_millis()
        );
        assert!(down(), "0x0A while the port is not down");
        let cached = counter(&d, CACHED);
        for unit in [1, 2, 1, 2] {
            assert_eq!(status_or_exception(&mut c, unit).await, Err(0x0A));
        }
        assert_eq!(counter(&d, CACHED), cached);

        // Plugged back: answered again, from the copy once it is live.
        let _sim = ExternalSim::start(&link, "1-2", &[]).await;
        eventually(
            Duration::from_secs(30),
            "the bus back and the drive live",
            || {
                bus.freshness(1)
                    .filter(|v| v.freshness.is_live())
                    .map(|_| ())
            },
        )
        .await;
        let again = counter(&d, CACHED);
        assert!(status_or_exception(&mut c, 1).await.is_ok());
        assert_eq!(counter(&d, CACHED) - again, 1.0, "read from the copy again");
        d.stop().await;
    })
    .await;
}
