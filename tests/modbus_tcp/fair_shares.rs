//! Connections shared fairly under the default configuration: a SCADA that
//! models each of 32 drives as a device with a connection of its own
//! (pymodbus, from one loopback address) is served whole; 300 idle sockets
//! from another address take only the free slots short of the last
//! eighth, and then are refused; the SCADA's 32 keep answering and a
//! client from a third address is served at once. The refusals are
//! counted per address in `/metrics`, written a few times in the log with
//! the key to change, and said on `/readyz` in the console's words.

use std::time::{Duration, Instant};

use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::metric;
use crate::support::modbus_tcp::{Raw, Scada, drives, read, registers};
use crate::support::{TestDaemon, bounded, eventually};

/// A connection to `addr` from the loopback address `source`.
async fn connect_from(source: &str, addr: std::net::SocketAddr) -> tokio::net::TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    tokio::time::timeout(Duration::from_secs(10), socket.connect(addr))
        .await
        .expect("connect in time")
        .expect("connect")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scada_with_a_connection_per_drive_is_served_beside_a_flood_of_idle_sockets() {
    capture_logs();
    bounded(Duration::from_secs(120), async {
        // 32 drives on one bus, [modbus_tcp] as it comes: max_connections
        // twice the drives plus 32 (96), no cap per address.
        let d = TestDaemon::start(&drives(32, "", "")).await;
        let addr = d.modbus_tcp.unwrap();
        let series = |s: &str| metric(&d.metrics.render(), s);
        assert_eq!(series("drivegate_connections_max{face=\"modbus_tcp\"}"), 96.0);
        assert_eq!(
            series("drivegate_connections_max_per_address{face=\"modbus_tcp\"}"),
            0.0
        );
        let (mut scada, hello) = Scada::connect(addr, "127.0.0.2", 32).await;
        assert_eq!(hello["connected"], 32, "{hello}");
        let first = scada.round().await;
        assert_eq!(first["answered"], 32, "{first}");

        // 300 sockets from another address that send nothing.
        let flood = "127.0.0.3";
        let mut idle = Vec::new();
        for _ in 0..300 {
            idle.push(connect_from(flood, addr).await);
        }
        let held = || series("drivegate_connections_by_address{face=\"modbus_tcp\",address=\"127.0.0.3\"}");
        let refused = || {
            series("drivegate_connections_turned_away_total{face=\"modbus_tcp\",address=\"127.0.0.3\"}")
        };
        eventually(Duration::from_secs(30), "the 300 held or refused", || {
            (held() + refused() == 300.0).then_some(())
        })
        .await;
        // The flood took the free slots short of the last eighth (96 - 12 -
        // the SCADA's 32), nothing of the SCADA's.
        assert_eq!(held(), 52.0);
        assert_eq!(refused(), 248.0);
        assert_eq!(
            series("drivegate_connections_refused_total{face=\"modbus_tcp\",reason=\"heaviest\"}"),
            248.0
        );
        assert_eq!(
            series("drivegate_modbus_tcp_connections_rejected_total{reason=\"heaviest\"}"),
            248.0
        );
        assert_eq!(series("drivegate_connections_closed_total{face=\"modbus_tcp\"}"), 0.0);

        // The SCADA's 32 keep answering...
        let again = scada.round().await;
        assert_eq!(again["answered"], 32, "{again}");
        // ... and a client from a third address is served at once.
        let asked = Instant::now();
        let mut third = Raw::from_stream(connect_from("127.0.0.4", addr).await);
        assert_eq!(registers(&third.ask(7, &read(0xC0, 7)).await).len(), 7);
        let waited = asked.elapsed();
        assert!(waited < Duration::from_secs(5), "{waited:?}");
        let text = d.metrics.render();
        assert_eq!(
            metric(&text, "drivegate_connections_by_address{face=\"modbus_tcp\",address=\"127.0.0.2\"}"),
            32.0
        );
        assert_eq!(metric(&text, "drivegate_connections{face=\"modbus_tcp\"}"), 85.0);

        // The log said it a few times, not 248, with the key to change.
        let lines: Vec<String> = log_text()
            .lines()
            .filter(|l| l.contains("WARN") && l.contains("connections from 127.0.0.3 refused") && l.contains(&addr.to_string()))
            .map(str::to_string)
            .collect();
        assert!((1..=4).contains(&lines.len()), "{lines:#?}");
        assert!(lines[0].contains("[modbus_tcp] max_connections"), "{}", lines[0]);
        // /readyz says it in the console's words.
        let ready: serde_json::Value = reqwest::get(d.url("/readyz")).await.unwrap().json().await.unwrap();
        let modbus = &ready["modbus_tcp"];
        assert_eq!(modbus["listen"], addr.to_string());
        assert_eq!(modbus["connections"], 85);
        let said = modbus["turned_away"][0]["text"].as_str().unwrap_or_default();
        assert_eq!(
            said,
            "248 connections from 127.0.0.3 refused: the listener was nearly full and this address held the most connections",
            "{ready}"
        );
        println!(
            "Modbus TCP, 32 drives, defaults (max_connections 96): the SCADA from 127.0.0.2 holds 32 (every read answered, slowest {} ms during the flood); \
             300 idle sockets from 127.0.0.3: 52 held, 248 refused, {} log line(s); a client from 127.0.0.4 waited {} ms",
            again["slowest_ms"],
            lines.len(),
            waited.as_millis()
        );
        drop((idle, scada));
        d.stop().await;
    })
    .await;
}
