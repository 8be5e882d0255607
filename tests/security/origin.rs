//! The browser-origin guards, from the outside: a page of another site
//! (its `Origin`), a DNS-rebinding page (its `Host`) and the daemon's own
//! console (same origin) against the REST routes, the stream and the bus
//! monitor's live feed, on the default, token-less configuration.

use std::time::Duration;

use crate::support::input::{RawAnswer, raw_http, request, writes_on_wire};
use crate::support::{FOUR_DRIVES, TestDaemon};

const LIMIT: Duration = Duration::from_secs(60);

/// A WebSocket upgrade; `Connection: close` too, so that a refusal ends
/// the connection.
fn upgrade(path: &str, host: &str, origin: Option<&str>) -> Vec<u8> {
    let origin = origin.map_or_else(String::new, |o| format!("Origin: {o}\r\n"));
    format!(
        "GET {path} HTTP/1.1\r\nHost: {host}\r\n{origin}Upgrade: websocket\r\nConnection: Upgrade, close\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    .into_bytes()
}

fn problem_type(a: &RawAnswer) -> String {
    a.json()
        .and_then(|j| j["type"].as_str().map(str::to_string))
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foreign_pages_cannot_change_anything_and_the_own_origin_can() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.http;
        let own = format!("http://127.0.0.1:{}", addr.port());
        let host = format!("Host: 127.0.0.1:{}", addr.port());
        let writes = writes_on_wire(&d.plant);

        // What a form or a no-cors fetch from another site sends.
        for origin in ["http://evil.example", "null", "http://127.0.0.1:1"] {
            let a = raw_http(
                addr,
                &request(
                    "POST",
                    "/api/v1/drives/conveyor/commands/activate",
                    None,
                    &[&format!("Origin: {origin}")],
                    b"",
                ),
            )
            .await
            .unwrap();
            assert_eq!(a.status, 403, "{origin}: {}", a.text());
            assert_eq!(problem_type(&a), "urn:drivegate:problem:foreign-origin");
            assert!(a.text().contains(origin), "{}", a.text());
        }
        // Without Origin, a browser's cross-site label is enough.
        let a = raw_http(
            addr,
            &request(
                "POST",
                "/api/v1/drives/conveyor/commands/brake",
                None,
                &["Sec-Fetch-Site: cross-site"],
                b"",
            ),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 403, "{}", a.text());
        assert_eq!(writes_on_wire(&d.plant), writes, "a refused request reached the bus");
        assert!(
            d.metrics
                .render()
                .contains("drivegate_http_guard_refused_total{reason=\"origin\"} 3")
        );

        // The stream and the monitor's live feed: the upgrade is refused.
        for path in ["/api/v1/stream", "/api/v1/buses/sim/monitor/live"] {
            let a = raw_http(
                addr,
                &upgrade(path, &format!("127.0.0.1:{}", addr.port()), Some("http://evil.example")),
            )
            .await
            .unwrap();
            assert_eq!(a.status, 403, "{path}: {}", a.text());
            assert_eq!(problem_type(&a), "urn:drivegate:problem:foreign-origin");
        }

        // The same origin (the console) and no origin at all (scripts) work.
        let a = raw_http(
            addr,
            &format!("POST /api/v1/drives/conveyor/commands/activate HTTP/1.1\r\n{host}\r\nOrigin: {own}\r\nConnection: close\r\nContent-Length: 0\r\n\r\n").into_bytes(),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 200, "{}", a.text());
        let a = raw_http(
            addr,
            &request("POST", "/api/v1/drives/conveyor/commands/deactivate", None, &[], b""),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 200, "{}", a.text());
        let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
        tokio::io::AsyncWriteExt::write_all(
            &mut stream,
            &upgrade("/api/v1/stream", &format!("127.0.0.1:{}", addr.port()), Some(&own)),
        )
        .await
        .unwrap();
        let mut head = [0u8; 12];
        tokio::io::AsyncReadExt::read_exact(&mut stream, &mut head).await.unwrap();
        assert_eq!(&head, b"HTTP/1.1 101", "same-origin stream refused");
        // Reads from any page pass (the browser hides the answer from it).
        let a = raw_http(
            addr,
            &request("GET", "/api/v1/drives", None, &["Origin: http://evil.example"], b""),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 200, "{}", a.text());
        d.stop().await;
    })
    .await
    .expect("in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foreign_host_names_are_refused_and_listed_ones_served() {
    tokio::time::timeout(LIMIT, async {
        let toml = FOUR_DRIVES.replacen(
            "[http]\n",
            "[http]\nallowed_hosts = [\"gateway.plant.local\"]\nallowed_origins = [\"https://hmi.plant.local\"]\n",
            1,
        );
        let d = TestDaemon::start(&toml).await;
        let addr = d.http;
        let get = |host: &str| {
            format!("GET /api/v1/drives HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n")
                .into_bytes()
        };
        let a = raw_http(addr, &get(&format!("evil.example:{}", addr.port())))
            .await
            .unwrap();
        assert_eq!(a.status, 421, "{}", a.text());
        assert_eq!(problem_type(&a), "urn:drivegate:problem:unknown-host");
        assert!(
            a.text().contains("evil.example") && a.text().contains("allowed_hosts"),
            "{}",
            a.text()
        );
        for host in [
            format!("127.0.0.1:{}", addr.port()),
            format!("localhost:{}", addr.port()),
            format!("gateway.plant.local:{}", addr.port()),
        ] {
            let a = raw_http(addr, &get(&host)).await.unwrap();
            assert_eq!(a.status, 200, "{host}: {}", a.text());
        }
        // A listed origin may change things.
        let a = raw_http(
            addr,
            &request(
                "POST",
                "/api/v1/drives/lift/commands/fault-reset",
                None,
                &["Origin: https://hmi.plant.local"],
                b"",
            ),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 200, "{}", a.text());
        d.stop().await;
    })
    .await
    .expect("in time");
}
