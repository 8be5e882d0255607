//! The HTTP API's limits hold however a client pushes them: a body over
//! `[http] max_body_bytes` is refused with 413 whether its length is
//! announced, chunked or only claimed, a stream message over it closes that
//! stream, and a flood of connections beyond `max_connections` is refused
//! while the connections already open keep being served; idle connections
//! from one address take the free slots short of the last eighth, which is
//! kept for other addresses, and are closed after `header_timeout_ms`, so
//! the admin gets in from another address at once and from the same one
//! within the timeout.

use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::input::{
    ADMIN, VIEWER, check_answer, config, parse_answer, raw_http, writes_on_wire, ws_frame,
    ws_handshake,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const LIMIT: Duration = Duration::from_secs(60);
const MAX_BODY: usize = 1024;

/// A JSON object of exactly `n` bytes (a setpoint padded with spaces).
fn object_of(n: usize) -> Vec<u8> {
    let mut body = b"{\"speed_rpm\": 1".to_vec();
    body.resize(n - 1, b' ');
    body.push(b'}');
    body
}

fn put(body_header: &str, body: &[u8]) -> Vec<u8> {
    let mut bytes = format!(
        "PUT /api/v1/drives/lift/setpoint HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Bearer {ADMIN}\r\nContent-Type: application/json\r\n{body_header}\r\n\r\n"
    )
    .into_bytes();
    bytes.extend_from_slice(body);
    bytes
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn body_limits_hold_however_the_body_comes() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            &format!("max_body_bytes = {MAX_BODY}\nread_timeout_s = 30"),
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let writes = writes_on_wire(&d.plant);

        // At the limit: read (the drive is not active: 409); one over: 413.
        let at = object_of(MAX_BODY);
        let a = raw_http(addr, &put(&format!("Content-Length: {}", at.len()), &at))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 409, "{}", a.text());
        let over = object_of(MAX_BODY + 1);
        let a = raw_http(
            addr,
            &put(&format!("Content-Length: {}", over.len()), &over),
        )
        .await
        .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 413, "{}", a.text());

        // A gigabyte announced and never sent: refused on the announcement.
        let a = raw_http(addr, &put("Content-Length: 1000000000", b""))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 413, "{}", a.text());

        // Chunked: many small chunks adding up to more than the limit.
        let mut chunked = Vec::new();
        for _ in 0..10 {
            chunked.extend_from_slice(format!("{:x}\r\n", 200).as_bytes());
            chunked.extend_from_slice(&[b' '; 200]);
            chunked.extend_from_slice(b"\r\n");
        }
        chunked.extend_from_slice(b"0\r\n\r\n");
        let a = raw_http(addr, &put("Transfer-Encoding: chunked", &chunked))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 413, "{}", a.text());
        // One chunk announcing four gigabytes: refused once the limit is
        // passed (a chunked body does not say its whole length).
        let mut huge_chunk = b"ffffffff\r\n".to_vec();
        huge_chunk.extend_from_slice(&object_of(2 * MAX_BODY));
        let a = raw_http(addr, &put("Transfer-Encoding: chunked", &huge_chunk))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 413, "{}", a.text());

        // A length smaller than what follows: the rest is not a request.
        let a = raw_http(addr, &put("Content-Length: 5", &object_of(500)))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 400, "{}", a.text());
        assert_eq!(writes_on_wire(&d.plant), writes, "an oversized body wrote");

        // The stream: a message of exactly the limit is read, one byte more
        // closes the stream.
        let query = format!("?access_token={VIEWER}");
        let mut s = ws_handshake(addr, &query).await;
        let mut subscribe = br#"{"type":"subscribe","drives":"lift""#.to_vec();
        subscribe.resize(MAX_BODY - 1, b' ');
        subscribe.push(b'}');
        s.write_all(&ws_frame(0x1, &subscribe, true)).await.unwrap();
        let mut head = [0u8; 2];
        tokio::time::timeout(Duration::from_secs(5), s.read_exact(&mut head))
            .await
            .unwrap()
            .unwrap();
        let mut text = vec![0u8; usize::from(head[1] & 0x7F)];
        s.read_exact(&mut text).await.unwrap();
        assert!(
            String::from_utf8_lossy(&text).contains("subscribed"),
            "{}",
            String::from_utf8_lossy(&text)
        );
        subscribe.insert(1, b' ');
        s.write_all(&ws_frame(0x1, &subscribe, true)).await.unwrap();
        let mut rest = Vec::new();
        let closed = tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut rest)).await;
        assert!(
            closed.is_ok(),
            "a message over the limit left the stream open"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// Sends a GET on an open keep-alive connection and reads its answer.
async fn ask(s: &mut TcpStream) -> u16 {
    s.write_all(format!("GET /api/v1/drives/lift HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {VIEWER}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut got = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut chunk))
            .await
            .expect("an answer in time")
            .unwrap();
        assert!(n > 0, "closed");
        got.extend_from_slice(&chunk[..n]);
        if let Ok(a) = parse_answer(&got)
            && a.header("content-length")
                .and_then(|l| l.parse::<usize>().ok())
                == Some(a.body.len())
        {
            return a.status;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_connections_is_refused_and_the_open_ones_kept() {
    tokio::time::timeout(LIMIT, async {
        // One address holding all but the slot kept for other addresses
        // (the last eighth), then capped.
        let d = TestDaemon::start(&config(
            "max_connections = 9\nmax_connections_per_address = 8",
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let mut held = Vec::new();
        for _ in 0..8 {
            let mut s = TcpStream::connect(addr).await.unwrap();
            assert_eq!(ask(&mut s).await, 200);
            held.push(s);
        }
        // 300 at once: each is answered 503 too-many-connections, or closed
        // without an answer once 64 refusals are in flight; never served.
        let flood: Vec<_> = (0..300)
            .map(|_| {
                tokio::spawn(async move {
                    raw_http(
                        addr,
                        format!("GET /api/v1/drives HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Bearer {VIEWER}\r\n\r\n").as_bytes(),
                    )
                    .await
                })
            })
            .collect();
        let (mut refused, mut dropped) = (0, 0);
        for f in flood {
            match f.await.unwrap() {
                Ok(a) => {
                    assert_eq!(a.status, 503, "a connection over the limit was served");
                    assert_eq!(a.header("content-type"), Some("application/problem+json"));
                    assert_eq!(a.json().unwrap()["type"], "urn:drivegate:problem:too-many-connections");
                    refused += 1;
                }
                Err(_) => dropped += 1,
            }
        }
        println!("HTTP connection flood: 300 beyond the 8 one address may hold: {refused} answered 503, {dropped} closed unanswered");
        assert!(refused > 0);
        // The eight open connections are served as before.
        for s in &mut held {
            assert_eq!(ask(s).await, 200);
        }
        // Their slots come back when they close.
        drop(held);
        let mut served = false;
        for _ in 0..50 {
            let a = raw_http(addr, format!("GET /api/v1/drives HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Bearer {VIEWER}\r\n\r\n").as_bytes()).await;
            if a.is_ok_and(|a| a.status == 200) {
                served = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(served, "the slots did not come back");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A connection to `addr` from the loopback address `from`.
async fn connect_from(from: &str, addr: std::net::SocketAddr) -> std::io::Result<TcpStream> {
    let socket = tokio::net::TcpSocket::new_v4()?;
    socket.bind(format!("{from}:0").parse().unwrap())?;
    socket.connect(addr).await
}

/// An admin's `GET /api/v1/drives` from `from`: its status, or why none.
async fn admin_from(from: &str, addr: std::net::SocketAddr) -> Result<u16, String> {
    let mut s = connect_from(from, addr).await.map_err(|e| e.to_string())?;
    let request = format!(
        "GET /api/v1/drives HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Bearer {ADMIN}\r\n\r\n"
    );
    let _ = s.write_all(request.as_bytes()).await;
    let mut bytes = Vec::new();
    tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut bytes))
        .await
        .map_err(|_| "no answer within 10 s".to_string())?
        .map_err(|e| e.to_string())?;
    parse_answer(&bytes).map(|a| a.status)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_from_one_address_do_not_lock_the_admin_out() {
    tokio::time::timeout(LIMIT, async {
        crate::support::logs::capture_logs();
        // The defaults: 128 connections, no cap per address, 5 s for a head.
        let d = TestDaemon::start(&config("", "", true, "")).await;
        let addr = d.http;
        let header_timeout = Duration::from_millis(5000);
        let metric = |name: &'static str| crate::support::metrics::counter(&d, name);
        for name in [
            "drivegate_http_connections",
            "drivegate_http_header_timeouts_total",
            "drivegate_http_connections_refused_total{reason=\"limit\"}",
            "drivegate_http_connections_refused_total{reason=\"per_address\"}",
            "drivegate_http_connections_refused_total{reason=\"heaviest\"}",
            "drivegate_http_connections_refused_total{reason=\"files\"}",
        ] {
            let fresh = d.metrics.render();
            assert_eq!(
                crate::support::metrics::exported(&fresh, name),
                0.0,
                "{name} in a fresh /metrics"
            );
        }
        // 200 connections from 127.0.0.1 that send nothing.
        let opened = tokio::time::Instant::now();
        let mut idle = Vec::new();
        for _ in 0..200 {
            idle.push(connect_from("127.0.0.1", addr).await.unwrap());
        }
        crate::support::wait::eventually(
            Duration::from_secs(10),
            "the idle connections held (112) or refused (88)",
            || {
                (metric("drivegate_http_connections") == 112.0
                    && metric("drivegate_http_connections_refused_total{reason=\"heaviest\"}")
                        >= 88.0)
                    .then_some(())
            },
        )
        .await;
        // The admin, from another address: served at once.
        let asked = tokio::time::Instant::now();
        assert_eq!(admin_from("127.0.0.2", addr).await, Ok(200));
        let elsewhere = asked.elapsed();
        assert!(elsewhere < Duration::from_secs(2), "{elsewhere:?}");
        // From the same address: refused while it holds the most, served
        // once the idle ones are closed for the head they never sent.
        let mut refused = 0;
        let same = loop {
            match admin_from("127.0.0.1", addr).await {
                Ok(200) => break opened.elapsed(),
                Ok(503) | Err(_) => refused += 1,
                Ok(other) => panic!("the admin from 127.0.0.1 got {other}"),
            }
            assert!(
                opened.elapsed() < header_timeout + Duration::from_secs(5),
                "the admin from 127.0.0.1 was not served within the header timeout"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        assert!(refused > 0, "served before the idle connections were closed");
        assert!(same >= header_timeout - Duration::from_millis(200), "{same:?}");
        // Every idle one is closed for its head (the admin may have been
        // served as soon as the first of them was).
        crate::support::wait::eventually(
            Duration::from_secs(10),
            "the 112 idle connections closed for their head",
            || (metric("drivegate_http_header_timeouts_total") >= 112.0).then_some(()),
        )
        .await;
        println!(
            "HTTP: 200 idle connections from 127.0.0.1 (112 held, {} refused): an admin from 127.0.0.2 served in {} ms, one from 127.0.0.1 after {:.1} s ({refused} tries refused; header_timeout_ms 5000), {} connections closed for their head",
            metric("drivegate_http_connections_refused_total{reason=\"heaviest\"}"),
            elsewhere.as_millis(),
            same.as_secs_f64(),
            metric("drivegate_http_header_timeouts_total"),
        );
        // The refusals of 127.0.0.1 were logged a few times, once per
        // second at most, the first with the key.
        let port = format!("listener=127.0.0.1:{}", addr.port());
        let lines: Vec<String> = crate::support::logs::log_text()
            .lines()
            .filter(|l| l.contains("HTTP: connections from 127.0.0.1 refused") && l.contains(&port))
            .map(str::to_string)
            .collect();
        assert!((1..=6).contains(&lines.len()), "{lines:#?}");
        assert!(lines[0].contains("[http] max_connections"), "{}", lines[0]);
        drop(idle);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_two_clients_of_one_address_keep_working_beside_a_flood_from_another() {
    tokio::time::timeout(LIMIT, async {
        // The defaults: 128 connections, no cap per address.
        let d = TestDaemon::start(&config("", "", true, "")).await;
        let addr = d.http;
        let metric = |name: &str| crate::support::metrics::counter(&d, name);
        // 32 kept-alive clients from one address (a dashboard's panels),
        // each answered.
        let mut panels = Vec::new();
        for _ in 0..32 {
            let mut s = connect_from("127.0.0.2", addr).await.unwrap();
            assert_eq!(ask(&mut s).await, 200);
            panels.push(s);
        }
        // 300 idle sockets from another address.
        let mut idle = Vec::new();
        for _ in 0..300 {
            idle.push(connect_from("127.0.0.3", addr).await.unwrap());
        }
        let held = "drivegate_connections_by_address{face=\"http\",address=\"127.0.0.3\"}";
        let turned = "drivegate_connections_turned_away_total{face=\"http\",address=\"127.0.0.3\"}";
        crate::support::wait::eventually(
            Duration::from_secs(20),
            "the 300 held or refused",
            || (metric(held) + metric(turned) == 300.0).then_some(()),
        )
        .await;
        // The free slots short of the last eighth: 128 - 16 - 32 = 80.
        assert_eq!(metric(held), 80.0);
        assert_eq!(
            metric("drivegate_connections_refused_total{face=\"http\",reason=\"heaviest\"}"),
            220.0
        );
        // The 32 keep working, and a client from a third address is served.
        for s in &mut panels {
            assert_eq!(ask(s).await, 200);
        }
        let asked = tokio::time::Instant::now();
        assert_eq!(admin_from("127.0.0.4", addr).await, Ok(200));
        let waited = asked.elapsed();
        println!(
            "HTTP, defaults (max_connections 128): 32 kept-alive clients from 127.0.0.2 answered throughout; \
             300 idle sockets from 127.0.0.3: 80 held, 220 refused; a client from 127.0.0.4 served in {} ms",
            waited.as_millis()
        );
        drop(idle);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
