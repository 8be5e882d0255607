//! Slow and hung HTTP clients against the daemon on the simulator, over
//! real sockets: request heads trickled a byte at a time (slow-loris),
//! bodies that never complete or trickle, kept-alive connections left
//! unused, and stream clients that stop answering pings. Each is
//! disconnected after `[http] header_timeout_ms` (a head), `read_timeout_s`
//! (a body) or the idle timeout (the stream) rather than holding one of the
//! `max_connections` slots for ever;
//! a well-behaved client is served throughout and no socket or task is left
//! behind.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use crate::support::TestDaemon;
use crate::support::input::{
    ADMIN, Baseline, Bystander, VIEWER, check_answer, config, parse_answer, writes_on_wire,
    ws_frame, ws_handshake, ws_handshake_small_buffer,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const LIMIT: Duration = Duration::from_secs(60);
/// `[http] read_timeout_s` of these tests.
const READ_TIMEOUT: Duration = Duration::from_secs(1);
/// `[http] header_timeout_ms` of the slow-loris test: long enough that a
/// loaded machine's stalls cannot close the trickling clients before the
/// test has seen them hold every slot.
const LORIS_HEADER_TIMEOUT: Duration = Duration::from_secs(3);

/// Reads until the server closes the connection; what it sent, or `None`
/// if it is still open after `limit`.
async fn read_until_closed(
    stream: &mut (impl AsyncReadExt + Unpin),
    limit: Duration,
) -> Option<Vec<u8>> {
    let mut all = Vec::new();
    let mut chunk = [0u8; 4096];
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, stream.read(&mut chunk)).await {
            Ok(Ok(0) | Err(_)) => return Some(all),
            Ok(Ok(n)) => all.extend_from_slice(&chunk[..n]),
            Err(_) => return None,
        }
    }
}

/// Sends `bytes` one at a time, `gap` apart, until done or the server
/// closes; true when the server closed first.
async fn trickle(stream: &mut TcpStream, bytes: &[u8], gap: Duration) -> bool {
    for b in bytes {
        if stream.write_all(&[*b]).await.is_err() {
            return true;
        }
        tokio::time::sleep(gap).await;
    }
    false
}

async fn get_status(addr: SocketAddr) -> u16 {
    let client = reqwest::Client::new();
    client
        .get(format!("http://{addr}/api/v1/drives/conveyor/status"))
        .bearer_auth(VIEWER)
        .timeout(Duration::from_secs(5))
        .send()
        .await
        .map(|r| r.status().as_u16())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_loris_heads_lose_their_connection_slots() {
    tokio::time::timeout(LIMIT, async {
        // Eight slots for one address (of nine: the last is kept for other
        // addresses), capped there; the idle timeout is long, so only the
        // head's deadline can free a slot a trickling client holds.
        let d = TestDaemon::start(&config(
            "max_connections = 9\nmax_connections_per_address = 8\nidle_timeout_s = 60\nheader_timeout_ms = 3000",
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(addr, Some(VIEWER));
        bystander.wait_for(3).await;

        // Seven clients take the other seven slots, each sending a request
        // head one byte every 100 ms (it would take seconds to finish).
        let head = format!(
            "GET /api/v1/drives/conveyor/status HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {VIEWER}\r\nX-Padding: {}\r\n\r\n",
            "p".repeat(40)
        );
        let (connected_tx, mut connected) = tokio::sync::mpsc::channel(7);
        let mut lorises = Vec::new();
        for _ in 0..7 {
            let head = head.clone();
            let connected_tx = connected_tx.clone();
            lorises.push(tokio::spawn(async move {
                // Taken before connecting: the server's deadline starts at
                // its accept, which may come before `connect` returns.
                let opened = Instant::now();
                let mut s = TcpStream::connect(addr).await.unwrap();
                let _ = connected_tx.send(opened).await;
                let closed_early = trickle(&mut s, head.as_bytes(), Duration::from_millis(100)).await;
                let answer = read_until_closed(&mut s, Duration::from_secs(10)).await;
                (closed_early, opened.elapsed(), answer)
            }));
        }
        // Once all seven are connected, and while they hold the slots, a
        // newcomer is refused (503)...
        drop(connected_tx);
        let mut first_opened = None;
        for _ in 0..7 {
            let opened = connected.recv().await.expect("a trickling client connected");
            first_opened.get_or_insert(opened);
        }
        let first_opened = first_opened.expect("seven trickling clients");
        let mut refused = false;
        let mut seen = Vec::new();
        while !refused && first_opened.elapsed() < LORIS_HEADER_TIMEOUT * 9 / 10 {
            let status = get_status(addr).await;
            seen.push((status, first_opened.elapsed()));
            refused = status == 503;
            if !refused {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
        assert!(
            refused,
            "seven trickling clients did not fill the slots: {seen:?}"
        );
        // ...and once the deadline has passed, served again.
        for loris in lorises {
            let (closed_early, after, answer) = loris.await.unwrap();
            assert!(closed_early, "a trickling client finished its head");
            assert!(after >= LORIS_HEADER_TIMEOUT, "closed after {after:?}");
            assert!(answer.is_some(), "a trickling client kept its connection");
        }
        let mut served = false;
        for _ in 0..50 {
            if get_status(addr).await == 200 {
                served = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(served, "the slots did not come back");

        // A kept-alive connection left unused is closed after the deadline
        // too; one request on it is answered first.
        let mut kept = TcpStream::connect(addr).await.unwrap();
        let opened = Instant::now();
        kept.write_all(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n")
            .await
            .unwrap();
        let answer = read_until_closed(&mut kept, Duration::from_secs(10))
            .await
            .expect("the unused kept-alive connection is closed");
        assert!(opened.elapsed() >= LORIS_HEADER_TIMEOUT);
        assert!(String::from_utf8_lossy(&answer).starts_with("HTTP/1.1 200"));

        let (ok, slowest) = bystander.finish(3, "slow-loris heads").await;
        println!("HTTP slow-loris: 7 trickling heads closed after the header timeout; well-behaved client: {ok} answers, slowest {slowest:?}");
        drop(kept);
        baseline
            .assert_back(Duration::from_secs(5), "slow-loris heads")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bodies_that_never_complete_are_answered_408_and_write_nothing() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            "idle_timeout_s = 60\nread_timeout_s = 1",
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(addr, Some(VIEWER));
        bystander.wait_for(3).await;
        let writes = writes_on_wire(&d.plant);

        let body = br#"{"ratio": 3, "save": false, "force": false}"#;
        let head = |path: &str| {
            format!(
                "PUT {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Bearer {ADMIN}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
                body.len()
            )
        };
        // Part of the body, then nothing; the body a byte every 200 ms; and
        // a chunked body that never sends its last chunk.
        let mut cases = Vec::new();
        for (i, how) in ["stall", "trickle", "chunked"].into_iter().enumerate() {
            let head = head("/api/v1/drives/lift/inertia");
            cases.push(tokio::spawn(async move {
                let opened = Instant::now();
                let mut s = TcpStream::connect(addr).await.unwrap();
                match how {
                    "stall" => {
                        s.write_all(head.as_bytes()).await.unwrap();
                        s.write_all(&body[..10]).await.unwrap();
                    }
                    "trickle" => {
                        s.write_all(head.as_bytes()).await.unwrap();
                        // Read the answer while still trickling: writing
                        // on after the server closed would reset the
                        // connection and lose the answer.
                        let (mut rd, mut wr) = s.into_split();
                        let writer = tokio::spawn(async move {
                            for b in body {
                                if wr.write_all(&[*b]).await.is_err() {
                                    return;
                                }
                                tokio::time::sleep(Duration::from_millis(200)).await;
                            }
                        });
                        let answer = read_until_closed(&mut rd, Duration::from_secs(10)).await;
                        writer.abort();
                        return (i, how, opened.elapsed(), answer);
                    }
                    _ => {
                        let chunked = head.replace(
                            &format!("Content-Length: {}", body.len()),
                            "Transfer-Encoding: chunked",
                        );
                        s.write_all(chunked.as_bytes()).await.unwrap();
                        s.write_all(format!("{:x}\r\n", body.len()).as_bytes())
                            .await
                            .unwrap();
                        s.write_all(body).await.unwrap();
                        s.write_all(b"\r\n").await.unwrap();
                    }
                }
                let answer = read_until_closed(&mut s, Duration::from_secs(10)).await;
                (i, how, opened.elapsed(), answer)
            }));
        }
        for case in cases {
            let (_, how, after, answer) = case.await.unwrap();
            let answer = answer.unwrap_or_else(|| panic!("{how}: the connection stayed open"));
            let answer = parse_answer(&answer).unwrap_or_else(|e| panic!("{how}: {e}"));
            check_answer(&answer).unwrap();
            assert_eq!(answer.status, 408, "{how}: {}", answer.text());
            assert_eq!(
                answer.json().unwrap()["type"],
                "urn:drivegate:problem:request-timeout"
            );
            assert!(after >= READ_TIMEOUT, "{how}: answered after {after:?}");
        }
        assert_eq!(writes_on_wire(&d.plant), writes, "an incomplete body wrote");
        assert_eq!(d.sim().drive(2).unwrap().settings.inertia_ratio, 1);

        let (ok, slowest) = bystander.finish(3, "incomplete bodies").await;
        println!("HTTP bodies that never complete: 3 answered 408; well-behaved client: {ok} answers, slowest {slowest:?}");
        baseline
            .assert_back(Duration::from_secs(5), "incomplete bodies")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stream_clients_that_stop_answering_pings_are_closed() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("idle_timeout_s = 1", "", false, "")).await;
        let addr = d.http;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(addr, None);
        bystander.wait_for(3).await;

        // A healthy client (tungstenite answers pings while it reads) keeps
        // its stream, subscribed or not.
        let mut healthy = {
            use tokio_tungstenite::tungstenite::client::IntoClientRequest;
            let request = format!("ws://{addr}/api/v1/stream?drives=all")
                .into_client_request()
                .unwrap();
            tokio_tungstenite::connect_async(request).await.unwrap().0
        };

        // Two that read what comes but never answer, not even a pong: one
        // subscribed to nothing (it only gets pings), one to every drive (a
        // busy stream).
        // (The daemon's idle time starts when it takes the stream, after
        // `opened`, however long the handshakes take.)
        let opened = Instant::now();
        let mut deaf = ws_handshake(addr, "").await;
        let mut mute = ws_handshake(addr, "?drives=all").await;
        let mute_read = tokio::spawn(async move {
            let got = read_until_closed(&mut mute, Duration::from_secs(10)).await;
            got.map(|bytes| bytes.len())
        });
        let healthy_read = tokio::spawn(async move {
            use futures_util::StreamExt;
            let mut statuses = 0;
            let until = tokio::time::Instant::now() + Duration::from_secs(3);
            while let Ok(Some(Ok(m))) = tokio::time::timeout_at(until, healthy.next()).await {
                if m.to_text().is_ok_and(|t| t.contains("\"status\"")) {
                    statuses += 1;
                }
            }
            (statuses, healthy)
        });
        let deaf_closed = read_until_closed(&mut deaf, Duration::from_secs(10)).await;
        assert!(deaf_closed.is_some(), "a quiet client that never answers kept its stream");
        let got = mute_read.await.unwrap();
        let after = opened.elapsed();
        let got = got.expect("a client that never answers pings kept its stream");
        assert!(got > 0, "the mute client was sent nothing");
        assert!(after >= Duration::from_secs(1), "closed after {after:?}");
        let (statuses, mut healthy) = healthy_read.await.unwrap();
        assert!(statuses > 10, "the healthy stream got {statuses} statuses");
        // The healthy one is still open after three idle timeouts.
        {
            use futures_util::SinkExt;
            healthy
                .send(tokio_tungstenite::tungstenite::Message::Text(
                    r#"{"type":"subscribe","drives":[]}"#.into(),
                ))
                .await
                .expect("the healthy stream is open");
        }
        drop(healthy);

        // A ping from the client is answered with a pong; then silence.
        let mut pinger = ws_handshake(addr, "").await;
        pinger
            .write_all(&ws_frame(0x9, b"are you there", true))
            .await
            .unwrap();
        let mut head = [0u8; 2];
        tokio::time::timeout(Duration::from_secs(5), pinger.read_exact(&mut head))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(head[0] & 0x0F, 0xA, "the answer to a ping is a pong");
        assert!(read_until_closed(&mut pinger, Duration::from_secs(10)).await.is_some());

        let (ok, slowest) = bystander.finish(3, "hung stream clients").await;
        println!("stream clients that never answer pings: closed after {after:?}; well-behaved client: {ok} answers, slowest {slowest:?}");
        drop((deaf, pinger));
        baseline
            .assert_back(Duration::from_secs(5), "hung stream clients")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// The number of open stream sessions, from `/metrics`.
async fn stream_clients(addr: SocketAddr) -> Option<u64> {
    let text = reqwest::get(format!("http://{addr}/metrics"))
        .await
        .ok()?
        .text()
        .await
        .ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix("drivegate_websocket_clients "))
        .and_then(|v| v.trim().parse().ok())
}

/// A stream client that sent a leased setpoint and a burst of commands,
/// then hung: its kernel keeps the connection open and acknowledges, but it
/// reads nothing. Its replies fill the socket, so the session's writer waits
/// on the socket and its reader for a free command slot; neither may wait
/// longer than the idle timeout, so the session ends, the connection slot
/// comes back and the lease taken over the socket stops the motor.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hung_stream_client_with_commands_in_flight_loses_its_slot() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            "idle_timeout_s = 2\nsend_buffer_bytes = 4096",
            "",
            false,
            "",
        ))
        .await;
        let addr = d.http;
        let http = reqwest::Client::new();
        for (method, path, body) in [
            ("POST", "/api/v1/drives/conveyor/commands/activate", None),
            ("PUT", "/api/v1/drives/conveyor/mode", Some(r#"{"mode":"speed"}"#)),
        ] {
            let url = format!("http://{addr}{path}");
            let request = match body {
                Some(b) => http
                    .request(method.parse().unwrap(), url)
                    .header("content-type", "application/json")
                    .body(b),
                None => http.request(method.parse().unwrap(), url),
            };
            assert_eq!(request.send().await.unwrap().status(), 200, "{path}");
        }
        let baseline = Baseline::take(&d).await;

        let opened = Instant::now();
        let mut hung = ws_handshake_small_buffer(addr, "?drives=all").await;
        let setpoint = r#"{"type":"command","id":0,"op":"setpoint","drive":"conveyor","body":{"speed_rpm":150,"lease_ms":60000}}"#;
        hung.write_all(&ws_frame(0x1, setpoint.as_bytes(), true))
            .await
            .unwrap();
        let sim = d.sim();
        crate::support::eventually(Duration::from_secs(5), "the setpoint on the drive", || {
            (sim.drive(1)?.setpoints.speed_rpm == 150).then_some(())
        })
        .await;
        for id in 1..=300 {
            let status =
                format!(r#"{{"type":"command","id":{id},"op":"status","drive":"conveyor"}}"#);
            hung.write_all(&ws_frame(0x1, status.as_bytes(), true))
                .await
                .unwrap();
        }
        assert_eq!(stream_clients(addr).await, Some(1));

        // Hung from now on. The session ends within the idle timeout of
        // its last blocked wait, with a wide margin for a loaded machine.
        let mut gone = false;
        for _ in 0..150 {
            if stream_clients(addr).await == Some(0) {
                gone = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let after = opened.elapsed();
        assert!(gone, "a hung stream client still holds its session after {after:?}");
        assert!(after >= Duration::from_secs(2), "closed after {after:?}");
        // The lease it held ended with it and stopped the motor.
        crate::support::eventually(Duration::from_secs(5), "the stop", || {
            (sim.drive(1)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        // The server closed the connection: what it had sent, then the end.
        assert!(
            read_until_closed(&mut hung, Duration::from_secs(10))
                .await
                .is_some(),
            "the server kept the hung client's connection open"
        );
        println!("a hung stream client with commands in flight: closed after {after:?}");
        drop(hung);
        baseline
            .assert_back(Duration::from_secs(5), "a hung stream client")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
