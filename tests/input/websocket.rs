//! Garbage on the WebSocket stream, over real sockets: frames no client
//! library would send (lengths of exabytes, oversized messages and control
//! frames, invalid UTF-8, unmasked frames, reserved opcodes), binary
//! messages, and generated JSON of every shape as messages and command
//! bodies. Protocol violations close that stream only; messages that are
//! merely wrong get an `error` (or a refused `reply`) and the stream goes on;
//! nothing is written to a drive; a well-behaved stream client keeps
//! receiving statuses throughout, and no socket or task is left behind.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::api::{Ws, connect};
use crate::support::input::{
    Baseline, Bystander, OPERATOR, VIEWER, config, writes_on_wire, ws_frame, ws_handshake,
};
use futures_util::{SinkExt, StreamExt};
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::{Config, TestRunner};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::Message;

const LIMIT: Duration = Duration::from_secs(60);
const MAX_MESSAGE: usize = 4096;

/// The next message that is not a status update or a ping, within 5 s.
async fn next_answer(ws: &mut Ws) -> Value {
    let until = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        let m = tokio::time::timeout_at(until, ws.next())
            .await
            .expect("an answer in time")
            .expect("the stream is open")
            .expect("a valid frame");
        if let Message::Text(t) = m {
            let v: Value = serde_json::from_str(t.as_str()).expect("JSON text");
            // News of the drives, not answers: a refused write is news too
            // (the core publishes every write's end, refusals included).
            if !matches!(
                v["type"].as_str(),
                Some("status" | "online" | "offline" | "lagged" | "write")
            ) {
                return v;
            }
        }
    }
}

/// Reads until the server closes; false if it is still open after 10 s.
async fn closed(stream: &mut tokio::net::TcpStream) -> bool {
    let mut sink = [0u8; 4096];
    let until = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        match tokio::time::timeout_at(until, stream.read(&mut sink)).await {
            Ok(Ok(0) | Err(_)) => return true,
            Ok(Ok(_)) => {}
            Err(_) => return false,
        }
    }
}

/// A well-behaved stream client, counting the statuses it receives.
struct Watcher {
    statuses: Arc<AtomicU64>,
    stop: tokio_util::sync::CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Watcher {
    fn start(mut ws: Ws) -> Watcher {
        let statuses = Arc::new(AtomicU64::new(0));
        let stop = tokio_util::sync::CancellationToken::new();
        let (count, done) = (statuses.clone(), stop.clone());
        let task = tokio::spawn(async move {
            loop {
                tokio::select! {
                    () = done.cancelled() => return,
                    m = ws.next() => match m {
                        Some(Ok(Message::Text(t))) if t.as_str().contains("\"type\":\"status\"") => {
                            count.fetch_add(1, Ordering::Relaxed);
                        }
                        Some(Ok(_)) => {}
                        other => panic!("the well-behaved stream ended: {other:?}"),
                    },
                }
            }
        });
        Watcher {
            statuses,
            stop,
            task,
        }
    }

    fn statuses(&self) -> u64 {
        self.statuses.load(Ordering::Relaxed)
    }

    /// Waits for `more` statuses than now: the stream still flows.
    async fn still_receiving(&self, more: u64) {
        let target = self.statuses() + more;
        crate::support::eventually(
            Duration::from_secs(5),
            "statuses on the well-behaved stream",
            || (self.statuses() >= target).then_some(()),
        )
        .await;
    }

    /// Closes it; the statuses it got.
    async fn stop(self) -> u64 {
        self.stop.cancel();
        let statuses = self.statuses.clone();
        self.task
            .await
            .expect("the well-behaved stream stayed open");
        statuses.load(Ordering::Relaxed)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protocol_violations_close_only_their_stream() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            &format!("max_body_bytes = {MAX_MESSAGE}"),
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(addr, Some(VIEWER));
        let watcher = Watcher::start(connect(addr, "?drives=all", Some(VIEWER)).await);
        watcher.still_receiving(5).await;
        let query = format!("?drives=all&access_token={VIEWER}");

        let huge_text = ws_frame(0x1, &vec![b'x'; 64 * 1024], true);
        let violations: Vec<(&str, Vec<u8>)> = vec![
            // A frame header announcing 2^63 - 1 bytes, then nothing.
            ("an exabyte frame", {
                let mut f = vec![0x81, 0x80 | 127];
                f.extend_from_slice(&(i64::MAX as u64).to_be_bytes());
                f.extend_from_slice(&[1, 2, 3, 4]);
                f
            }),
            ("a message over max_body_bytes", huge_text),
            ("a message over the limit in fragments", {
                let mut f = Vec::new();
                for _ in 0..4 {
                    let mut part = ws_frame(0x0, &vec![b'y'; 1500], true);
                    part[0] &= 0x7F; // not the last fragment
                    f.extend(part);
                }
                f[0] = (f[0] & 0xF0) | 0x1; // the first is a text frame
                f
            }),
            ("invalid UTF-8 in a text frame", ws_frame(0x1, &[0x7B, 0xFF, 0xFE, 0x7D], true)),
            ("an unmasked frame", ws_frame(0x1, br#"{"type":"subscribe","drives":"all"}"#, false)),
            ("a reserved opcode", ws_frame(0x3, b"??", true)),
            ("a ping of 200 bytes", {
                let mut f = vec![0x89, 0x80 | 126];
                f.extend_from_slice(&200u16.to_be_bytes());
                f.extend_from_slice(&[0, 0, 0, 0]);
                f.extend_from_slice(&[b'p'; 200]);
                f
            }),
            ("a continuation with nothing to continue", ws_frame(0x0, b"tail", true)),
            ("reserved bits set", {
                let mut f = ws_frame(0x1, b"{}", true);
                f[0] |= 0x70;
                f
            }),
        ];
        for (what, bytes) in &violations {
            let mut s = ws_handshake(addr, &query).await;
            let _ = s.write_all(bytes).await;
            assert!(closed(&mut s).await, "{what}: the stream stayed open");
            watcher.still_receiving(2).await;
        }

        // A binary message is answered with an error; the stream goes on.
        let mut ws = connect(addr, "", Some(VIEWER)).await;
        ws.send(Message::Binary(vec![0x01, 0x02, 0xFF].into()))
            .await
            .unwrap();
        let answer = next_answer(&mut ws).await;
        assert_eq!(answer["type"], "error", "{answer}");
        assert_eq!(answer["problem"]["status"], 400);
        ws.send(Message::Text(r#"{"type":"subscribe","drives":"lift"}"#.into()))
            .await
            .unwrap();
        assert_eq!(next_answer(&mut ws).await["type"], "subscribed");
        drop(ws);

        let statuses = watcher.stop().await;
        let (ok, _) = bystander.finish(3, "WebSocket protocol violations").await;
        println!(
            "WebSocket: {} protocol violations closed their stream; well-behaved stream {statuses} statuses, HTTP client {ok} answers",
            violations.len()
        );
        baseline
            .assert_back(Duration::from_secs(5), "WebSocket protocol violations")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A stream message of any shape: subscriptions and commands with odd
/// fields, JSON values of every kind, and text that is not JSON at all.
fn message() -> impl Strategy<Value = String> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        (-1e6..1e6f64).prop_map(Value::from),
        prop::sample::select(vec![-1.0, 0.0, 1.0, 2047.5, 65536.0, 1e300]).prop_map(Value::from),
        ".{0,16}".prop_map(Value::String),
    ];
    let value = leaf.prop_recursive(2, 10, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,8}", inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    });
    let name = prop_oneof![
        3 => prop::sample::select(vec!["all", "lift", "conveyor", "1", "sim", "nosuch", ""])
            .prop_map(Value::from),
        1 => value.clone(),
    ];
    let subscribe = prop_oneof![
        name.clone(),
        prop::collection::vec(name.clone(), 0..3).prop_map(Value::Array),
    ]
    .prop_map(|drives| json!({"type": "subscribe", "drives": drives}));
    let field = prop::sample::select(vec![
        "speed_rpm",
        "torque_a",
        "lease_ms",
        "mode",
        "ratio",
        "alpha",
        "from",
        "to",
        "address",
        "only_drive_on_bus",
        "enabled",
        "fresh",
        "force",
        "save",
        "stall_ms",
        "limit_a",
    ]);
    let body = prop_oneof![
        3 => prop::collection::btree_map(field, value.clone(), 0..3).prop_map(|m| {
            Value::Object(m.into_iter().map(|(k, v)| (k.to_string(), v)).collect())
        }),
        1 => value.clone(),
    ];
    let command = (
        prop_oneof![3 => any::<u32>().prop_map(Value::from), 1 => value.clone()],
        prop::sample::select(vec![
            "activate",
            "brake",
            "factory-reset",
            "setpoint",
            "mode",
            "inertia",
            "protection",
            "speed-ramp",
            "lease-renew",
            "lease-release",
            "status",
            "scan",
            "set-address",
            "rs485-control",
            "launch",
            "",
        ]),
        prop::sample::select(vec!["drive", "bus", "drives"]),
        name,
        prop::option::of(body),
    )
        .prop_map(|(id, op, key, target, body)| {
            let mut m = json!({"type": "command", "id": id, "op": op});
            m[key] = target;
            if let Some(body) = body {
                m["body"] = body;
            }
            m
        });
    prop_oneof![
        2 => subscribe.prop_map(|v| v.to_string()),
        5 => command.prop_map(|v| v.to_string()),
        2 => value.prop_map(|v| v.to_string()),
        1 => ".{0,64}",
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_of_every_shape_get_an_answer_and_write_nothing() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            &format!("max_body_bytes = {MAX_MESSAGE}"),
            "",
            true,
            "",
        ))
        .await;
        let addr = d.http;
        let baseline = Baseline::take(&d).await;
        let watcher = Watcher::start(connect(addr, "?drives=all", Some(VIEWER)).await);
        watcher.still_receiving(5).await;
        let writes = writes_on_wire(&d.plant);

        // A viewer's stream: whatever it sends, nothing may be written; each
        // message gets one answer and the stream stays open.
        let mut ws = connect(addr, "", Some(VIEWER)).await;
        let mut runner = TestRunner::new(Config {
            cases: 300,
            failure_persistence: None,
            ..Config::default()
        });
        let mut messages = Vec::new();
        for _ in 0..runner.config().cases {
            messages.push(
                message()
                    .new_tree(&mut runner)
                    .unwrap()
                    .current(),
            );
        }
        let mut answers = std::collections::BTreeMap::<String, u32>::new();
        for text in &messages {
            ws.send(Message::Text(text.clone().into())).await.unwrap();
            let answer = next_answer(&mut ws).await;
            let kind = match answer["type"].as_str() {
                Some("error") => {
                    // Not understood (400), or a subscription to a drive
                    // that is not there (404).
                    let status = answer["problem"]["status"].as_u64();
                    assert!(matches!(status, Some(400 | 404)), "{text}: {answer}");
                    "error".to_string()
                }
                Some("subscribed") => "subscribed".to_string(),
                Some("reply") if answer["ok"] == false => {
                    let status = answer["problem"]["status"].as_u64().unwrap();
                    assert!((400..500).contains(&status), "{text}: {answer}");
                    format!("refused {status}")
                }
                Some("reply") => {
                    // A viewer may read a status; nothing else.
                    assert!(text.contains("\"status\""), "{text} was carried out: {answer}");
                    "status read".to_string()
                }
                _ => panic!("{text}: unexpected answer {answer}"),
            };
            *answers.entry(kind).or_default() += 1;
        }
        assert_eq!(writes_on_wire(&d.plant), writes, "a viewer's message wrote");
        println!("WebSocket: {} generated messages, answers: {answers:?}", messages.len());
        assert!(answers.contains_key("error") && answers.keys().any(|k| k.starts_with("refused")));
        drop(ws);

        // An operator's command bodies of the wrong shape are refused with
        // the REST route's problem, and write nothing either.
        let mut ws = connect(addr, "", Some(OPERATOR)).await;
        for (id, body) in [
            json!([100]),
            json!("speed_rpm=100"),
            json!(100),
            json!({"speed_rpm": "100"}),
            json!({"speed_rpm": 100, "torque_a": 1}),
            json!({"speed_rpm": 1e9}),
            json!({"speed_rpm": 10, "lease_ms": 1}),
        ]
        .into_iter()
        .enumerate()
        {
            ws.send(Message::Text(
                json!({"type": "command", "id": id, "op": "setpoint", "drive": "lift", "body": body})
                    .to_string()
                    .into(),
            ))
            .await
            .unwrap();
            let answer = next_answer(&mut ws).await;
            assert_eq!((answer["id"].as_u64(), answer["ok"].as_bool()), (Some(id as u64), Some(false)), "{body}: {answer}");
            let status = answer["problem"]["status"].as_u64().unwrap();
            assert!(matches!(status, 400 | 422), "{body}: {answer}");
            if status == 422 {
                assert!(answer["problem"]["valid_range"]["max"].is_number(), "{answer}");
            }
        }
        assert_eq!(writes_on_wire(&d.plant), writes, "a refused command wrote");
        drop(ws);

        watcher.still_receiving(5).await;
        watcher.stop().await;
        baseline
            .assert_back(Duration::from_secs(5), "generated stream messages")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
