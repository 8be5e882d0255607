//! The overview's line of the Modbus TCP face: where it listens, the
//! connections it holds, and who it refused lately, in the daemon's words.

use std::time::Duration;

use serde_json::json;

use super::browser::{LONG, assert_clean, open};
use super::harness::cdp::Browser;
use crate::support::TestDaemon;
use crate::support::config::ConfigBuilder;
use crate::support::metrics::counter;
use crate::support::wait::eventually;

/// A connection to `addr` from the loopback address `source`.
async fn connect_from(source: &str, addr: std::net::SocketAddr) -> tokio::net::TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    socket.connect(addr).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_says_who_the_modbus_tcp_listener_refused() {
    let daemon = TestDaemon::start(
        &ConfigBuilder::four_drives()
            .modbus_tcp("max_connections = 2")
            .toml(),
    )
    .await;
    let modbus = daemon.modbus_tcp.unwrap();
    // 127.0.0.5 holds both slots, then twelve more of its connections find
    // the listener full.
    let mut held = Vec::new();
    for _ in 0..2 {
        held.push(connect_from("127.0.0.5", modbus).await);
    }
    eventually(Duration::from_secs(10), "two connections held", || {
        (counter(&daemon, "drivegate_connections{face=\"modbus_tcp\"}") == 2.0).then_some(())
    })
    .await;
    let mut refused = Vec::new();
    for _ in 0..12 {
        refused.push(connect_from("127.0.0.5", modbus).await);
    }
    let series =
        "drivegate_connections_turned_away_total{face=\"modbus_tcp\",address=\"127.0.0.5\"}";
    eventually(Duration::from_secs(10), "twelve refused", || {
        (counter(&daemon, series) == 12.0).then_some(())
    })
    .await;

    let browser = Browser::start(&[]).await;
    let base = daemon.url("");
    let page = open(&browser, &base, "/", None).await;
    let line = format!("Modbus TCP: serving on {modbus} (2 connections)");
    page.wait_for(
        &format!(
            "(document.querySelector('.summary.modbus.good:not([hidden])') || {{}}).textContent === {}",
            json!(line)
        ),
        LONG,
        "the Modbus TCP line",
    )
    .await;
    let said = "12 connections from 127.0.0.5 refused: the listener was full";
    page.wait_for(
        &format!(
            "[...document.querySelectorAll('.modbus-refused')].some((p) => p.textContent === {})",
            json!(said)
        ),
        LONG,
        "the refusals beside it",
    )
    .await;
    assert_clean(&page, &base);
    drop((held, refused));
    browser.stop().await;
    daemon.stop().await;
}
