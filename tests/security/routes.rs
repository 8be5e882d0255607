//! Access control of the HTTP API and the stream, route by route, taken
//! from the OpenAPI document the daemon serves, so a route added later is
//! checked without anyone remembering to: every write route refuses a
//! missing token (401), a wrong one (401) and a token of too low a role
//! (403) without touching a drive, and lets the role its document names
//! through; the stream's commands follow the same roles; no token value
//! appears in the logs, the metrics or any answer, on success or failure.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::support::input::{
    ADMIN, OPERATOR, RawAnswer, VIEWER, check_answer, config, raw_http, request, writes_on_wire,
};
use crate::support::logs::{capture_logs, log_text};
use crate::support::{TestDaemon, replaced};
use drivegate::control::policy::{self, Role};
use drivegate::drive::ConfigCommand;
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

const LIMIT: Duration = Duration::from_secs(60);

/// Tokens that are not ours, some close to ours.
const WRONG: [&str; 4] = [
    "wrong-token-4e1f0a9b",
    "admin-e3a8d6f10b47c92",
    "admin-e3a8d6f10b47c925x",
    "ADMIN-E3A8D6F10B47C925",
];

fn secret(role: Role) -> &'static str {
    match role {
        Role::Viewer => VIEWER,
        Role::Operator => OPERATOR,
        Role::Admin => ADMIN,
    }
}

const ROLES: [Role; 3] = [Role::Viewer, Role::Operator, Role::Admin];

fn role_named(name: &str) -> Role {
    ROLES
        .into_iter()
        .find(|r| r.name() == name)
        .unwrap_or_else(|| panic!("unknown role {name}"))
}

/// One request to check: a write operation of the document, made concrete.
#[derive(Debug, Clone)]
struct Write {
    method: String,
    target: String,
    body: Option<Value>,
    /// The role it needs.
    role: Role,
    /// What the stream calls it, with its target and body.
    stream: Option<Value>,
}

/// A body that passes the checks behind the role check, per operation, and
/// the stream command doing the same. The address setting leaves out its
/// confirmation: a right role then meets 409 (never a broadcast that would
/// readdress every drive). Every write operation of the document must be
/// here: a new one fails the test until it is added.
fn bodies() -> BTreeMap<&'static str, (Option<Value>, Option<&'static str>)> {
    BTreeMap::from([
        ("post_command", (None, None)),
        ("put_mode", (Some(json!({"mode": "speed"})), Some("mode"))),
        (
            "put_setpoint",
            (Some(json!({"speed_rpm": 5})), Some("setpoint")),
        ),
        (
            "post_renew",
            (Some(json!({"lease_ms": 500})), Some("lease-renew")),
        ),
        ("delete_lease", (None, Some("lease-release"))),
        (
            "put_protection",
            (
                Some(json!({"limit_a": 12.0, "stall_ms": 3000})),
                Some("protection"),
            ),
        ),
        (
            "put_speed_ramp",
            (Some(json!({"alpha": 500000})), Some("speed-ramp")),
        ),
        (
            "put_position_ramp",
            (Some(json!({"alpha": 500000})), Some("position-ramp")),
        ),
        ("put_inertia", (Some(json!({"ratio": 1})), Some("inertia"))),
        (
            "put_rs485_control",
            (Some(json!({"enabled": true})), Some("rs485-control")),
        ),
        (
            "put_settings",
            (Some(json!({"inertia_ratio": 1})), Some("settings")),
        ),
        (
            "post_scan",
            (Some(json!({"from": 1, "to": 2})), Some("scan")),
        ),
        (
            "post_address",
            (Some(json!({"address": 9})), Some("set-address")),
        ),
        // The scope: a capture changes what the bus polls, so arming,
        // triggering and cancelling need the operator.
        (
            "post_scope",
            (
                Some(
                    json!({"drives": ["lift"], "trigger": {"type": "manual"}, "length": {"samples": 10}}),
                ),
                Some("scope-arm"),
            ),
        ),
        ("delete_scope", (None, Some("scope-cancel"))),
        ("post_trigger", (None, Some("scope-trigger"))),
        (
            "post_replacement",
            (Some(json!({"event": "started"})), Some("replacement")),
        ),
        // The configuration file is commissioning work; not on the stream.
        ("post_reload", (None, None)),
        (
            "post_drives",
            (
                Some(
                    json!({"bus": "sim", "drives": [{"unit": 5, "name": "press"}], "dry_run": true}),
                ),
                None,
            ),
        ),
        // The gateway's own files are the admin's, none on the stream: the
        // file changed only on a version read (no If-Match here: 428), a
        // check, tokens made and revoked (the test daemon runs without a
        // file: 409), certificates trusted, removed or renewed (no such
        // thumbprint: 404; no OPC UA server: 409).
        ("put_file", (Some(json!({"text": ""})), None)),
        ("post_check", (Some(json!({"text": "[http]\n"})), None)),
        (
            "post_token",
            (Some(json!({"name": "panel", "role": "viewer"})), None),
        ),
        ("delete_token", (None, None)),
        ("post_trust", (None, None)),
        ("delete_trusted", (None, None)),
        ("post_certificate_renew", (None, None)),
        // An acknowledgement is the operator's (alarm 1 may not exist yet:
        // a right role then meets 404); on the stream the id is the body's.
        ("post_ack", (None, Some("alarm-ack"))),
    ])
}

/// Every write operation of the served document, with the role its bearer
/// requirement names; the command route once per command, with the role
/// that command needs.
fn writes(doc: &Value) -> Vec<Write> {
    let bodies = bodies();
    let mut out = Vec::new();
    let mut seen = Vec::new();
    for (path, ops) in doc["paths"].as_object().unwrap() {
        for (method, op) in ops.as_object().unwrap() {
            if method == "get" {
                continue;
            }
            let id = op["operationId"].as_str().unwrap();
            seen.push(id.to_string());
            let scopes = op["security"][0]["bearer"].as_array();
            let named = scopes
                .and_then(|s| s.first())
                .and_then(Value::as_str)
                .unwrap_or_else(|| panic!("{method} {path} names no role in its security"));
            let documented = role_named(named);
            assert_ne!(
                documented,
                Role::Viewer,
                "{method} {path} is a write open to viewers"
            );
            let (body, op_name) = bodies.get(id).cloned().unwrap_or_else(|| {
                panic!("{method} {path} ({id}) is new: give it a body in bodies()")
            });
            let target = path
                .replace("{drive}", "lift")
                .replace("{bus}", "sim")
                .replace("{id}", "1")
                .replace("{thumbprint}", "00ff")
                .replace("{name}", "nobody");
            let in_stream = |name: &str, body: &Option<Value>| {
                let mut m = json!({"type": "command", "op": name});
                if path.contains("{bus}") {
                    m["bus"] = json!("sim");
                } else {
                    m["drive"] = json!("lift");
                }
                if let Some(b) = body {
                    m["body"] = b.clone();
                }
                if path.contains("{id}") {
                    m["body"] = json!({"alarm": 1});
                }
                m
            };
            if path.contains("{command}") {
                for command in ConfigCommand::ALL {
                    let role =
                        policy::of_request(&drivegate::drive::DriveRequest::Config(command)).needs;
                    assert!(
                        role >= documented,
                        "{}: below the route's role",
                        command.name()
                    );
                    out.push(Write {
                        method: method.to_uppercase(),
                        target: target.replace("{command}", command.name()),
                        body: None,
                        role,
                        stream: Some(in_stream(command.name(), &None)),
                    });
                }
            } else {
                out.push(Write {
                    method: method.to_uppercase(),
                    target,
                    stream: op_name.map(|n| in_stream(n, &body)),
                    body,
                    role: documented,
                });
            }
        }
    }
    let mut known: Vec<String> = bodies.keys().map(|k| k.to_string()).collect();
    known.sort();
    seen.sort();
    assert_eq!(seen, known, "the write operations of the document changed");
    out
}

async fn send(d: &TestDaemon, w: &Write, authorization: Option<String>) -> RawAnswer {
    let body = w.body.as_ref().map(|b| b.to_string()).unwrap_or_default();
    let mut extra = Vec::new();
    if !body.is_empty() {
        extra.push("Content-Type: application/json".to_string());
    }
    if let Some(a) = authorization {
        extra.push(format!("Authorization: {a}"));
    }
    let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
    let answer = raw_http(
        d.http,
        &request(&w.method, &w.target, None, &extra, body.as_bytes()),
    )
    .await
    .unwrap();
    // A drive may refuse what a right role asked for (502): the state the
    // earlier requests left it in. Anything else is a client error or a
    // success, well formed.
    if answer.status >= 500 {
        let kind = problem_type(&answer);
        assert!(
            [
                "urn:drivegate:problem:drive-refused",
                "urn:drivegate:problem:drive-timeout",
                "urn:drivegate:problem:drive-offline",
            ]
            .contains(&kind.as_str()),
            "{} {}: {} {}",
            w.method,
            w.target,
            answer.status,
            answer.text()
        );
    } else {
        check_answer(&answer).unwrap_or_else(|e| panic!("{} {}: {e}", w.method, w.target));
    }
    answer
}

fn problem_type(a: &RawAnswer) -> String {
    a.json()
        .map(|v| v["type"].as_str().unwrap_or("").to_string())
        .unwrap_or_default()
}

/// Every route is tried with wrong tokens: more than the pause after
/// token guesses would let through (tests/security/tokens.rs tests it).
/// The lift declares a setting, so its declaration can be read too.
async fn daemon() -> TestDaemon {
    let text = replaced(
        &config("token_guesses = 1000000", "", true, ""),
        "name = \"lift\"\ngear_ratio = 10.0\n",
        "name = \"lift\"\ngear_ratio = 10.0\nsettings = { inertia_ratio = 1 }\n",
    );
    TestDaemon::start(&text).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_write_route_checks_the_token_and_its_role() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let doc: Value = reqwest::get(d.url("/openapi.json"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let writes = writes(&doc);
        let mut checked = 0;
        for w in &writes {
            let before = writes_on_wire(&d.plant);
            let what = format!("{} {}", w.method, w.target);
            // No token, a wrong one, a malformed one: 401, nothing written.
            let mut refusals = vec![None, Some(format!("Basic {ADMIN}"))];
            refusals.extend(WRONG.iter().map(|t| Some(format!("Bearer {t}"))));
            for auth in refusals {
                let a = send(&d, w, auth.clone()).await;
                assert_eq!(a.status, 401, "{what} with {auth:?}: {}", a.text());
                assert_eq!(problem_type(&a), "urn:drivegate:problem:unauthorized");
            }
            // Every role below the one needed: 403 naming it.
            for role in ROLES.into_iter().filter(|r| *r < w.role) {
                let a = send(&d, w, Some(format!("Bearer {}", secret(role)))).await;
                assert_eq!(a.status, 403, "{what} as {}: {}", role.name(), a.text());
                let detail = a.json().unwrap()["detail"].as_str().unwrap().to_string();
                assert!(
                    detail.contains(&format!("{} role", w.role.name())),
                    "{what}: {detail}"
                );
            }
            assert_eq!(
                writes_on_wire(&d.plant),
                before,
                "{what}: a refused request wrote"
            );
            // The role needed, and every one above it, get past the check.
            for role in ROLES.into_iter().filter(|r| *r >= w.role) {
                let a = send(&d, w, Some(format!("Bearer {}", secret(role)))).await;
                assert!(
                    a.status != 401 && a.status != 403,
                    "{what} as {}: {} {}",
                    role.name(),
                    a.status,
                    a.text()
                );
            }
            checked += 1;
        }
        println!("{checked} write requests checked with no token, 6 wrong ones and every role");
        assert!(checked >= 22, "only {checked} write requests");

        // Reads need a token too (viewer is enough); health, readiness and
        // metrics need none.
        for (path, ops) in doc["paths"].as_object().unwrap() {
            // The WebSocket routes answer a plain GET 400 (they are checked
            // below and in tests/monitor_sim.rs).
            if ops.get("get").is_none() || path.contains("stream") || path.ends_with("/live") {
                continue;
            }
            let target = path.replace("{drive}", "lift").replace("{bus}", "sim");
            // No security, or an empty requirement among them (`{}`: the
            // token is optional, as for whoami), is open to anonymous reads.
            let open = ops["get"].get("security").is_none_or(|s| {
                s.as_array().is_some_and(|a| {
                    a.iter()
                        .any(|r| r.as_object().is_some_and(|o| o.is_empty()))
                })
            });
            let anonymous = raw_http(d.http, &request("GET", &target, None, &[], b""))
                .await
                .unwrap();
            let viewer = raw_http(d.http, &request("GET", &target, Some(VIEWER), &[], b""))
                .await
                .unwrap();
            // The gateway's own files are read by admins only.
            let needs = ops["get"]["security"][0]["bearer"][0]
                .as_str()
                .map_or(Role::Viewer, role_named);
            if needs == Role::Viewer {
                assert_eq!(viewer.status, 200, "{target} as a viewer");
            } else {
                assert_eq!(viewer.status, 403, "{target} as a viewer");
                let right = raw_http(
                    d.http,
                    &request("GET", &target, Some(secret(needs)), &[], b""),
                )
                .await
                .unwrap();
                assert!(
                    ![401, 403].contains(&right.status),
                    "{target} as {needs:?}: {}",
                    right.status
                );
            }
            assert_eq!(
                anonymous.status,
                if open { 200 } else { 401 },
                "{target} without a token"
            );
        }
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

async fn stream(d: &TestDaemon, token: Option<&str>, query: &str) -> Result<common_ws::Ws, u16> {
    let mut req = format!("ws://{}/api/v1/stream{query}", d.http)
        .into_client_request()
        .unwrap();
    if let Some(t) = token {
        req.headers_mut()
            .insert("authorization", format!("Bearer {t}").parse().unwrap());
    }
    match tokio_tungstenite::connect_async(req).await {
        Ok((ws, _)) => Ok(ws),
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => Err(r.status().as_u16()),
        Err(e) => panic!("stream connect: {e}"),
    }
}

mod common_ws {
    pub type Ws = tokio_tungstenite::WebSocketStream<
        tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>,
    >;
}

/// Sends a command and returns its reply.
async fn command(ws: &mut common_ws::Ws, id: u64, mut message: Value) -> Value {
    message["id"] = json!(id);
    ws.send(Message::Text(message.to_string().into()))
        .await
        .unwrap();
    let until = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let m = tokio::time::timeout_at(until, ws.next())
            .await
            .expect("a reply in time")
            .expect("the stream is open")
            .expect("a frame");
        if let Message::Text(t) = m {
            let v: Value = serde_json::from_str(t.as_str()).unwrap();
            if v["type"] == "reply" && v["id"] == id {
                return v;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_needs_a_token_and_its_commands_the_same_roles() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let doc: Value = reqwest::get(d.url("/openapi.json"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        // No token, a wrong one, in the header or the query: 401 before the
        // upgrade.
        assert_eq!(stream(&d, None, "").await.err(), Some(401));
        for wrong in WRONG {
            assert_eq!(stream(&d, Some(wrong), "").await.err(), Some(401));
            assert_eq!(
                stream(&d, None, &format!("?access_token={wrong}"))
                    .await
                    .err(),
                Some(401)
            );
        }
        let writes = writes(&doc);
        let before = writes_on_wire(&d.plant);
        let mut streams = Vec::new();
        for role in ROLES {
            streams.push((role, stream(&d, Some(secret(role)), "").await.unwrap()));
        }
        let mut id = 0;
        let mut checked = 0;
        // Refusals first (nothing may be written), then the right roles.
        for pass in [false, true] {
            for w in &writes {
                // The gateway's own files (its configuration, tokens and
                // certificates) are the only writes the stream does not
                // carry: they edit files, not drives.
                let Some(message) = w.stream.clone() else {
                    assert!(
                        ["/api/v1/config/", "/api/v1/tokens", "/api/v1/certificates"]
                            .iter()
                            .any(|p| w.target.starts_with(p)),
                        "{} {} has no stream command",
                        w.method,
                        w.target
                    );
                    continue;
                };
                for (role, ws) in &mut streams {
                    if (*role >= w.role) != pass {
                        continue;
                    }
                    id += 1;
                    let reply = command(ws, id, message.clone()).await;
                    let status = reply["problem"]["status"].as_u64();
                    if pass {
                        assert!(
                            reply["ok"] == true || !matches!(status, Some(401 | 403)),
                            "{message} as {}: {reply}",
                            role.name()
                        );
                    } else {
                        assert_eq!(status, Some(403), "{message} as {}: {reply}", role.name());
                        checked += 1;
                    }
                }
            }
            if !pass {
                assert_eq!(
                    writes_on_wire(&d.plant),
                    before,
                    "a refused stream command wrote"
                );
            }
        }
        println!("{checked} stream commands refused to roles below the one needed");
        drop(streams);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_token_appears_in_logs_metrics_or_answers() {
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let mut answers: Vec<String> = Vec::new();
        let keep = |a: &RawAnswer, answers: &mut Vec<String>| {
            answers.push(format!("{:?} {}", a.headers, a.text()));
        };
        // Successes: reads and writes with each token, a stream opened with
        // the token in its query string (URLs end up in logs).
        for token in [VIEWER, OPERATOR, ADMIN] {
            let a = raw_http(d.http, &request("GET", "/api/v1/drives", Some(token), &[], b"")).await.unwrap();
            assert_eq!(a.status, 200);
            keep(&a, &mut answers);
        }
        for (token, path, body) in [
            (OPERATOR, "/api/v1/drives/lift/commands/fault-reset", ""),
            (ADMIN, "/api/v1/drives/lift/inertia", r#"{"ratio": 2}"#),
        ] {
            let method = if body.is_empty() { "POST" } else { "PUT" };
            let a = raw_http(
                d.http,
                &request(method, path, Some(token), &["Content-Type: application/json"], body.as_bytes()),
            )
            .await
            .unwrap();
            assert_eq!(a.status, 200, "{}", a.text());
            keep(&a, &mut answers);
        }
        let mut ws = stream(&d, None, &format!("?drives=all&access_token={OPERATOR}")).await.unwrap();
        let reply = command(&mut ws, 1, json!({"type": "command", "op": "status", "drive": "lift"})).await;
        answers.push(reply.to_string());
        drop(ws);

        // Failures: wrong tokens near ours, ours in the wrong place or of
        // the wrong role, malformed requests carrying ours.
        let mut failures: Vec<Vec<u8>> = Vec::new();
        for wrong in WRONG {
            failures.push(request("POST", "/api/v1/drives/lift/commands/brake", Some(wrong), &[], b""));
        }
        failures.push(request("POST", "/api/v1/drives/lift/commands/brake", Some(VIEWER), &[], b""));
        failures.push(request("PUT", "/api/v1/drives/lift/protection", Some(OPERATOR), &["Content-Type: application/json"], br#"{"limit_a": 1, "stall_ms": 5}"#));
        failures.push(request("POST", &format!("/api/v1/drives/lift/commands/brake?access_token={OPERATOR}"), None, &[], b""));
        failures.push(request("GET", &format!("/api/v1/stream?access_token={ADMIN}&drives=nosuch"), None, &[], b""));
        failures.push(request("GET", &format!("/api/v1/stream?access_token={VIEWER}&access_token={ADMIN}"), None, &[], b""));
        failures.push(request("GET", &format!("/api/v1/drives/lift/status?fresh={ADMIN}"), Some(ADMIN), &[], b""));
        failures.push(request("PUT", "/api/v1/drives/lift/setpoint", Some(ADMIN), &["Content-Type: application/json"], format!(r#"{{"speed_rpm": "{ADMIN}"}}"#).as_bytes()));
        failures.push(format!("POST /api/v1/drives/lift/commands/brake HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nAuthorization: Basic {ADMIN}\r\n\r\n").into_bytes());
        for bytes in &failures {
            let a = raw_http(d.http, bytes).await.unwrap();
            assert!(a.status >= 400, "{}: {}", String::from_utf8_lossy(bytes), a.status);
            keep(&a, &mut answers);
        }
        let mut ws = stream(&d, Some(VIEWER), "").await.unwrap();
        let reply = command(&mut ws, 2, json!({"type": "command", "op": "brake", "drive": "lift"})).await;
        assert_eq!(reply["problem"]["status"], 403);
        answers.push(reply.to_string());
        drop(ws);

        let metrics = reqwest::get(d.url("/metrics")).await.unwrap().text().await.unwrap();
        // The writes are in the audit log under the tokens' names.
        let logs = log_text();
        assert!(
            logs.lines().any(|l| l.contains("drivegate::audit") && l.contains("commissioning") && l.contains("load inertia ratio 2")),
            "the audit log does not name the token"
        );
        for secret in [VIEWER, OPERATOR, ADMIN].into_iter().chain(WRONG) {
            let line = logs.lines().find(|l| l.contains(secret));
            assert!(line.is_none(), "a token value is in the log: {line:?}");
            assert!(!metrics.contains(secret), "a token value is in the metrics: {secret}");
            // An answer may echo what the client itself sent in a field it
            // got wrong (the speed given as a token above); no other answer
            // may carry one.
            for a in answers.iter().filter(|a| !a.contains("speed_rpm")) {
                assert!(!a.contains(secret), "a token value is in an answer: {a}");
            }
        }
        println!(
            "no token value in {} bytes of log (every level), {} bytes of metrics, {} answers",
            logs.len(),
            metrics.len(),
            answers.len()
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
