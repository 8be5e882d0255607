//! A bus behind a serial device server: the simulator served on TCP on
//! loopback (as a Moxa NPort serves a line), the daemon with
//! `port = "tcp://127.0.0.1:N"`. End to end: polls, commands, Modbus TCP,
//! `/readyz` and `/metrics` as for a serial port; the connection dropped
//! during traffic and made again by itself; a refused connection reported
//! in words, then taken up once the server is there.

use std::time::Duration;

use crate::support::config::ConfigBuilder;
use crate::support::metrics::exported;
use crate::support::{TestDaemon, eventually};
use drivegate::bus::BusError;
use drivegate::bus::handle::{JobOptions, PortState};
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest};
use drivegate::sim::{SimConfig, SimHandle, Simulator};
use tokio_modbus::client::Reader;
use tokio_modbus::{Slave, client::tcp};

const LIMIT: Duration = Duration::from_secs(15);

fn sim_on(address: &str) -> SimHandle {
    let mut config = SimConfig::for_units(1..=4);
    config.listen = Some(address.parse().unwrap());
    Simulator::start(config).unwrap()
}

fn daemon_config(port: &str) -> String {
    ConfigBuilder::new()
        .bus("remote", |b| {
            let b = b.port(port).keys("response_timeout_ms = 100").auto_guard();
            (1..=4).fold(b, |b, unit| b.drive(unit, &format!("d{unit}")))
        })
        .toml()
}

async fn readyz(d: &TestDaemon) -> (u16, serde_json::Value) {
    let r = reqwest::get(d.url("/readyz")).await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_on_a_serial_device_server_works_and_reconnects_after_a_drop() {
    let sim = sim_on("127.0.0.1:0");
    let port = sim.port_path().display().to_string();
    assert!(port.starts_with("tcp://127.0.0.1:"), "{port}");
    let d = TestDaemon::start(&daemon_config(&port)).await;
    let bus = d.plant.buses()[0].handle.clone();

    // Commands are confirmed by the drives behind the device server.
    for request in [
        DriveRequest::Config(ConfigCommand::Activate),
        DriveRequest::Config(ConfigCommand::SpeedMode),
        DriveRequest::Speed { rpm: 50 },
    ] {
        let reply = bus
            .execute(2, &request, JobOptions::default())
            .await
            .unwrap();
        assert_eq!(reply, DriveReply::Confirmed);
    }
    assert_eq!(sim.drive(2).unwrap().setpoints.speed_rpm, 50);
    // Modbus TCP reaches them as through a local adapter.
    let mut client = tcp::connect_slave(d.modbus_tcp.unwrap(), Slave(3))
        .await
        .unwrap();
    assert_eq!(
        client
            .read_holding_registers(0x00C0, 7)
            .await
            .unwrap()
            .unwrap()
            .len(),
        7
    );
    // Ready, and the metrics describe the port.
    let (status, ready) = readyz(&d).await;
    assert_eq!(status, 200, "{ready}");
    assert_eq!(ready["buses"][0]["port_open"], true);
    let text = d.metrics.render();
    let info = format!("drivegate_bus_info{{bus=\"remote\",port=\"{port}\",baud=\"115200\"}} 1");
    assert!(text.contains(&info), "{text}");
    assert_eq!(
        exported(&text, "drivegate_bus_port_open{bus=\"remote\"}"),
        1.0
    );

    // Traffic while the device server drops the connection.
    let traffic = {
        let bus = bus.clone();
        tokio::spawn(async move {
            let (mut ok, mut failed) = (0, Vec::new());
            for _ in 0..400 {
                match bus
                    .transact(1, vec![0x03, 0x00, 0xC0, 0x00, 0x07], JobOptions::default())
                    .await
                {
                    Ok(_) => ok += 1,
                    Err(e) => {
                        failed.push(e);
                        tokio::time::sleep(Duration::from_millis(5)).await;
                    }
                }
            }
            (ok, failed)
        })
    };
    eventually(LIMIT, "traffic under way", || {
        (bus.stats().transactions.values().sum::<u64>() > 50).then_some(())
    })
    .await;
    assert!(sim.disconnect());
    // The bus goes down with the reason in words...
    let reason = eventually(LIMIT, "the bus down", || match bus.port_state() {
        PortState::Down { reason, .. } => Some(reason),
        _ => None,
    })
    .await;
    // (closed, or reset when a request was still unread on the server)
    assert!(
        reason.contains("connection to the serial device server")
            && (reason.contains("closed the connection") || reason.contains("reset")),
        "{reason}"
    );
    // ...and comes back by itself, with every drive answering again.
    eventually(LIMIT, "the bus up again", || {
        matches!(bus.port_state(), PortState::Up { .. }).then_some(())
    })
    .await;
    let (ok, failed) = traffic.await.unwrap();
    assert!(ok > 300, "{ok} answered");
    // What failed failed for the drop, in words that say whether it was sent.
    for e in &failed {
        assert!(
            matches!(
                e,
                BusError::BusDown { .. } | BusError::BusDownAfterSend { .. }
            ),
            "{e}"
        );
    }
    let after = bus
        .execute(2, &DriveRequest::ReadStatus, JobOptions::default())
        .await;
    assert!(matches!(after, Ok(DriveReply::Status(_))), "{after:?}");
    assert_eq!(sim.stats().connections, 2);
    let text = d.metrics.render();
    assert_eq!(
        exported(&text, "drivegate_bus_reopens_total{bus=\"remote\"}"),
        1.0
    );
    assert!(exported(&text, "drivegate_bus_port_errors_total{bus=\"remote\"}") >= 1.0);
    assert_eq!(sim.stats().gap_violations, 0);
    let (status, _) = readyz(&d).await;
    assert_eq!(status, 200);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_connection_is_reported_and_retried_until_the_server_is_there() {
    // A loopback port with nobody listening (yet): bound but not
    // listening, it refuses connections and no other program can take it
    // until the device server comes up.
    let held = tokio::net::TcpSocket::new_v4().unwrap();
    held.bind("127.0.0.1:0".parse().unwrap()).unwrap();
    let address = held.local_addr().unwrap().to_string();
    let d = TestDaemon::start_no_wait(&daemon_config(&format!("tcp://{address}"))).await;
    let bus = d.plant.buses()[0].handle.clone();
    let reason = eventually(LIMIT, "the bus down", || match bus.port_state() {
        PortState::Down { reason, .. } => Some(reason),
        _ => None,
    })
    .await;
    assert!(
        reason.contains(&format!(
            "cannot connect to the serial device server at {address}"
        )) && reason.contains("refused"),
        "{reason}"
    );
    // Not ready, saying why; requests fail at once as not sent.
    let (status, ready) = readyz(&d).await;
    assert_eq!(status, 503);
    assert!(
        ready["reasons"][0].as_str().unwrap().contains("refused"),
        "{ready}"
    );
    let e = bus
        .transact(1, vec![0x03, 0x00, 0xC0, 0x00, 0x07], JobOptions::default())
        .await
        .unwrap_err();
    assert!(e.not_sent(), "{e}");
    // The device server comes up: the daemon connects on its next try.
    drop(held);
    let sim = sim_on(&address);
    d.wait_all_online(LIMIT).await;
    let (status, ready) = readyz(&d).await;
    assert_eq!(status, 200, "{ready}");
    assert_eq!(sim.stats().connections, 1);
    d.stop().await;
}
