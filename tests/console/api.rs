//! The public API the console stands on, and that any client may use:
//! `GET /api/v1/whoami`, `GET /api/v1/drives/{drive}/settings` (read back
//! from the drive) and the stream's `write` messages (every write, from
//! every face, with who, what and the drive's answer).

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use super::harness::{ADMIN, OPERATOR, VIEWER, Watcher, config};
use crate::support::modbus_tcp::{Raw, write};
use crate::support::{FOUR_DRIVES, TestDaemon};

const LONG: Duration = Duration::from_secs(60);

async fn call(
    d: &TestDaemon,
    token: Option<&str>,
    method: &str,
    path: &str,
    body: Option<Value>,
) -> (u16, Value) {
    let mut r = reqwest::Client::new().request(method.parse().unwrap(), d.url(path));
    if let Some(t) = token {
        r = r.bearer_auth(t);
    }
    if let Some(b) = body {
        r = r.json(&b);
    }
    let res = r.send().await.unwrap();
    (
        res.status().as_u16(),
        res.json().await.unwrap_or(Value::Null),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn whoami_names_the_token_and_its_role() {
    let open = TestDaemon::start(FOUR_DRIVES).await;
    let (status, me) = call(&open, None, "GET", "/api/v1/whoami", None).await;
    assert_eq!(status, 200);
    assert_eq!(
        (
            me["role"].clone(),
            me["tokens_required"].clone(),
            me["jog_lease_ms"].clone()
        ),
        (json!("admin"), json!(false), json!(300))
    );
    assert!(
        me["who"].as_str().unwrap().starts_with("127.0.0.1:"),
        "{me}"
    );
    open.stop().await;

    let d = TestDaemon::start(&config(true, "")).await;
    let (status, me) = call(&d, None, "GET", "/api/v1/whoami", None).await;
    assert_eq!(
        (status, me),
        (
            200,
            json!({"who": null, "role": null, "tokens_required": true,
                   "jog_lease_ms": super::harness::JOG_LEASE_MS})
        )
    );
    for (token, name, role) in [
        (VIEWER, "dashboard", "viewer"),
        (OPERATOR, "panel", "operator"),
        (ADMIN, "commissioning", "admin"),
    ] {
        let (status, me) = call(&d, Some(token), "GET", "/api/v1/whoami", None).await;
        assert_eq!(
            (status, me),
            (
                200,
                json!({"who": name, "role": role, "tokens_required": true,
                       "jog_lease_ms": super::harness::JOG_LEASE_MS})
            )
        );
    }
    let (status, problem) = call(&d, Some("not-a-token"), "GET", "/api/v1/whoami", None).await;
    assert_eq!(
        (status, problem["type"].clone()),
        (401, json!("urn:drivegate:problem:unauthorized"))
    );
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn settings_are_read_back_from_the_drive() {
    let d = TestDaemon::start(&config(true, "")).await;
    let (status, s) = call(
        &d,
        Some(VIEWER),
        "GET",
        "/api/v1/drives/lift/settings",
        None,
    )
    .await;
    assert_eq!(status, 200, "{s}");
    assert_eq!(
        (
            s["drive"].clone(),
            s["unit"].clone(),
            s["gear_ratio"].clone()
        ),
        (json!("lift"), json!(2), json!(10.0))
    );
    assert_eq!(
        s["speed_ramp"]["alpha"], 500_000,
        "the power-on default (manual 1.9)"
    );
    assert_eq!(s["rs485_control"], true);

    // What an admin writes is what the drive then holds.
    let writes = [
        ("/protection", json!({"limit_a": 10.0, "stall_ms": 2000})),
        ("/ramps/speed", json!({"alpha": 5000})),
        ("/ramps/position", json!({"alpha": 200})),
        ("/inertia", json!({"ratio": 7})),
    ];
    for (path, body) in writes {
        let (status, r) = call(
            &d,
            Some(ADMIN),
            "PUT",
            &format!("/api/v1/drives/lift{path}"),
            Some(body),
        )
        .await;
        assert_eq!(status, 200, "{path}: {r}");
    }
    call(
        &d,
        Some(OPERATOR),
        "POST",
        "/api/v1/drives/lift/commands/activate",
        None,
    )
    .await;
    let (status, r) = call(
        &d,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/lift/setpoint",
        Some(json!({"position_deg": -45.5})),
    )
    .await;
    assert_eq!(status, 200, "{r}");
    let (_, s) = call(
        &d,
        Some(VIEWER),
        "GET",
        "/api/v1/drives/lift/settings",
        None,
    )
    .await;
    assert_eq!(
        s["protection"],
        json!({"limit_a": 10.0, "limit_counts": 1280, "stall_ms": 2000})
    );
    assert_eq!(
        (
            s["speed_ramp"]["alpha"].clone(),
            s["position_ramp"]["alpha"].clone()
        ),
        (json!(5000), json!(200))
    );
    assert_eq!(s["inertia_ratio"], 7);
    assert_eq!(s["setpoints"]["position_deg"], -45.5);

    let (status, p) = call(
        &d,
        Some(VIEWER),
        "GET",
        "/api/v1/drives/nope/settings",
        None,
    )
    .await;
    assert_eq!(
        (status, p["type"].clone()),
        (404, json!("urn:drivegate:problem:unknown-drive"))
    );
    let (status, _) = call(&d, None, "GET", "/api/v1/drives/lift/settings", None).await;
    assert_eq!(status, 401);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_write_of_every_face_is_on_the_stream() {
    let d = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(d.http, Some(VIEWER)).await;
    let is_write = |drive: &'static str, who: &'static str, what: &'static str| {
        move |v: &Value| {
            v["type"] == "write"
                && v["drive"] == drive
                && v["who"] == who
                && v["what"].as_str().unwrap_or("").contains(what)
        }
    };

    // REST.
    let start = Instant::now();
    call(
        &d,
        Some(OPERATOR),
        "POST",
        "/api/v1/drives/conveyor/commands/activate",
        None,
    )
    .await;
    let (_, w) = watcher
        .wait(
            start,
            LONG,
            "the REST write",
            is_write("conveyor", "panel", "activate"),
        )
        .await;
    assert_eq!(w["ok"], true);
    assert_eq!(w["answer"], "confirmed by the drive");
    assert_eq!(
        (w["bus"].clone(), w["unit"].clone()),
        (json!("sim"), json!(1))
    );
    assert!(w["at"].as_str().unwrap().ends_with('Z'));

    // Modbus TCP: a write the drive refuses (a speed beyond 2047 rpm).
    let mut raw = Raw::connect(d.modbus_tcp.unwrap()).await;
    let start = Instant::now();
    raw.ask(2, &write(0x0006, 3000)).await;
    let (_, w) = watcher
        .wait(start, LONG, "the Modbus TCP write", |v| {
            v["type"] == "write"
                && v["drive"] == "lift"
                && v["who"].as_str().unwrap_or("").starts_with("127.0.0.1:")
        })
        .await;
    assert_eq!(w["ok"], false, "{w}");
    assert!(w["answer"].as_str().unwrap().contains("refused"), "{w}");

    // The daemon's own: a lease's stop.
    call(
        &d,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/conveyor/mode",
        Some(json!({"mode": "speed"})),
    )
    .await;
    let start = Instant::now();
    let (status, r) = call(
        &d,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/conveyor/setpoint",
        Some(json!({"speed_rpm": 30, "lease_ms": 200})),
    )
    .await;
    assert_eq!(status, 200, "{r}");
    let (_, w) = watcher
        .wait(start, LONG, "the lease's stop", |v| {
            v["type"] == "write" && v["who"] == "lease-expiry (panel)"
        })
        .await;
    assert_eq!(w["ok"], true, "{w}");
    d.stop().await;
}

/// `POST .../replacement`: the replace-a-drive page's start and end in
/// the audit log, with who and the detail; an admin's work, refused to an
/// operator; a detail that is not one short line is refused in words.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replacement_is_noted_in_the_audit_log_by_an_admin_only() {
    crate::support::logs::capture_logs();
    let d = TestDaemon::start(&config(true, "")).await;
    let path = "/api/v1/drives/lift/replacement";
    let detail = "settings from lift-settings-7f3a.json; calibration asked";
    let (status, noted) = call(
        &d,
        Some(ADMIN),
        "POST",
        path,
        Some(json!({"event": "started", "detail": detail})),
    )
    .await;
    assert_eq!(status, 200, "{noted}");
    assert_eq!(noted["drive"], "lift");
    assert_eq!(noted["event"], "started");
    assert_eq!(noted["who"], "commissioning");
    let (status, _) = call(
        &d,
        Some(ADMIN),
        "POST",
        path,
        Some(json!({"event": "finished", "detail": "lift-7f3a replaced in 95 s"})),
    )
    .await;
    assert_eq!(status, 200);
    let logs = crate::support::logs::log_text();
    let started = logs
        .lines()
        .find(|l| l.contains("drive replacement started") && l.contains("lift-settings-7f3a"))
        .unwrap_or_else(|| panic!("no start line in the audit log:\n{logs}"));
    for field in [
        "drivegate::audit",
        "face=\"http\"",
        "who=\"commissioning\"",
        "drive=\"lift\"",
    ] {
        assert!(started.contains(field), "{started} lacks {field}");
    }
    assert!(
        logs.lines()
            .any(|l| l.contains("drive replacement finished") && l.contains("lift-7f3a replaced")),
        "no end line:\n{logs}"
    );

    let (status, p) = call(
        &d,
        Some(OPERATOR),
        "POST",
        path,
        Some(json!({"event": "started"})),
    )
    .await;
    assert_eq!(
        (status, p["type"].as_str()),
        (403, Some("urn:drivegate:problem:forbidden")),
        "{p}"
    );
    let (status, p) = call(
        &d,
        Some(ADMIN),
        "POST",
        path,
        Some(json!({"event": "started", "detail": "two\nlines"})),
    )
    .await;
    assert_eq!(status, 400, "{p}");
    assert!(p["detail"].as_str().unwrap().contains("one line"), "{p}");
    let (status, p) = call(
        &d,
        Some(ADMIN),
        "POST",
        path,
        Some(json!({"event": "begun"})),
    )
    .await;
    assert_eq!(status, 400, "{p}");
    let (status, _) = call(
        &d,
        Some(ADMIN),
        "POST",
        "/api/v1/drives/nope/replacement",
        Some(json!({"event": "started"})),
    )
    .await;
    assert_eq!(status, 404);
    d.stop().await;
}
