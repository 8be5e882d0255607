//! Access control over real HTTP and WebSocket: tokens from a hash, a file
//! and the environment; what each role may do; the audit log naming the
//! token; secrets kept out of logs and metrics; loopback only without
//! tokens; limits on bodies, messages and connections.

use std::io::Write as _;
use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::api::{Api, config, connect, next_json, send_json};
use crate::support::config::ConfigBuilder;
use crate::support::config::sha256_hex;
use crate::support::logs::{capture_logs, log_text};
use futures_util::StreamExt;
use serde_json::json;
use tokio::io::AsyncWriteExt;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

const LIMIT: Duration = Duration::from_secs(40);

const VIEWER_SECRET: &str = "viewer-secret-7f3a";
const OPERATOR_SECRET: &str = "operator-secret-19c2";

/// PATH stands in for a secret in the environment: setting a variable is
/// `unsafe` in Rust 2024, which this crate forbids, and PATH is always set.
fn admin_secret() -> String {
    std::env::var("PATH").expect("PATH is set")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn roles_decide_who_may_do_what() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let mut file = tempfile::NamedTempFile::new().unwrap();
        writeln!(file, "{OPERATOR_SECRET}").unwrap();
        let http = format!(
            "[[http.token]]\nname = \"dashboard\"\nrole = \"viewer\"\nsha256 = \"{}\"\n\
             [[http.token]]\nname = \"scada\"\nrole = \"operator\"\nfile = \"{}\"\n\
             [[http.token]]\nname = \"commissioning\"\nrole = \"admin\"\nenv = \"PATH\"\n",
            sha256_hex(VIEWER_SECRET),
            file.path().display()
        );
        let d = TestDaemon::start(&config(&http, "")).await;
        let anonymous = Api::new(d.http, None);
        let viewer = anonymous.with_token(Some(VIEWER_SECRET));
        let operator = anonymous.with_token(Some(OPERATOR_SECRET));
        let admin_token = admin_secret();
        let admin = anonymous.with_token(Some(&admin_token));

        // No token, or a wrong one: 401 with the scheme to use.
        let r = anonymous.get("/api/v1/drives").await;
        assert_eq!(
            r.headers.get("www-authenticate").unwrap(),
            "Bearer realm=\"drivegate\""
        );
        r.expect_problem(401, "unauthorized");
        anonymous
            .with_token(Some("guess"))
            .get("/api/v1/drives")
            .await
            .expect_problem(401, "unauthorized");
        // Health, readiness and metrics need none.
        for path in ["/healthz", "/readyz", "/metrics"] {
            assert_eq!(anonymous.get(path).await.status, 200, "{path}");
        }

        // Viewer: reads only.
        viewer.get("/api/v1/drives").await.expect(200);
        viewer
            .get("/api/v1/drives/conveyor/status")
            .await
            .expect(200);
        viewer.get("/api/v1/buses").await.expect(200);
        let p = viewer
            .post_empty("/api/v1/drives/conveyor/commands/activate")
            .await
            .expect_problem(403, "forbidden");
        assert!(
            p["detail"].as_str().unwrap().contains("operator role"),
            "{p:#}"
        );
        viewer
            .put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": 10}))
            .await
            .expect_problem(403, "forbidden");

        // Operator: runs the machine, does not commission it.
        operator.activate_in("conveyor", "speed").await;
        operator
            .put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": 30}))
            .await
            .expect(200);
        operator.command("conveyor", "brake").await;
        operator.command("conveyor", "fault-reset").await;
        for (path, body) in [
            (
                "/api/v1/drives/conveyor/protection",
                json!({"limit_a": 5.0, "stall_ms": 100}),
            ),
            (
                "/api/v1/drives/conveyor/ramps/speed",
                json!({"alpha": 1000}),
            ),
            ("/api/v1/drives/conveyor/inertia", json!({"ratio": 2})),
            (
                "/api/v1/drives/conveyor/rs485-control",
                json!({"enabled": true}),
            ),
        ] {
            operator
                .put(path, body)
                .await
                .expect_problem(403, "forbidden");
        }
        for command in ["factory-reset", "calibrate", "fine-tune"] {
            operator
                .post_empty(&format!("/api/v1/drives/lift/commands/{command}"))
                .await
                .expect_problem(403, "forbidden");
        }
        operator
            .post("/api/v1/buses/sim/scan", json!({"from": 1, "to": 2}))
            .await
            .expect_problem(403, "forbidden");
        assert_eq!(d.sim().drive(1).unwrap().settings.speed_alpha, 500_000);

        // Admin: everything.
        admin
            .put(
                "/api/v1/drives/lift/protection",
                json!({"limit_a": 5.0, "stall_ms": 100}),
            )
            .await
            .expect(200);
        admin.command("lift", "factory-reset").await;
        admin
            .post("/api/v1/buses/sim/scan", json!({"from": 1, "to": 2}))
            .await
            .expect(200);

        // The stream: a token in the header or the query; none is refused.
        let mut ws = connect(d.http, "?drives=conveyor", Some(VIEWER_SECRET)).await;
        assert_eq!(
            next_json(&mut ws, Duration::from_secs(5)).await["type"],
            "subscribed"
        );
        let mut ws2 = connect(
            d.http,
            &format!("?drives=all&access_token={VIEWER_SECRET}"),
            None,
        )
        .await;
        assert_eq!(
            next_json(&mut ws2, Duration::from_secs(5)).await["type"],
            "subscribed"
        );
        let refused = tokio_tungstenite::connect_async(
            format!("ws://{}/api/v1/stream", d.http)
                .into_client_request()
                .unwrap(),
        )
        .await;
        match refused {
            Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
                assert_eq!(response.status(), 401);
            }
            other => panic!("the stream took a client without a token: {other:?}"),
        }
        // A viewer's command over the stream is refused like over REST.
        send_json(
            &mut ws,
            json!({"type": "command", "id": 1, "op": "activate", "drive": "lift"}),
        )
        .await;
        let reply =
            crate::support::api::wait_for(&mut ws, Duration::from_secs(5), "the reply", |v| {
                v["type"] == "reply"
            })
            .await;
        assert_eq!(reply["ok"], false);
        assert_eq!(reply["problem"]["status"], 403);
        drop((ws, ws2));

        // Writes are audited under the token's name; no secret is logged or
        // exported.
        let logs = log_text();
        let audit: Vec<&str> = logs
            .lines()
            .filter(|l| l.contains("drivegate::audit"))
            .collect();
        assert!(
            audit
                .iter()
                .any(|l| l.contains("scada") && l.contains("speed setpoint 30 rpm")),
            "no audit line for the operator's setpoint in:\n{}",
            audit.join("\n")
        );
        assert!(
            audit
                .iter()
                .any(|l| l.contains("commissioning") && l.contains("over-current limit"))
        );
        let metrics = reqwest::get(anonymous.url("/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        for secret in [VIEWER_SECRET, OPERATOR_SECRET, admin_token.as_str()] {
            assert!(!logs.contains(secret), "a token was logged");
            assert!(!metrics.contains(secret), "a token is in the metrics");
        }
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_tokens_the_api_listens_on_loopback_only() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        // Asked for every interface, but no tokens: loopback, same port.
        let text = ConfigBuilder::four_drives().http_listen("0.0.0.0:0").toml();
        let d = TestDaemon::start(&text).await;
        assert!(d.http.ip().is_loopback(), "bound {}", d.http);
        // Every local client then has full rights, audited by its address.
        let api = Api::new(d.http, None);
        api.put("/api/v1/drives/lift/inertia", json!({"ratio": 2}))
            .await
            .expect(200);
        let logs = log_text();
        // Other tests of this binary log too: this daemon's line names its port.
        let listening = format!("listening={}", d.http);
        assert!(
            logs.lines()
                .any(|l| l.contains("loopback only") && l.contains(&listening)),
            "the log does not say so"
        );
        assert!(
            logs.lines().any(|l| l.contains("drivegate::audit")
                && l.contains("127.0.0.1:")
                && l.contains("load inertia ratio 2")),
            "no audit line naming the client address"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_on_connections_bodies_and_messages() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(
            "max_connections = 3\nmax_connections_per_address = 3\nmax_body_bytes = 1024",
            "",
        ))
        .await;
        let api = Api::new(d.http, None);

        // A body over the limit: 413, and the daemon carries on.
        let big = json!({"speed_rpm": 1, "note": "x".repeat(2000)});
        api.put("/api/v1/drives/conveyor/setpoint", big)
            .await
            .expect_problem(413, "payload-too-large");

        // A stream message over the limit closes that stream only.
        let mut ws = connect(d.http, "", None).await;
        send_json(
            &mut ws,
            json!({"type": "subscribe", "drives": ["x".repeat(2000)]}),
        )
        .await;
        let closed = tokio::time::timeout(Duration::from_secs(5), async {
            loop {
                match ws.next().await {
                    None | Some(Err(_)) => return,
                    Some(Ok(m)) if m.is_close() => return,
                    Some(Ok(_)) => {}
                }
            }
        })
        .await;
        assert!(
            closed.is_ok(),
            "the oversized message did not close the stream"
        );
        api.get("/api/v1/drives").await.expect(200);

        // Three idle connections hold every slot: the next one gets 503.
        let mut idle = Vec::new();
        for _ in 0..3 {
            let mut s = tokio::net::TcpStream::connect(d.http).await.unwrap();
            s.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
                .await
                .unwrap();
            idle.push(s);
        }
        // The server accepts them in the background: retry until refused.
        let refused = async {
            loop {
                let mut s = tokio::net::TcpStream::connect(d.http).await.unwrap();
                s.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
                    .await
                    .unwrap();
                let mut answer = Vec::new();
                let read = tokio::time::timeout(
                    Duration::from_secs(2),
                    tokio::io::AsyncReadExt::read_to_end(&mut s, &mut answer),
                )
                .await;
                let answer = String::from_utf8_lossy(&answer).into_owned();
                if read.is_ok() && answer.starts_with("HTTP/1.1 503") {
                    return answer;
                }
            }
        };
        let answer = tokio::time::timeout(Duration::from_secs(15), refused)
            .await
            .expect("a connection over the limit is refused");
        assert!(
            answer.contains("urn:drivegate:problem:too-many-connections"),
            "{answer}"
        );
        assert!(answer.contains("application/problem+json"), "{answer}");
        // Closing them frees the slots.
        drop(idle);
        let ok = async {
            loop {
                if let Ok(r) = reqwest::get(api.url("/healthz")).await
                    && r.status() == 200
                {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        };
        tokio::time::timeout(Duration::from_secs(5), ok)
            .await
            .expect("the API serves again once connections closed");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_are_closed_but_quiet_streams_are_kept() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("idle_timeout_s = 1", "")).await;

        // A client that connects and says nothing loses its connection.
        let mut silent = tokio::net::TcpStream::connect(d.http).await.unwrap();
        let mut buf = [0u8; 64];
        let read = tokio::time::timeout(
            Duration::from_secs(10),
            tokio::io::AsyncReadExt::read(&mut silent, &mut buf),
        )
        .await
        .expect("the idle connection was closed");
        assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");

        // A stream subscribed to nothing gets pings, and stays open.
        let mut ws = connect(d.http, "", None).await;
        let quiet = tokio::time::timeout(Duration::from_secs(3), async {
            loop {
                match ws.next().await {
                    Some(Ok(m)) if m.is_ping() => {}
                    other => return other,
                }
            }
        })
        .await;
        assert!(quiet.is_err(), "the quiet stream ended: {quiet:?}");
        send_json(&mut ws, json!({"type": "subscribe", "drives": "all"})).await;
        let ack = crate::support::api::wait_for(&mut ws, Duration::from_secs(5), "the ack", |m| {
            m["type"] == "subscribed"
        })
        .await;
        assert_eq!(ack["drives"].as_array().unwrap().len(), 4);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
