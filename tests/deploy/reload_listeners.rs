//! A reload that moves a listener or a bus's port reopens only that one
//! (`src/daemon/supervisor.rs`): a drive turning at 100 rpm over HTTP keeps turning,
//! its speed and lease unchanged, its stream going, while the Modbus TCP
//! listener moves (the old port refuses, pymodbus reads on the new one, the
//! PLC that was connected to the old one is closed and its
//! communication-loss lease ends with its stop, audited), while the HTTP
//! listener moves under the very request that reloads, while a listener
//! that cannot move stays where it was (the reload says so: its answer,
//! `/readyz`, the metric, the log), and while another bus's port changes.

use std::net::SocketAddr;
use std::time::Duration;

use futures_util::StreamExt;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use crate::support::api::{Api, Reply, Ws, connect, wait_for};
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::exported;
use crate::support::modbus_tcp::{Plc, Raw, pymodbus, read};
use crate::support::{TestDaemon, bounded, eventually};
use drivegate::plant::SimRef;

const LIMIT: Duration = Duration::from_secs(90);
/// Longest wait for an event the design says must come.
const EVENT: Duration = Duration::from_secs(20);
const ADMIN: &str = "listeners-admin-token";
/// Modbus registers of the drive (its own addresses).
const CONFIG: u16 = 0x0002;
const ACTIVATE: u16 = 0x0000;
const SPEED_MODE: u16 = 0x000A;
const SPEED_REF: u16 = 0x0006;

/// One bus, `line1`: the belt (unit 1) that HTTP turns, the press (unit 2)
/// that a PLC turns over Modbus TCP, from loopback, an operator network
/// whose communication loss stops the motor; `modbus_tcp` listens where
/// given. Names no other test of this binary uses: the log is shared.
fn plant(modbus_tcp: &str, http: &str) -> String {
    ConfigBuilder::new()
        .http_listen(http)
        .modbus_tcp_listen(modbus_tcp)
        .bus("line1", |b| b.drive(1, "lsn_belt").drive(2, "lsn_press"))
        .http_token("admin", "admin", ADMIN)
        .section(
            "safety",
            "lease_max_ms = 600000\non_shutdown = \"zero-speed\"",
        )
        .tables(
            "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"\ncomm_loss_ms = 60000\ncomm_loss_action = \"zero-speed\"",
        )
        .toml()
}

/// A loopback address nobody listens on, outside the range the system
/// hands out for `:0` and outgoing connections.
fn free_port() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], crate::support::ports::free_port()))
}

/// Moves a listener to a free loopback port: writes `file(port)` and
/// reloads through `api`; the port and the answer. A port another process
/// took in between (the system hands out the same free ports to everyone)
/// is a problem of the answer, and another port is tried.
async fn reload_to_free_port(
    d: &TestDaemon,
    api: &Api,
    file: impl Fn(SocketAddr) -> String,
) -> (SocketAddr, Value) {
    for _ in 0..5 {
        let new = free_port();
        d.rewrite(&file(new));
        let reply = reload(api).await.expect(200);
        let taken = reply["problems"].as_array().is_some_and(|p| {
            p.iter()
                .any(|p| p.as_str().is_some_and(|p| p.contains("in use")))
        });
        if !taken {
            return (new, reply);
        }
    }
    panic!("no free loopback port in five tries");
}

/// Turns the belt at 100 rpm with a lease of ten minutes, and waits for it.
async fn belt_turning(api: &Api, line1: &SimRef) -> Value {
    api.activate_in("lsn_belt", "speed").await;
    api.put(
        "/api/v1/drives/lsn_belt/setpoint",
        json!({"speed_rpm": 100, "lease_ms": 600000}),
    )
    .await
    .expect(200);
    eventually(EVENT, "the belt at 100 rpm", || {
        ((line1.drive(1)?.speed_rpm - 100.0).abs() <= 2.0).then_some(())
    })
    .await;
    api.get("/api/v1/drives/lsn_belt").await.expect(200)["lease"].clone()
}

/// The belt still turns at 100 rpm with the lease it was given (never
/// renewed nor replaced), and its stream goes on.
async fn belt_unchanged(api: &Api, line1: &SimRef, lease: &Value, ws: &mut Ws) {
    let drive = line1.drive(1).unwrap();
    assert_eq!(drive.setpoints.speed_rpm, 100);
    assert!(
        (drive.speed_rpm - 100.0).abs() <= 2.0,
        "{}",
        drive.speed_rpm
    );
    let now = api.get("/api/v1/drives/lsn_belt").await.expect(200)["lease"].clone();
    assert_eq!(
        (&now["owner"], &now["lease_ms"]),
        (&lease["owner"], &lease["lease_ms"]),
        "{now}"
    );
    assert!(now["expires_in_ms"].as_u64() < lease["expires_in_ms"].as_u64());
    let v = wait_for(ws, EVENT, "a status of the belt", |v| {
        v["type"] == "status" && v["drive"] == "lsn_belt"
    })
    .await;
    let rpm = v["status"]["speed_rpm"].as_i64().unwrap();
    assert!((98..=102).contains(&rpm), "{v}");
}

async fn reload(api: &Api) -> Reply {
    api.post_empty("/api/v1/config/reload").await
}

fn lines(reply: &Value, key: &str) -> Vec<String> {
    reply[key]
        .as_array()
        .unwrap_or_else(|| panic!("no {key} in {reply}"))
        .iter()
        .map(|c| c.as_str().unwrap().to_string())
        .collect()
}

/// True when nothing listens at `addr` any more.
async fn refused(addr: SocketAddr) -> bool {
    match tokio::time::timeout(EVENT, tokio::net::TcpStream::connect(addr)).await {
        Ok(Err(e)) => e.kind() == std::io::ErrorKind::ConnectionRefused,
        Ok(Ok(_)) => false,
        Err(_) => panic!("a connection to {addr} neither made nor refused in time"),
    }
}

/// The Modbus status block of unit 1, read by pymodbus at `addr`.
async fn status_by_pymodbus(addr: SocketAddr) -> Vec<u16> {
    let out = pymodbus(addr, &["read", "1", "0xC0", "7"]).await;
    serde_json::from_value(out["registers"].clone())
        .unwrap_or_else(|_| panic!("no registers in {out}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_moved_modbus_tcp_listener_closes_its_port_and_its_clients_while_a_drive_keeps_turning() {
    capture_logs();
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant("127.0.0.1:0", "127.0.0.1:0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        let line1 = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        let lease = belt_turning(&api, &line1).await;
        let mut ws = connect(d.http, "?drives=all", Some(ADMIN)).await;
        let old = d.modbus_tcp.unwrap();
        assert_eq!(status_by_pymodbus(old).await.len(), 7);
        // A PLC on the old port turns the press, under its network's
        // communication-loss function.
        let mut plc = Plc::connect(old).await;
        plc.write(2, CONFIG, ACTIVATE).await;
        plc.write(2, CONFIG, SPEED_MODE).await;
        plc.write(2, SPEED_REF, 300).await;
        eventually(EVENT, "the press turning", || {
            (line1.drive(2)?.speed_rpm > 100.0).then_some(())
        })
        .await;
        let press = api.get("/api/v1/drives/lsn_press").await.expect(200)["lease"].clone();
        let plc_owner = press["owner"].as_str().unwrap().to_string();

        let (new, reply) =
            reload_to_free_port(&d, &api, |new| plant(&new.to_string(), "127.0.0.1:0")).await;
        assert_eq!(
            lines(&reply, "changes"),
            vec![format!(
                "Modbus TCP listener moved to {new} (it was on {old})"
            )],
            "{reply}"
        );
        assert_eq!(reply["problems"], json!([]), "{reply}");
        assert_eq!(reply["stopped"], json!([]), "{reply}");
        // The old port refuses from the answer on; the new one answers a
        // third-party client.
        assert!(refused(old).await, "{old} still takes connections");
        let status = status_by_pymodbus(new).await;
        assert_eq!(status.len(), 7, "{status:?}");
        assert_eq!(
            d.faces_addresses().await.modbus_tcp,
            Some(new),
            "where the daemon says Modbus TCP is"
        );

        // The PLC's connection on the old port was closed: its lease ended
        // with its network's stop, at once and audited.
        let expired = wait_for(&mut ws, EVENT, "the PLC's lease ending", |v| {
            v["type"] == "lease-expired" && v["owner"] == plc_owner.as_str()
        })
        .await;
        assert_eq!(expired["reason"], "its Modbus TCP connection closed");
        assert_eq!(
            expired["sent"], "speed setpoint 0 rpm (SPEED_REF=0)",
            "{expired:#}"
        );
        eventually(EVENT, "the press stopped", || {
            (line1.drive(2)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        let who = format!("who={plc_owner}");
        eventually(EVENT, "the PLC's lease end in the audit log", || {
            log_text().lines().find(|l| {
                l.contains("drivegate::audit")
                    && l.contains("lease ended with its stop")
                    && l.contains(&who)
                    && l.contains("reason=its Modbus TCP connection closed")
            })?;
            Some(())
        })
        .await;
        plc.kill().await;

        // The belt, its lease, its stream and the API went on.
        belt_unchanged(&api, &line1, &lease, &mut ws).await;
        let ready = api.get("/readyz").await.expect(200);
        assert_eq!(ready["configuration"]["last_reload_ok"], true, "{ready}");
        d.stop().await;
    })
    .await;
}

/// Reads the stream until the server closes it; its close frame.
async fn closed(ws: &mut Ws) -> Option<(u16, String)> {
    loop {
        match tokio::time::timeout(EVENT, ws.next())
            .await
            .expect("the stream closed in time")
        {
            Some(Ok(Message::Close(frame))) => {
                return frame.map(|f| (u16::from(f.code), f.reason.to_string()));
            }
            Some(Ok(_)) => continue,
            Some(Err(_)) | None => return None,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_moved_http_listener_answers_the_reload_that_moves_it_then_serves_only_at_its_new_address()
 {
    capture_logs();
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant("127.0.0.1:0", "127.0.0.1:0")).await;
        let old = d.http;
        let api = Api::new(old, Some(ADMIN));
        let line1 = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        let lease = belt_turning(&api, &line1).await;
        let mut old_ws = connect(old, "?drives=all", Some(ADMIN)).await;
        wait_for(&mut old_ws, EVENT, "a status of the belt", |v| {
            v["type"] == "status" && v["drive"] == "lsn_belt"
        })
        .await;
        let modbus = d.modbus_tcp.unwrap();

        // Asked on the old address, answered there: the request in
        // progress finishes before its connection closes.
        let (new, reply) =
            reload_to_free_port(&d, &api, |new| plant("127.0.0.1:0", &new.to_string())).await;
        assert_eq!(
            lines(&reply, "changes"),
            vec![format!(
                "HTTP API listener moved to {new} (it was on {old})"
            )],
            "{reply}"
        );
        assert!(refused(old).await, "{old} still takes connections");
        // The stream on the old listener was closed, saying why.
        let (code, reason) = closed(&mut old_ws).await.expect("a close frame");
        assert_eq!(code, 1001, "{reason}");
        assert!(reason.contains("reopening this listener"), "{reason}");

        // Everything at the new address: the API, the stream, the belt
        // still turning under the lease it had.
        let api = Api::new(new, Some(ADMIN));
        let mut ws = connect(new, "?drives=all", Some(ADMIN)).await;
        belt_unchanged(&api, &line1, &lease, &mut ws).await;
        // Modbus TCP was not touched.
        let mut raw = Raw::connect(modbus).await;
        assert_eq!(raw.ask(1, &read(0xC0, 7)).await[0], 0x03);
        assert!(
            log_text()
                .lines()
                .any(|l| l.contains("HTTP API listener moved by a reload")
                    && l.contains(&new.to_string())),
            "no log line of the move"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_listener_that_cannot_move_stays_where_it_was_and_the_reload_says_so() {
    capture_logs();
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant("127.0.0.1:0", "127.0.0.1:0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        let old = d.modbus_tcp.unwrap();
        // Someone else holds the new port.
        let squatter = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let taken = squatter.local_addr().unwrap();
        d.rewrite(&plant(&taken.to_string(), "127.0.0.1:0"));
        let reply = reload(&api).await.expect(200);
        let problems = lines(&reply, "problems");
        assert_eq!(problems.len(), 1, "{reply}");
        assert!(
            problems[0].starts_with(&format!(
                "Modbus TCP listener not moved: cannot listen for Modbus TCP on {taken}: "
            )) && problems[0].contains(&format!("it stays on {old} with its previous settings")),
            "{reply}"
        );
        // Still served where it was, by a third-party client.
        assert_eq!(status_by_pymodbus(old).await.len(), 7);
        let ready = api.get("/readyz").await.expect(200);
        let config = &ready["configuration"];
        assert_eq!(config["last_reload_ok"], false, "{ready}");
        assert!(
            config["last_reload_error"]
                .as_str()
                .unwrap()
                .contains("Modbus TCP listener not moved"),
            "{ready}"
        );
        let text = d.metrics.render();
        assert_eq!(
            exported(&text, "drivegate_config_reload_total{result=\"partial\"}"),
            1.0
        );
        assert_eq!(exported(&text, "drivegate_config_last_reload_ok "), 0.0);
        assert!(
            log_text()
                .lines()
                .any(|l| l.contains("configuration reloaded in part")
                    && l.contains(&taken.to_string())),
            "no log line of the listener that did not move"
        );

        // The port is free again: the same file, reloaded, moves it.
        drop(squatter);
        let reply = reload(&api).await.expect(200);
        assert_eq!(
            lines(&reply, "changes"),
            vec![format!(
                "Modbus TCP listener moved to {taken} (it was on {old})"
            )],
            "{reply}"
        );
        assert!(refused(old).await);
        assert_eq!(status_by_pymodbus(taken).await.len(), 7);
        let ready = api.get("/readyz").await.expect(200);
        assert_eq!(ready["configuration"]["last_reload_ok"], true, "{ready}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_token_removed_reopens_the_api_open_on_loopback_at_once() {
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant("127.0.0.1:0", "127.0.0.1:0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        let me = Api::new(d.http, None)
            .get("/api/v1/whoami")
            .await
            .expect(200);
        assert_eq!(
            (&me["role"], &me["tokens_required"]),
            (&json!(null), &json!(true)),
            "{me}"
        );
        let without = plant("127.0.0.1:0", "127.0.0.1:0").replace(
            &format!(
                "[[http.token]]\nname = \"admin\"\nrole = \"admin\"\nsha256 = \"{}\"\n",
                crate::support::config::sha256_hex(ADMIN)
            ),
            "",
        );
        assert!(!without.contains("http.token"), "{without}");
        d.rewrite(&without);
        let reply = reload(&api).await.expect(200);
        assert_eq!(
            lines(&reply, "changes"),
            vec![
                "tokens changed: 1".to_string(),
                format!(
                    "HTTP API listener reopened on {} with the new [http]",
                    d.http
                )
            ],
            "{reply}"
        );
        // The same loopback socket, now open to local clients as admin.
        let me = Api::new(d.http, None)
            .get("/api/v1/whoami")
            .await
            .expect(200);
        assert_eq!(
            (&me["role"], &me["tokens_required"]),
            (&json!("admin"), &json!(false)),
            "{me}"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_first_token_says_that_loopback_needs_one_from_then_on_and_how_to_make_an_admin_one() {
    capture_logs();
    bounded(LIMIT, async {
        let token = |name: &str, role: &str, secret: &str| {
            format!(
                "[[http.token]]\nname = \"{name}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
                crate::support::config::sha256_hex(secret)
            )
        };
        let with_admin = plant("127.0.0.1:0", "127.0.0.1:0");
        let without = with_admin.replace(&token("admin", "admin", ADMIN), "");
        assert!(!without.contains("http.token"), "{without}");
        let d = TestDaemon::reloadable(&without).await;
        // Without tokens, a client on loopback is admin without one.
        let open = Api::new(d.http, None);
        let me = open.get("/api/v1/whoami").await.expect(200);
        assert_eq!(me["role"], "admin", "{me}");

        // The first token, for a SCADA: an operator's.
        const SCADA: &str = "listeners-first-scada-token";
        d.rewrite(&format!(
            "{without}\n{}",
            token("lsn_first_scada", "operator", SCADA)
        ));
        let reply = reload(&open).await.expect(200);
        let said = lines(&reply, "changes");
        let first = said
            .iter()
            .find(|l| l.starts_with("first API token: "))
            .unwrap_or_else(|| panic!("{reply}"));
        assert!(
            first
                .contains("from now on every client needs a token, on this machine (loopback) too")
                && first.contains("no token has the admin role")
                && first.contains("`drivegate token new --name NAME --role admin`"),
            "{first}"
        );
        // The log line of the reload says it too.
        assert!(
            log_text()
                .lines()
                .any(|l| l.contains("configuration reloaded") && l.contains(first.as_str())),
            "no log line of the first token"
        );
        // And so it is: no token, no answer; the operator may not reload.
        let api = Api::new(d.http, None);
        let me = api.get("/api/v1/whoami").await.expect(200);
        assert_eq!(
            (&me["role"], &me["tokens_required"]),
            (&json!(null), &json!(true)),
            "{me}"
        );
        reload(&api).await.expect_problem(401, "unauthorized");
        reload(&api.with_token(Some(SCADA)))
            .await
            .expect_problem(403, "forbidden");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_port_changed_reopens_that_bus_only() {
    bounded(LIMIT, async {
        let two = |line2_port: &str| {
            ConfigBuilder::new()
                .bus("line1", |b| b.drive(1, "lsn_kiln"))
                .bus("line2", |b| {
                    b.port(line2_port)
                        .auto_guard()
                        .drive(1, "lsn_saw")
                        .drive(2, "lsn_drill")
                })
                .http_token("admin", "admin", ADMIN)
                .section("safety", "lease_max_ms = 600000")
                .toml()
        };
        let d = TestDaemon::reloadable(&two("sim")).await;
        let api = Api::new(d.http, Some(ADMIN));
        let line1_bus = d.plant.bus("line1").unwrap();
        let line1 = SimRef::of(line1_bus.clone()).unwrap();
        api.activate_in("lsn_kiln", "speed").await;
        api.put(
            "/api/v1/drives/lsn_kiln/setpoint",
            json!({"speed_rpm": 100, "lease_ms": 600000}),
        )
        .await
        .expect(200);
        eventually(EVENT, "the kiln at 100 rpm", || {
            ((line1.drive(1)?.speed_rpm - 100.0).abs() <= 2.0).then_some(())
        })
        .await;
        let lease = api.get("/api/v1/drives/lsn_kiln").await.expect(200)["lease"].clone();
        let mut ws = connect(d.http, "?drives=lsn_kiln", Some(ADMIN)).await;

        // line2's drives move behind a serial device server.
        let mut config = drivegate::sim::SimConfig::for_units(1..=2);
        config.listen = Some("127.0.0.1:0".parse().unwrap());
        let server = drivegate::sim::Simulator::start(config).unwrap();
        let port = server.port_path().display().to_string();
        d.rewrite(&two(&port));
        let reply = reload(&api).await.expect(200);
        // Its port (and, being no longer the built-in simulator, its
        // [bus.sim]) changed; nothing else.
        let changes = lines(&reply, "changes");
        assert_eq!(changes.len(), 1, "{reply}");
        assert!(
            changes[0].starts_with("bus line2 reopened (port"),
            "{reply}"
        );
        assert_eq!(reply["problems"], json!([]), "{reply}");
        // Its drives answer through the new port.
        eventually(
            EVENT,
            "the saw and the drill polled on the new port",
            || {
                let bus = d.plant.bus("line2")?;
                assert_eq!(*bus.config.port.get_ref(), port);
                bus.handle
                    .drives()
                    .iter()
                    .all(|s| s.status.is_some())
                    .then_some(())
            },
        )
        .await;
        assert!(
            server.stats().replies > 0,
            "the server on {port} was never asked"
        );
        // line1 is the same bus, its kiln turning under its lease.
        assert!(std::sync::Arc::ptr_eq(
            &line1_bus,
            &d.plant.bus("line1").unwrap()
        ));
        let drive = line1.drive(1).unwrap();
        assert_eq!(drive.setpoints.speed_rpm, 100);
        let now = api.get("/api/v1/drives/lsn_kiln").await.expect(200)["lease"].clone();
        assert_eq!(
            (&now["owner"], &now["lease_ms"]),
            (&lease["owner"], &lease["lease_ms"])
        );
        wait_for(&mut ws, EVENT, "a status of the kiln", |v| {
            v["type"] == "status" && v["drive"] == "lsn_kiln"
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn new_limits_keep_the_listener_socket_and_a_disabled_listener_closes_then_opens_again() {
    bounded(LIMIT, async {
        let d = TestDaemon::reloadable(&plant("127.0.0.1:0", "127.0.0.1:0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        let at = d.modbus_tcp.unwrap();
        let mut before = Raw::connect(at).await;
        assert_eq!(before.ask(1, &read(0xC0, 7)).await[0], 0x03);

        // New limits, same address: the same socket, served with them; the
        // client connected under the old ones is closed and connects again.
        let limits = plant("127.0.0.1:0", "127.0.0.1:0")
            .replace("[modbus_tcp]\n", "[modbus_tcp]\nmax_connections = 5\n");
        assert_ne!(limits, plant("127.0.0.1:0", "127.0.0.1:0"));
        d.rewrite(&limits);
        let reply = reload(&api).await.expect(200);
        assert_eq!(
            lines(&reply, "changes"),
            vec![format!(
                "Modbus TCP listener reopened on {at} with the new [modbus_tcp]"
            )],
            "{reply}"
        );
        assert!(before.closed_by_server().await, "the old connection stayed");
        let mut after = Raw::connect(at).await;
        assert_eq!(after.ask(1, &read(0xC0, 7)).await[0], 0x03);
        assert_eq!(d.faces_addresses().await.modbus_tcp, Some(at));

        // Turned off: closed, the port refuses.
        let off = plant("127.0.0.1:0", "127.0.0.1:0")
            .replace("[modbus_tcp]\n", "[modbus_tcp]\nenabled = false\n");
        d.rewrite(&off);
        let reply = reload(&api).await.expect(200);
        assert_eq!(
            lines(&reply, "changes"),
            vec![format!("Modbus TCP listener closed (it was on {at})")],
            "{reply}"
        );
        assert!(refused(at).await, "{at} still takes connections");
        assert!(after.closed_by_server().await);
        assert_eq!(d.faces_addresses().await.modbus_tcp, None);

        // On again, where the system chooses.
        d.rewrite(&plant("127.0.0.1:0", "127.0.0.1:0"));
        let reply = reload(&api).await.expect(200);
        let now = d
            .faces_addresses()
            .await
            .modbus_tcp
            .expect("listening again");
        let changes = lines(&reply, "changes");
        assert!(
            changes.contains(&format!("Modbus TCP listener opened on {now}")),
            "{reply}"
        );
        assert_eq!(status_by_pymodbus(now).await.len(), 7);
        d.stop().await;
    })
    .await;
}
