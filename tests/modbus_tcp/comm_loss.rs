//! The communication-loss function of a Modbus TCP client network, with a
//! real third-party client (pymodbus, `tests/python/plc_client.py`) as the
//! PLC: it writes a speed, then keeps polling (the motor keeps turning),
//! falls silent (stopped once the time passes), closes its socket (stopped
//! at once), or is cut off without a FIN behind a proxy and killed (stopped
//! by the time). A network without a time leaves the motor alone, as
//! before; a brake over HTTP ends the PLC's lease and nothing follows it.
//!
//! Timing is asserted only as the design gives it: a stop is waited for as
//! an event, with generous bounds; "at once" is checked against a time ten
//! times longer.

use std::time::{Duration, Instant};

use serde_json::Value;

use crate::support::api::{Api, Ws, connect, messages_within, wait_for};
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::metric;
use crate::support::modbus_tcp::{Plc, Raw, four_drives_with, write, writes_handled};
use crate::support::proxy::CutProxy;
use crate::support::{TestDaemon, eventually};

const LIMIT: Duration = Duration::from_secs(90);
/// Longest wait for an event the design says must come.
const EVENT: Duration = Duration::from_secs(20);
const CONVEYOR: u8 = 1;
const CONFIG: u16 = 0x0002;
const ACTIVATE: u16 = 0x0000;
const SPEED_MODE: u16 = 0x000A;
const SPEED_REF: u16 = 0x0006;
const RPM: u16 = 300;
/// The PLC's cycle.
const POLL_MS: u64 = 100;

/// FOUR_DRIVES with loopback an operator network, its communication-loss
/// keys `keys` (none: the function is off).
fn config(keys: &str) -> String {
    four_drives_with(&format!(
        "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"\n{keys}"
    ))
}

/// Starts a PLC at `addr` that activates the conveyor in speed mode and
/// sets it turning.
async fn plc_turning(d: &TestDaemon, addr: std::net::SocketAddr) -> Plc {
    let mut plc = Plc::connect(addr).await;
    plc.write(CONVEYOR, CONFIG, ACTIVATE).await;
    plc.write(CONVEYOR, CONFIG, SPEED_MODE).await;
    plc.write(CONVEYOR, SPEED_REF, RPM).await;
    eventually(EVENT, "the conveyor turning", || {
        (d.sim().drive(CONVEYOR)?.speed_rpm > 100.0).then_some(())
    })
    .await;
    plc
}

/// The conveyor's lease as `GET /api/v1/drives/conveyor` shows it.
async fn lease(api: &Api) -> Value {
    api.get("/api/v1/drives/conveyor").await.expect(200)["lease"].clone()
}

fn lease_news(v: &Value) -> bool {
    matches!(
        v["type"].as_str(),
        Some("lease-expired" | "lease-stop" | "lease-ended")
    )
}

/// The PLC falls silent past its time (`comm_loss_ms`), then closes its
/// connection; every stream message seen meanwhile.
async fn silence_then_close(plc: &mut Plc, ws: &mut Ws, comm_loss_ms: u64) -> Vec<Value> {
    plc.tell("silence").await;
    let mut seen = messages_within(ws, Duration::from_millis(comm_loss_ms + 1000)).await;
    plc.tell("close").await;
    seen.extend(messages_within(ws, Duration::from_millis(500)).await);
    seen
}

/// The conveyor comes to rest: the stop set its speed setpoint to 0.
async fn stopped(d: &TestDaemon) {
    eventually(EVENT, "the conveyor stopping", || {
        let drive = d.sim().drive(CONVEYOR)?;
        (drive.setpoints.speed_rpm == 0 && drive.speed_rpm.abs() < 5.0).then_some(())
    })
    .await;
}

/// `drivegate_modbus_tcp_comm_loss_stops_total` of bus `sim` for
/// `reason`; the series must be there, at 0 from start-up.
fn comm_loss_stops(d: &TestDaemon, reason: &str) -> f64 {
    let series =
        format!("drivegate_modbus_tcp_comm_loss_stops_total{{bus=\"sim\",reason=\"{reason}\"}}");
    let text = d.metrics.render();
    assert!(
        text.contains(&format!("{series} ")),
        "no {series} in:\n{text}"
    );
    metric(&text, &series)
}

/// The stop's write, as the stream shows it: drivegate's, for the lease of
/// `owner`, confirmed.
async fn stop_write(ws: &mut Ws, owner: &str) -> Value {
    let who = format!("lease-expiry ({owner})");
    let write = wait_for(ws, EVENT, "the stop's write", |v| {
        v["type"] == "write" && v["who"] == who.as_str()
    })
    .await;
    assert_eq!(
        write["what"], "speed setpoint 0 rpm (SPEED_REF=0)",
        "{write:#}"
    );
    assert_eq!(write["ok"], true, "{write:#}");
    write
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_polling_plc_keeps_its_motor_turning_and_a_silent_one_is_stopped() {
    const COMM_LOSS_MS: u64 = 1000;
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!("comm_loss_ms = {COMM_LOSS_MS}"))).await;
        let api = Api::new(d.http, None);
        assert_eq!(comm_loss_stops(&d, "timeout"), 0.0, "present from start-up");
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;

        // The lease is the PLC connection's, shown with its address.
        let held = lease(&api).await;
        let owner = held["owner"].as_str().unwrap().to_string();
        assert!(owner.starts_with("modbus-tcp 127.0.0.1:"), "{held:#}");
        assert_eq!(held["lease_ms"], COMM_LOSS_MS);
        assert_eq!(held["comm_loss"], true);
        assert_eq!(held["websocket"], false);
        assert_eq!(held["action"], "zero-speed");

        // Polling at its cycle for four times the time: it keeps turning.
        assert_eq!(
            plc.tell(&format!("poll {CONVEYOR} {POLL_MS}")).await["polling"],
            true
        );
        let seen = messages_within(&mut ws, Duration::from_millis(4 * COMM_LOSS_MS)).await;
        let news: Vec<&Value> = seen.iter().filter(|v| lease_news(v)).collect();
        assert!(news.is_empty(), "the lease ended while polled: {news:#?}");
        assert!(d.sim().drive(CONVEYOR).unwrap().speed_rpm > 100.0);
        assert_eq!(lease(&api).await["owner"], owner.as_str());

        // Silent: stopped once the time has passed since its last request.
        let silent = plc.tell("silence").await;
        let silent_at = Instant::now();
        assert!(silent["polls"].as_u64().unwrap() > 0, "{silent}");
        assert_eq!(silent["failed"], 0, "{silent}");
        stop_write(&mut ws, &owner).await;
        let expired = wait_for(&mut ws, EVENT, "lease-expired", |v| {
            v["type"] == "lease-expired"
        })
        .await;
        assert!(
            silent_at.elapsed() < Duration::from_millis(COMM_LOSS_MS + POLL_MS) + EVENT,
            "the stop came too late"
        );
        assert_eq!(expired["owner"], owner.as_str(), "{expired:#}");
        assert_eq!(
            expired["reason"],
            format!(
                "communication was lost: no request came on its connection for {COMM_LOSS_MS} ms"
            ),
        );
        assert_eq!(
            (&expired["action"], &expired["ok"], &expired["retrying"]),
            (&"zero-speed".into(), &true.into(), &false.into()),
            "{expired:#}"
        );
        stopped(&d).await;
        assert!(lease(&api).await.is_null());
        assert_eq!(comm_loss_stops(&d, "timeout"), 1.0);
        assert_eq!(comm_loss_stops(&d, "closed"), 0.0);

        // Closing the connection afterwards ends nothing more.
        plc.tell("close").await;
        let seen = messages_within(&mut ws, Duration::from_millis(500)).await;
        assert!(!seen.iter().any(lease_news), "{seen:#?}");
        assert_eq!(comm_loss_stops(&d, "closed"), 0.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_closing_its_connection_is_stopped_at_once() {
    // Ten times longer than the bound on "at once" below.
    const COMM_LOSS_MS: u64 = 60_000;
    capture_logs();
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!(
            "comm_loss_ms = {COMM_LOSS_MS}\ncomm_loss_action = \"zero-speed\""
        )))
        .await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;
        let owner = lease(&api).await["owner"].as_str().unwrap().to_string();
        assert_eq!(plc.tell("close").await["closed"], true);
        let closed_at = Instant::now();
        // The stop's write is published first, then the lease's end.
        stop_write(&mut ws, &owner).await;
        let expired = wait_for(&mut ws, EVENT, "lease-expired", |v| {
            v["type"] == "lease-expired"
        })
        .await;
        assert!(closed_at.elapsed() < Duration::from_millis(COMM_LOSS_MS / 3));
        assert_eq!(expired["reason"], "its Modbus TCP connection closed");
        assert_eq!(expired["owner"], owner.as_str());
        assert_eq!(
            expired["sent"], "speed setpoint 0 rpm (SPEED_REF=0)",
            "{expired:#}"
        );
        // The audit log has the lease's end, its holder and why.
        let who = format!("who={owner}");
        let line = eventually(EVENT, "the lease's end in the audit log", || {
            log_text()
                .lines()
                .find(|l| {
                    l.contains("drivegate::audit")
                        && l.contains("lease ended with its stop")
                        && l.contains(&who)
                })
                .map(str::to_string)
        })
        .await;
        assert!(
            line.contains("reason=its Modbus TCP connection closed")
                && line.contains("action=\"zero-speed\"")
                && line.contains("confirmed by the drive"),
            "{line}"
        );
        stopped(&d).await;
        assert_eq!(comm_loss_stops(&d, "closed"), 1.0);
        assert_eq!(comm_loss_stops(&d, "timeout"), 0.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_cut_off_without_a_fin_is_stopped_by_the_time() {
    const COMM_LOSS_MS: u64 = 1000;
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!("comm_loss_ms = {COMM_LOSS_MS}"))).await;
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let proxy = CutProxy::start(d.modbus_tcp.unwrap()).await;
        let mut plc = plc_turning(&d, proxy.addr).await;
        plc.tell(&format!("poll {CONVEYOR} {POLL_MS}")).await;
        // The cable is pulled, then the PLC dies: its FIN goes nowhere.
        proxy.cut();
        plc.kill().await;
        let expired = wait_for(&mut ws, EVENT, "lease-expired", |v| {
            v["type"] == "lease-expired"
        })
        .await;
        assert_eq!(
            expired["reason"],
            format!(
                "communication was lost: no request came on its connection for {COMM_LOSS_MS} ms"
            ),
            "{expired:#}"
        );
        stopped(&d).await;
        // The daemon never saw the connection close: the time stopped it.
        let text = d.metrics.render();
        assert_eq!(metric(&text, "drivegate_modbus_tcp_connections "), 1.0);
        assert_eq!(comm_loss_stops(&d, "timeout"), 1.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_network_without_a_time_leaves_the_motor_as_before() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("")).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;
        assert!(lease(&api).await.is_null(), "no lease without a time");
        plc.tell("silence").await;
        plc.tell("close").await;
        let seen = messages_within(&mut ws, Duration::from_millis(1500)).await;
        assert!(!seen.iter().any(lease_news), "{seen:#?}");
        let drive = d.sim().drive(CONVEYOR).unwrap();
        assert_eq!(drive.setpoints.speed_rpm, RPM as i16);
        assert!(drive.speed_rpm > 100.0);
        assert_eq!(comm_loss_stops(&d, "timeout"), 0.0);
        assert_eq!(comm_loss_stops(&d, "closed"), 0.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_http_brake_ends_a_plc_lease_and_no_stop_follows() {
    const COMM_LOSS_MS: u64 = 1000;
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!(
            "comm_loss_ms = {COMM_LOSS_MS}\ncomm_loss_action = \"zero-speed\""
        )))
        .await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;
        plc.tell(&format!("poll {CONVEYOR} {POLL_MS}")).await;
        let owner = lease(&api).await["owner"].as_str().unwrap().to_string();

        api.command("conveyor", "brake").await;
        let after = writes_handled(&bus);
        assert!(lease(&api).await.is_null(), "ended at once");
        let ended = wait_for(&mut ws, EVENT, "lease-ended", |v| {
            v["type"] == "lease-ended"
        })
        .await;
        // The brake's own write comes after the end of the lease it ended.
        wait_for(&mut ws, EVENT, "the brake's write", |v| {
            v["type"] == "write"
                && v["what"]
                    .as_str()
                    .unwrap()
                    .starts_with("config command brake")
        })
        .await;
        assert_eq!(ended["owner"], owner.as_str());
        assert!(
            ended["reason"]
                .as_str()
                .unwrap()
                .starts_with("the brake from"),
            "{ended:#}"
        );
        assert!(
            ended["reason"]
                .as_str()
                .unwrap()
                .ends_with("over HTTP was confirmed"),
            "{ended:#}"
        );

        // The PLC falls silent, then closes: past the time, nothing is
        // sent, and the brake holds.
        let seen = silence_then_close(&mut plc, &mut ws, COMM_LOSS_MS).await;
        let news: Vec<&Value> = seen.iter().filter(|v| lease_news(v)).collect();
        assert!(news.is_empty(), "a stop followed the brake: {news:#?}");
        let stops: Vec<&Value> = seen.iter().filter(|v| v["type"] == "write").collect();
        assert!(stops.is_empty(), "a write followed the brake: {stops:#?}");
        assert_eq!(writes_handled(&bus), after, "a write reached the bus");
        assert!(
            d.sim().drive(CONVEYOR).unwrap().braking,
            "the brake was released"
        );
        assert_eq!(comm_loss_stops(&d, "timeout"), 0.0);
        assert_eq!(comm_loss_stops(&d, "closed"), 0.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broadcast_setpoint_takes_a_lease_on_each_active_drive() {
    const COMM_LOSS_MS: u64 = 60_000;
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!("comm_loss_ms = {COMM_LOSS_MS}"))).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=all", None).await;
        // The conveyor is active in speed mode; the lift is not.
        api.activate_in("conveyor", "speed").await;
        eventually(EVENT, "the poll seeing the conveyor active", || {
            d.plant.buses()[0]
                .handle
                .drive(CONVEYOR)?
                .status?
                .active()
                .then_some(())
        })
        .await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        let owner = format!("modbus-tcp {}", plc.stream.local_addr().unwrap());
        plc.send(1, 0, &write(SPEED_REF, RPM)).await;
        eventually(EVENT, "the conveyor turning", || {
            (d.sim().drive(CONVEYOR)?.speed_rpm > 100.0).then_some(())
        })
        .await;
        let held = lease(&api).await;
        assert_eq!(
            (&held["owner"], &held["comm_loss"]),
            (&owner.as_str().into(), &true.into())
        );
        for other in ["lift", "turntable", "feeder"] {
            let drive = api
                .get(&format!("/api/v1/drives/{other}"))
                .await
                .expect(200);
            assert!(drive["lease"].is_null(), "{other}: {drive:#}");
        }
        // Closed: the conveyor alone is stopped.
        drop(plc);
        let expired = wait_for(&mut ws, EVENT, "lease-expired", |v| {
            v["type"] == "lease-expired"
        })
        .await;
        assert_eq!(
            (&expired["drive"], &expired["ok"]),
            (&"conveyor".into(), &true.into())
        );
        stopped(&d).await;
        let seen = messages_within(&mut ws, Duration::from_millis(500)).await;
        assert!(!seen.iter().any(lease_news), "{seen:#?}");
        assert_eq!(comm_loss_stops(&d, "closed"), 1.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_leased_setpoint_over_http_takes_over_and_the_plcs_silence_stops_nothing() {
    const COMM_LOSS_MS: u64 = 1000;
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config(&format!(
            "comm_loss_ms = {COMM_LOSS_MS}\ncomm_loss_action = \"brake\""
        )))
        .await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;
        let owner = lease(&api).await["owner"].as_str().unwrap().to_string();
        let r = api
            .put(
                "/api/v1/drives/conveyor/setpoint",
                serde_json::json!({"speed_rpm": 200, "lease_ms": 60000}),
            )
            .await
            .expect(200);
        assert_eq!(r["lease"]["comm_loss"], false, "{r:#}");
        let ended = wait_for(&mut ws, EVENT, "lease-ended", |v| {
            v["type"] == "lease-ended"
        })
        .await;
        assert_eq!(ended["owner"], owner.as_str());
        assert!(
            ended["reason"]
                .as_str()
                .unwrap()
                .starts_with("replaced by a leased setpoint from"),
            "{ended:#}"
        );
        // The PLC goes quiet, then closes: its time passes, nothing stops.
        let seen = silence_then_close(&mut plc, &mut ws, COMM_LOSS_MS).await;
        let news: Vec<&Value> = seen.iter().filter(|v| lease_news(v)).collect();
        assert!(news.is_empty(), "{news:#?}");
        let drive = d.sim().drive(CONVEYOR).unwrap();
        assert!(!drive.braking && drive.setpoints.speed_rpm == 200);
        assert_eq!(lease(&api).await["comm_loss"], false);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn action_none_shows_and_counts_the_loss_and_leaves_the_motor_turning() {
    tokio::time::timeout(LIMIT, async {
        let d =
            TestDaemon::start(&config("comm_loss_ms = 60000\ncomm_loss_action = \"none\"")).await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = plc_turning(&d, d.modbus_tcp.unwrap()).await;
        let held = lease(&api).await;
        assert_eq!(
            (&held["action"], &held["comm_loss"]),
            (&"none".into(), &true.into())
        );
        let before = writes_handled(&bus);
        plc.tell("close").await;
        let expired = wait_for(&mut ws, EVENT, "lease-expired", |v| {
            v["type"] == "lease-expired"
        })
        .await;
        assert_eq!(expired["action"], "none", "{expired:#}");
        assert!(expired["sent"].is_null(), "{expired:#}");
        assert_eq!(
            expired["result"],
            "the lease's action is \"none\": nothing sent"
        );
        assert_eq!(comm_loss_stops(&d, "closed"), 1.0);
        assert_eq!(writes_handled(&bus), before, "something was written");
        let drive = d.sim().drive(CONVEYOR).unwrap();
        assert_eq!(drive.setpoints.speed_rpm, RPM as i16);
        assert!(drive.speed_rpm > 100.0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A communication-loss stop is an alarm (kind `comm-loss`) that waits for
/// an operator's acknowledgement, whatever the PLC does next; here a raw
/// MBAP client that closes its connection.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_communication_loss_stop_raises_an_alarm() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("comm_loss_ms = 60000")).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        plc.ask(CONVEYOR, &write(CONFIG, ACTIVATE)).await;
        plc.ask(CONVEYOR, &write(CONFIG, SPEED_MODE)).await;
        plc.ask(CONVEYOR, &write(SPEED_REF, RPM)).await;
        eventually(EVENT, "the conveyor's lease", || {
            d.control().lease(0).map(|_| ())
        })
        .await;
        drop(plc);
        let raised = wait_for(&mut ws, EVENT, "the comm-loss alarm", |v| {
            v["type"] == "alarm-raised" && v["alarm"]["kind"] == "comm-loss"
        })
        .await;
        let alarm = &raised["alarm"];
        assert_eq!(alarm["drive"], "conveyor", "{alarm:#}");
        assert!(
            alarm["text"]
                .as_str()
                .unwrap()
                .contains("its connection closed"),
            "{alarm:#}"
        );
        assert!(
            alarm["help"].as_str().unwrap().contains("comm_loss_ms"),
            "{alarm:#}"
        );
        let list = api
            .get("/api/v1/alarms?unacknowledged=true")
            .await
            .expect(200);
        assert!(
            list["alarms"]
                .as_array()
                .unwrap()
                .iter()
                .any(|a| a["id"] == alarm["id"]),
            "{list:#}"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
