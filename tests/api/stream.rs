//! The WebSocket stream over real sockets against the daemon on the
//! simulator: subscriptions, statuses as they are polled, online/offline
//! events, commands with correlated replies, malformed messages, a hundred
//! clients while one never reads, lease ends told to the client that held
//! the lease, and closing on shutdown.

use std::collections::HashSet;
use std::time::{Duration, Instant};

use crate::support::api::{Api, Ws, config, connect, next_json, send_json, wait_for, ws_command};
use crate::support::{FOUR_DRIVES, TestDaemon};
use futures_util::{SinkExt, StreamExt};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

const LIMIT: Duration = Duration::from_secs(45);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn subscriptions_statuses_and_link_events() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let mut ws = connect(d.http, "", None).await;

        // One drive: only its statuses arrive, with the REST field names.
        send_json(&mut ws, json!({"type": "subscribe", "drives": ["lift"]})).await;
        let ack = next_json(&mut ws, Duration::from_secs(5)).await;
        assert_eq!(ack, json!({"type": "subscribed", "drives": ["lift"]}));
        for _ in 0..20 {
            let m = next_json(&mut ws, Duration::from_secs(5)).await;
            assert_eq!(
                (m["type"].as_str(), m["drive"].as_str()),
                (Some("status"), Some("lift")),
                "{m:#}"
            );
            assert_eq!(
                (m["bus"].as_str(), m["unit"].as_u64()),
                (Some("sim"), Some(2))
            );
            assert!(m["seen_at"].as_str().unwrap().ends_with('Z'));
            for field in [
                "turns",
                "angle_deg",
                "speed_rpm",
                "current_a",
                "voltage_v",
                "active",
                "mode",
                "fault",
                "fault_code",
            ] {
                assert!(!m["status"][field].is_null(), "{field} missing: {m:#}");
            }
        }

        // All drives: every one shows up.
        send_json(&mut ws, json!({"type": "subscribe", "drives": "all"})).await;
        wait_for(&mut ws, Duration::from_secs(5), "the ack", |m| {
            m["type"] == "subscribed"
        })
        .await;
        let mut seen = HashSet::new();
        while seen.len() < 4 {
            let m = next_json(&mut ws, Duration::from_secs(5)).await;
            if m["type"] == "status" {
                seen.insert(m["drive"].as_str().unwrap().to_string());
            }
        }

        // A drive that stops answering goes offline, then online again.
        d.sim().set_silent(3, true);
        let off = wait_for(&mut ws, Duration::from_secs(10), "the offline event", |m| {
            m["type"] == "offline"
        })
        .await;
        assert_eq!(off["drive"], "turntable");
        assert!(off["reason"].is_string());
        d.sim().set_silent(3, false);
        let on = wait_for(&mut ws, Duration::from_secs(10), "the online event", |m| {
            m["type"] == "online"
        })
        .await;
        assert_eq!(on["drive"], "turntable");

        // Unknown drives, garbage and binary frames get an error, and the
        // stream carries on.
        send_json(&mut ws, json!({"type": "subscribe", "drives": ["nosuch"]})).await;
        let e = wait_for(&mut ws, Duration::from_secs(5), "an error", |m| {
            m["type"] == "error"
        })
        .await;
        assert_eq!(e["problem"]["status"], 404);
        ws.send(Message::Text("{not json".into())).await.unwrap();
        let e = wait_for(&mut ws, Duration::from_secs(5), "an error", |m| {
            m["type"] == "error"
        })
        .await;
        assert_eq!(e["problem"]["status"], 400);
        ws.send(Message::Binary(vec![1, 2, 3].into()))
            .await
            .unwrap();
        let e = wait_for(&mut ws, Duration::from_secs(5), "an error", |m| {
            m["type"] == "error"
        })
        .await;
        assert!(e["problem"]["detail"].as_str().unwrap().contains("text"));
        wait_for(&mut ws, Duration::from_secs(5), "statuses again", |m| {
            m["type"] == "status"
        })
        .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_over_the_stream_get_correlated_replies() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let mut ws = connect(d.http, "", None).await;

        let r = ws_command(&mut ws, 1, "activate", "conveyor", json!({})).await;
        assert_eq!((r["ok"].as_bool(), r["result"]["command"].as_str()), (Some(true), Some("activate")));
        let r = ws_command(&mut ws, 2, "mode", "conveyor", json!({"mode": "speed"})).await;
        assert_eq!(r["result"]["written"][0]["raw"], 0xA);

        // Several in flight at once, ids of any JSON type, replies matched.
        for (id, body) in [(json!("a"), json!({"speed_rpm": 40})), (json!({"n": 3}), json!({"speed_rpm": 3000}))] {
            send_json(
                &mut ws,
                json!({"type": "command", "id": id, "op": "setpoint", "drive": "conveyor", "body": body}),
            )
            .await;
        }
        send_json(&mut ws, json!({"type": "command", "id": 4, "op": "status", "drive": "conveyor", "body": {"fresh": true}})).await;
        send_json(&mut ws, json!({"type": "command", "id": 5, "op": "teleport", "drive": "conveyor"})).await;
        send_json(&mut ws, json!({"type": "command", "id": 6, "op": "scan", "bus": "sim", "body": {"from": 1, "to": 4}})).await;
        let mut replies = std::collections::HashMap::new();
        while replies.len() < 5 {
            let m = next_json(&mut ws, Duration::from_secs(10)).await;
            if m["type"] == "reply" {
                replies.insert(m["id"].to_string(), m);
            }
        }
        let ok = &replies["\"a\""];
        assert_eq!(ok["ok"], true);
        assert_eq!(ok["result"]["written"][0]["raw"], 40);
        let range = &replies[r#"{"n":3}"#];
        assert_eq!((range["ok"].as_bool(), range["problem"]["status"].as_u64()), (Some(false), Some(422)));
        assert_eq!(range["problem"]["valid_range"]["max"], 2047.0);
        assert_eq!(replies["4"]["result"]["source"], "bus");
        let unknown = &replies["5"];
        assert_eq!(unknown["problem"]["status"], 400);
        assert!(unknown["problem"]["detail"].as_str().unwrap().contains("teleport"));
        let found: Vec<u64> = replies["6"]["result"]["answered"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| h["unit"].as_u64().unwrap())
            .collect();
        assert_eq!(found, [1, 2, 3, 4]);
        assert_eq!(d.sim().drive(1).unwrap().setpoints.speed_rpm, 40);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A client whose socket receive buffer is small, so a server writing to it
/// fills up quickly when it does not read.
async fn connect_small_buffer(addr: std::net::SocketAddr, query: &str) -> Ws {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let stream = socket.connect(addr).await.unwrap();
    let request = format!("ws://{addr}/api/v1/stream{query}")
        .into_client_request()
        .unwrap();
    let (ws, _) =
        tokio_tungstenite::client_async(request, tokio_tungstenite::MaybeTlsStream::Plain(stream))
            .await
            .unwrap();
    ws
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hundred_clients_keep_receiving_while_one_never_reads() {
    tokio::time::timeout(LIMIT, async {
        // A hundred clients of one address: its share is all the slots.
        let d = TestDaemon::start(&config(
            "stream_buffer = 8\nsend_buffer_bytes = 4096\nmax_connections_per_address = 128",
            "",
        ))
        .await;
        let names = ["conveyor", "lift", "turntable", "feeder"];

        // The slow one subscribes to everything and then reads nothing.
        let mut slow = connect_small_buffer(d.http, "?drives=all").await;

        let mut readers = Vec::new();
        for i in 0..99 {
            let query = format!("?drives={}", names[i % 4]);
            readers.push(connect(d.http, &query, None).await);
        }
        let metrics = reqwest::get(format!("http://{}/metrics", d.http))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        assert!(
            metrics.contains("drivegate_websocket_clients 100"),
            "{metrics}"
        );

        let polls_before = d.plant.buses()[0].handle.stats().polls;
        let started = Instant::now();
        let tasks: Vec<_> = readers
            .into_iter()
            .map(|mut ws| {
                tokio::spawn(async move {
                    let mut statuses = 0;
                    while statuses < 30 {
                        let m = next_json(&mut ws, Duration::from_secs(20)).await;
                        if m["type"] == "status" {
                            statuses += 1;
                        }
                    }
                    ws
                })
            })
            .collect();
        let mut readers = Vec::new();
        for t in tasks {
            readers.push(t.await.expect("every reader got 30 statuses"));
        }
        let took = started.elapsed();
        let polls = d.plant.buses()[0].handle.stats().polls - polls_before;
        // The bus kept polling all along (about 170 polls/s on this bus).
        assert!(
            polls as f64 >= 40.0 * took.as_secs_f64(),
            "{polls} polls in {took:?}"
        );

        // The slow client, reading at last, is told how much it missed.
        let lagged = wait_for(
            &mut slow,
            Duration::from_secs(20),
            "the lagged notice",
            |m| m["type"] == "lagged",
        )
        .await;
        assert!(lagged["missed"].as_u64().unwrap() > 0, "{lagged:#}");
        // ... and gets fresh statuses after it.
        wait_for(&mut slow, Duration::from_secs(5), "a status", |m| {
            m["type"] == "status"
        })
        .await;
        drop(readers);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_are_closed_when_the_daemon_stops() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        api.get("/healthz").await.expect(200);
        let mut ws = connect(d.http, "?drives=all", None).await;
        wait_for(&mut ws, Duration::from_secs(5), "a status", |m| {
            m["type"] == "status"
        })
        .await;
        let stopping = tokio::spawn(d.stop());
        let close = async {
            loop {
                match ws.next().await {
                    Some(Ok(Message::Close(frame))) => return frame.map(|f| u16::from(f.code)),
                    Some(Ok(_)) => {}
                    None | Some(Err(_)) => return None,
                }
            }
        };
        let code = tokio::time::timeout(Duration::from_secs(10), close)
            .await
            .expect("the stream closed on shutdown");
        assert_eq!(code, Some(1001));
        tokio::time::timeout(Duration::from_secs(15), stopping)
            .await
            .expect("the daemon stopped")
            .unwrap();
    })
    .await
    .expect("test finished in time");
}

/// The lease-expired events a stream gets for `drive` within `within`.
async fn lease_ends(ws: &mut Ws, drive: &str, within: Duration) -> usize {
    let until = tokio::time::Instant::now() + within;
    let mut n = 0;
    while let Ok(Some(Ok(m))) = tokio::time::timeout_at(until, ws.next()).await {
        if let Message::Text(t) = m {
            let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
            if v["type"] == "lease-expired" && v["drive"] == drive {
                n += 1;
            }
        }
    }
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_holding_a_lease_is_told_it_ended() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("stream_buffer = 2\nsend_buffer_bytes = 4096", "")).await;
        let api = Api::new(d.http, None);
        api.activate_in("conveyor", "speed").await;
        let setpoint = json!({"speed_rpm": 100, "lease_ms": 300});

        // Subscribed to nothing: the lease's end is its own business.
        let mut quiet = connect(d.http, "", None).await;
        let r = ws_command(&mut quiet, 1, "setpoint", "conveyor", setpoint.clone()).await;
        assert_eq!(r["ok"], true, "{r:#}");
        let ended = wait_for(
            &mut quiet,
            Duration::from_secs(10),
            "the lease-expired event",
            |v| v["type"] == "lease-expired",
        )
        .await;
        assert_eq!(
            (ended["drive"].as_str(), ended["ok"].as_bool()),
            (Some("conveyor"), Some(true)),
            "{ended:#}"
        );

        // Subscribed to everything and reading, it is told once.
        let mut reader = connect(d.http, "?drives=all", None).await;
        let r = ws_command(&mut reader, 2, "setpoint", "conveyor", setpoint.clone()).await;
        assert_eq!(r["ok"], true, "{r:#}");
        // Once: the first arrives (however loaded the machine), and no
        // second follows it.
        let first = wait_for(
            &mut reader,
            Duration::from_secs(10),
            "the lease-expired event",
            |v| v["type"] == "lease-expired" && v["drive"] == "conveyor",
        )
        .await;
        assert_eq!(first["ok"], true, "{first:#}");
        assert_eq!(
            lease_ends(&mut reader, "conveyor", Duration::from_secs(2)).await,
            0,
            "told more than once"
        );

        // Subscribed to everything and not reading while the lease ends:
        // updates are skipped for it, the lease's end is not.
        let mut slow = connect_small_buffer(d.http, "?drives=all").await;
        let r = ws_command(&mut slow, 3, "setpoint", "conveyor", setpoint).await;
        assert_eq!(r["ok"], true, "{r:#}");
        // Not reading while the bus polls 200 times more: about 60 KB of
        // status updates, against 8 KB of socket buffers and 2 messages of
        // stream buffer (a loaded machine polls slower; it takes longer).
        let bus = d.plant.buses()[0].handle.clone();
        let polls = bus.stats().polls;
        crate::support::eventually(Duration::from_secs(30), "200 polls", || {
            (bus.stats().polls >= polls + 200).then_some(())
        })
        .await;
        let ended = wait_for(
            &mut slow,
            Duration::from_secs(10),
            "the lease-expired event",
            |v| v["type"] == "lease-expired",
        )
        .await;
        assert_eq!(ended["drive"], "conveyor");
        let lagged = wait_for(
            &mut slow,
            Duration::from_secs(10),
            "the lagged notice",
            |v| v["type"] == "lagged",
        )
        .await;
        assert!(lagged["missed"].as_u64().unwrap() > 0, "{lagged:#}");
        drop((quiet, reader, slow));
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
