//! Motor-safety leases over real HTTP and WebSocket, checked against the
//! simulated drive: an unrenewed lease stops the motor (zero speed, zero
//! torque, or the brake as configured) and says so on the stream; renewing
//! keeps it running; a lease taken over a WebSocket ends with the socket;
//! the brake and an explicit release end a lease without a stop.

use std::time::{Duration, Instant};

use crate::support::api::{Api, config, connect, next_json, send_json, wait_for, ws_command};
use crate::support::bus::hold_the_wire;
use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(40);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unrenewed_lease_stops_the_motor() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let mut ws = connect(d.http, "?drives=conveyor,feeder", None).await;
        assert_eq!(
            next_json(&mut ws, Duration::from_secs(5)).await["type"],
            "subscribed"
        );

        api.activate_in("conveyor", "speed").await;
        let sent = Instant::now();
        let r = api
            .put(
                "/api/v1/drives/conveyor/setpoint",
                json!({"speed_rpm": 200, "lease_ms": 300}),
            )
            .await
            .expect(200);
        let lease = &r["lease"];
        assert_eq!(
            (lease["lease_ms"].as_u64(), lease["websocket"].as_bool()),
            (Some(300), Some(false))
        );
        assert!(lease["owner"].as_str().unwrap().starts_with("127.0.0.1:"));
        assert!(lease["expires_in_ms"].as_u64().unwrap() <= 300);
        let shown = api.get("/api/v1/drives/conveyor").await.expect(200);
        assert_eq!(shown["lease"]["lease_ms"], 300);
        eventually(Duration::from_secs(5), "the conveyor turning", || {
            (sim.drive(1)?.speed_rpm > 100.0).then_some(())
        })
        .await;

        // Nobody renews: the setpoint goes to zero and the motor stops.
        eventually(Duration::from_secs(5), "the zero-speed stop", || {
            (sim.drive(1)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        assert!(
            sent.elapsed() >= Duration::from_millis(300),
            "stopped before the lease ran out"
        );
        let event = wait_for(
            &mut ws,
            Duration::from_secs(5),
            "the lease-expired event",
            |v| v["type"] == "lease-expired",
        )
        .await;
        assert_eq!(event["drive"], "conveyor");
        assert_eq!(event["action"], "zero-speed");
        assert_eq!(event["ok"], true);
        assert!(
            event["sent"]
                .as_str()
                .unwrap()
                .contains("speed setpoint 0 rpm"),
            "{event:#}"
        );
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        assert!(api.get("/api/v1/drives/conveyor").await.expect(200)["lease"].is_null());
        api.post_empty("/api/v1/drives/conveyor/lease/renew")
            .await
            .expect_problem(409, "no-lease");

        // In torque mode zero speed means zero current.
        api.activate_in("feeder", "torque").await;
        api.put(
            "/api/v1/drives/feeder/setpoint",
            json!({"torque_a": 0.25, "lease_ms": 300}),
        )
        .await
        .expect(200);
        assert_eq!(sim.drive(4).unwrap().setpoints.current_counts, 32);
        eventually(Duration::from_secs(5), "the zero-torque stop", || {
            (sim.drive(4)?.setpoints.current_counts == 0).then_some(())
        })
        .await;
        let event = wait_for(
            &mut ws,
            Duration::from_secs(5),
            "the feeder's lease-expired event",
            |v| v["type"] == "lease-expired" && v["drive"] == "feeder",
        )
        .await;
        assert!(
            event["sent"]
                .as_str()
                .unwrap()
                .contains("torque setpoint 0 A"),
            "{event:#}"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// The lease renewed in `renewing_keeps_the_motor_running_and_release_ends_the_lease`.
const RENEWED_LEASE_MS: u64 = 5000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn renewing_keeps_the_motor_running_and_release_ends_the_lease() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        api.activate_in("lift", "speed").await;
        api.put(
            "/api/v1/drives/lift/setpoint",
            json!({"speed_rpm": 100, "lease_ms": RENEWED_LEASE_MS}),
        )
        .await
        .expect(200);
        let granted = Instant::now();

        // Renew every 100 ms for over a second, by the renew route and by
        // repeating the setpoint: the motor keeps its setpoint (a renewal
        // may come seconds late on a loaded machine: the lease is longer).
        let until = Instant::now() + Duration::from_millis(1200);
        let mut i = 0;
        while Instant::now() < until {
            if i % 2 == 0 {
                let lease = api
                    .post_empty("/api/v1/drives/lift/lease/renew")
                    .await
                    .expect(200);
                assert_eq!(lease["lease_ms"], RENEWED_LEASE_MS);
            } else {
                api.put(
                    "/api/v1/drives/lift/setpoint",
                    json!({"speed_rpm": 100, "lease_ms": RENEWED_LEASE_MS}),
                )
                .await
                .expect(200);
            }
            assert_eq!(
                sim.drive(2).unwrap().setpoints.speed_rpm,
                100,
                "stopped while renewed"
            );
            i += 1;
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // Each renewal pushed the end a whole lease ahead (the grant alone
        // would have left 1.2 s less).
        let lease = api
            .post_empty("/api/v1/drives/lift/lease/renew")
            .await
            .expect(200);
        let left = lease["expires_in_ms"].as_u64().unwrap();
        let since = u64::try_from(granted.elapsed().as_millis()).unwrap();
        assert!(
            left + since > RENEWED_LEASE_MS + 1000,
            "{left} ms left {since} ms after the grant"
        );
        // A renewal may change the length, within the configured bounds.
        let lease = api
            .post("/api/v1/drives/lift/lease/renew", json!({"lease_ms": 400}))
            .await
            .expect(200);
        assert_eq!(lease["lease_ms"], 400);
        api.post(
            "/api/v1/drives/lift/lease/renew",
            json!({"lease_ms": 10_000_000}),
        )
        .await
        .expect_problem(422, "out-of-range");
        // Then it stops when the renewals stop.
        eventually(Duration::from_secs(5), "the stop", || {
            (sim.drive(2)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;

        // Released, the lease ends without a stop.
        api.put(
            "/api/v1/drives/lift/setpoint",
            json!({"speed_rpm": 80, "lease_ms": 300}),
        )
        .await
        .expect(200);
        let released = api.delete("/api/v1/drives/lift/lease").await.expect(200);
        assert_eq!(released["drive"], "lift");
        api.delete("/api/v1/drives/lift/lease")
            .await
            .expect_problem(409, "no-lease");
        tokio::time::sleep(Duration::from_millis(700)).await;
        assert_eq!(sim.drive(2).unwrap().setpoints.speed_rpm, 80);

        // The brake ends a lease too: zero speed at expiry would release it.
        api.put(
            "/api/v1/drives/lift/setpoint",
            json!({"speed_rpm": 60, "lease_ms": 300}),
        )
        .await
        .expect(200);
        api.command("lift", "brake").await;
        assert!(api.get("/api/v1/drives/lift").await.expect(200)["lease"].is_null());
        tokio::time::sleep(Duration::from_millis(700)).await;
        assert!(sim.drive(2).unwrap().braking, "the brake was released");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lease_taken_over_a_websocket_ends_with_the_socket() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        api.activate_in("turntable", "speed").await;

        let mut ws = connect(d.http, "", None).await;
        let reply = ws_command(
            &mut ws,
            7,
            "setpoint",
            "turntable",
            json!({"speed_rpm": 150, "lease_ms": 60000}),
        )
        .await;
        assert_eq!(reply["ok"], true, "{reply:#}");
        assert_eq!(reply["result"]["lease"]["websocket"], true);
        assert_eq!(sim.drive(3).unwrap().setpoints.speed_rpm, 150);
        // Renewals over the socket work like the REST route.
        let renewed = ws_command(&mut ws, 8, "lease-renew", "turntable", json!({})).await;
        assert_eq!(renewed["result"]["lease_ms"], 60000);

        // The client vanishes without a close handshake (a crash): the motor
        // is stopped long before the 60 s lease would have run out.
        let gone = Instant::now();
        drop(ws);
        eventually(
            Duration::from_secs(5),
            "the stop after the socket dropped",
            || (sim.drive(3)?.setpoints.speed_rpm == 0).then_some(()),
        )
        .await;
        assert!(gone.elapsed() < Duration::from_secs(30));
        assert!(api.get("/api/v1/drives/turntable").await.expect(200)["lease"].is_null());
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_expiry_action_can_be_the_brake() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("", "[safety]\non_lease_expiry = \"brake\"")).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        api.activate_in("conveyor", "speed").await;
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 120, "lease_ms": 300}),
        )
        .await
        .expect(200);
        eventually(Duration::from_secs(5), "the emergency brake", || {
            sim.drive(1)?.braking.then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "the conveyor held", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A bus whose response timeout (and guard time) is 1.5 s, so a request to
/// a unit nobody answers holds the wire for 3 s, and whose leases end with
/// the brake: one emergency job, so nothing can slip in between the stop's
/// read and its write, and a setpoint sent after it would release it.
fn slow_bus_with_brake_on_expiry() -> String {
    ConfigBuilder::four_drives()
        .with_bus("sim", |b| b.keys("response_timeout_ms = 1500").auto_guard())
        .section("safety", "on_lease_expiry = \"brake\"")
        .toml()
}

/// Waits until the conveyor's poll shows it active, so a setpoint goes
/// straight to the queue (no read to confirm an inactive cached status).
async fn polled_active(bus: &drivegate::bus::BusHandle) {
    eventually(Duration::from_secs(5), "the conveyor polled active", || {
        bus.drive(1)?.status?.active().then_some(())
    })
    .await;
}

/// Waits until the stream's setpoint for the conveyor is queued (the only
/// command waiting) with its lease in place.
async fn setpoint_queued(api: &Api, bus: &drivegate::bus::BusHandle) {
    let start = Instant::now();
    loop {
        if bus.queue_depths()[1] == 1
            && !api.get("/api/v1/drives/conveyor").await.expect(200)["lease"].is_null()
        {
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(2),
            "the setpoint was not queued with its lease"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Writes (function 0x06) the bus has dealt with: sent, failed or dropped.
fn writes_dealt_with(bus: &drivegate::bus::BusHandle) -> u64 {
    bus.stats()
        .transactions
        .iter()
        .filter(|((function, _), _)| *function == 0x06)
        .map(|(_, n)| n)
        .sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_still_queued_when_its_socket_closes_never_runs_the_motor() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&slow_bus_with_brake_on_expiry()).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let bus = d.plant.buses()[0].handle.clone();
        api.activate_in("conveyor", "speed").await;
        polled_active(&bus).await;
        let mut ws = connect(d.http, "", None).await;
        let before = writes_dealt_with(&bus);

        // The setpoint queues behind a request that holds the wire, with
        // its lease in place; then the client vanishes.
        let blocker = hold_the_wire(&bus).await;
        send_json(
            &mut ws,
            json!({"type": "command", "id": 1, "op": "setpoint", "drive": "conveyor",
                   "body": {"speed_rpm": 200, "lease_ms": 60000}}),
        )
        .await;
        setpoint_queued(&api, &bus).await;
        drop(ws);

        // Both writes dealt with, the brake and the setpoint (sent or
        // dropped), in whichever order the daemon chose.
        eventually(
            Duration::from_secs(15),
            "the brake and the setpoint",
            || (writes_dealt_with(&bus) >= before + 2).then_some(()),
        )
        .await;
        let conveyor = sim.drive(1).unwrap();
        assert!(
            conveyor.braking,
            "the motor is not held: setpoint {} rpm, turning at {:.0} rpm",
            conveyor.setpoints.speed_rpm, conveyor.speed_rpm
        );
        assert_eq!(
            conveyor.setpoints.speed_rpm, 0,
            "the setpoint reached the drive"
        );
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        assert!(api.get("/api/v1/drives/conveyor").await.expect(200)["lease"].is_null());
        drop(blocker);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_renewal_before_the_setpoint_is_confirmed_keeps_the_pending_allowance() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&slow_bus_with_brake_on_expiry()).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let bus = d.plant.buses()[0].handle.clone();
        api.activate_in("conveyor", "speed").await;
        polled_active(&bus).await;
        let mut ws = connect(d.http, "", None).await;

        let blocker = hold_the_wire(&bus).await;
        send_json(
            &mut ws,
            json!({"type": "command", "id": 1, "op": "setpoint", "drive": "conveyor",
                   "body": {"speed_rpm": 200, "lease_ms": 300}}),
        )
        .await;
        setpoint_queued(&api, &bus).await;
        // Renewed while the setpoint waits: the lease still allows for the
        // queue (seconds), not just its own 300 ms, which would run out
        // (and stop the motor) before the setpoint is even sent.
        let renewed = ws_command(&mut ws, 2, "lease-renew", "conveyor", json!({})).await;
        assert_eq!(renewed["ok"], true, "{renewed:#}");
        let left = renewed["result"]["expires_in_ms"].as_u64().unwrap();
        assert!(
            left > 1000,
            "the renewal cut the pending lease to {left} ms"
        );

        let reply = wait_for(
            &mut ws,
            Duration::from_secs(15),
            "the setpoint's reply",
            |v| v["type"] == "reply" && v["id"] == 1,
        )
        .await;
        assert_eq!(reply["ok"], true, "{reply:#}");
        assert_eq!(
            reply["result"]["lease"]["lease_ms"], 300,
            "the setpoint lost its lease while queued: {reply:#}"
        );
        // Then it runs its 300 ms and the brake holds the motor.
        eventually(Duration::from_secs(5), "the brake at expiry", || {
            sim.drive(1)?.braking.then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        drop(blocker);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_the_drive_did_not_answer_is_tried_again_until_it_does() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        api.activate_in("conveyor", "speed").await;
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 200, "lease_ms": 1000}),
        )
        .await
        .expect(200);
        // The drive stops answering (its motor keeps its setpoint), and the
        // lease runs out: the stop gets no answer.
        sim.set_silent(1, true);
        let event = wait_for(
            &mut ws,
            Duration::from_secs(10),
            "the lease-expired event",
            |v| v["type"] == "lease-expired",
        )
        .await;
        assert_eq!(
            (event["ok"].as_bool(), event["retrying"].as_bool()),
            (Some(false), Some(true)),
            "{event:#}"
        );
        assert!(
            event["result"].as_str().unwrap().contains("did not answer"),
            "{event:#}"
        );
        let p = api
            .post_empty("/api/v1/drives/conveyor/lease/renew")
            .await
            .expect_problem(409, "no-lease");
        let detail = p["detail"].as_str().unwrap();
        assert!(
            detail.contains("not confirmed yet")
                && detail.contains("did not answer")
                && !detail.contains("was stopped"),
            "{detail}"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert_eq!(sim.drive(1).unwrap().setpoints.speed_rpm, 200);

        // It answers again: the stop is tried again and confirmed.
        sim.set_silent(1, false);
        eventually(Duration::from_secs(15), "the zero-speed stop", || {
            (sim.drive(1)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        let event = wait_for(
            &mut ws,
            Duration::from_secs(10),
            "the lease-stop event",
            |v| v["type"] == "lease-stop",
        )
        .await;
        assert_eq!(event["stopped"], true, "{event:#}");
        assert!(event["attempts"].as_u64().unwrap() >= 2, "{event:#}");
        assert!(
            event["sent"]
                .as_str()
                .unwrap()
                .contains("speed setpoint 0 rpm"),
            "{event:#}"
        );
        let p = api
            .post_empty("/api/v1/drives/conveyor/lease/renew")
            .await
            .expect_problem(409, "no-lease");
        assert!(
            p["detail"]
                .as_str()
                .unwrap()
                .contains("confirmed by the drive"),
            "{p:#}"
        );
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A USB adapter between the daemon and the simulated drives: the daemon
/// opens a pty whose other end is relayed to the simulator's, so the
/// adapter can be unplugged (the daemon's port fails and its path is gone)
/// while the drives behind it keep their power and keep turning, as on a
/// real bus.
struct Adapter {
    link: std::path::PathBuf,
    drives: std::path::PathBuf,
    relay: Option<tokio::task::JoinHandle<()>>,
}

impl Adapter {
    fn new(link: &std::path::Path, drives: &std::path::Path) -> Self {
        Adapter {
            link: link.to_path_buf(),
            drives: drives.to_path_buf(),
            relay: None,
        }
    }

    fn plug_in(&mut self) {
        let mut pty = drivegate::sim::pty::Pty::open().unwrap();
        let _ = std::fs::remove_file(&self.link);
        std::os::unix::fs::symlink(pty.path(), &self.link).unwrap();
        let mut drives = drivegate::bus::port::open(
            &self.drives.display().to_string(),
            115_200,
            &Default::default(),
        )
        .unwrap();
        self.relay = Some(tokio::spawn(async move {
            let _ = tokio::io::copy_bidirectional(pty.master(), &mut drives).await;
        }));
    }

    async fn unplug(&mut self) {
        let _ = std::fs::remove_file(&self.link);
        if let Some(relay) = self.relay.take() {
            relay.abort();
            let _ = relay.await;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_the_bus_could_not_carry_is_sent_once_the_adapter_is_back() {
    use drivegate::bus::handle::PortState;
    use drivegate::sim::{SimConfig, Simulator};

    tokio::time::timeout(LIMIT, async {
        let sim = Simulator::start(SimConfig::for_units([1])).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-drives");
        let mut adapter = Adapter::new(&link, sim.port_path());
        adapter.plug_in();
        let toml = format!(
            "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
             [[bus]]\nname = \"line\"\nport = \"{}\"\nresponse_timeout_ms = 200\n\
             [[bus.drive]]\nunit = 1\nname = \"conveyor\"\ngear_ratio = 3.75\n",
            link.display()
        );
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        api.activate_in("conveyor", "speed").await;
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 200, "lease_ms": 2000}),
        )
        .await
        .expect(200);

        // Unplugged: the lease runs out while the bus is down.
        adapter.unplug().await;
        let event = wait_for(
            &mut ws,
            Duration::from_secs(10),
            "the lease-expired event",
            |v| v["type"] == "lease-expired",
        )
        .await;
        assert_eq!(
            (event["ok"].as_bool(), event["retrying"].as_bool()),
            (Some(false), Some(true)),
            "{event:#}"
        );
        assert!(
            event["result"].as_str().unwrap().contains("is down"),
            "{event:#}"
        );
        assert!(matches!(bus.port_state(), PortState::Down { .. }));
        let p = api
            .post_empty("/api/v1/drives/conveyor/lease/renew")
            .await
            .expect_problem(409, "no-lease");
        let detail = p["detail"].as_str().unwrap();
        assert!(
            detail.contains("not confirmed yet") && detail.contains("is down"),
            "{detail}"
        );
        // Behind the adapter the motor still turns.
        let conveyor = sim.drive(1).unwrap();
        assert_eq!(conveyor.setpoints.speed_rpm, 200);
        assert!(conveyor.speed_rpm > 100.0, "{:.0} rpm", conveyor.speed_rpm);

        // Plugged back in: the port reopens and the stop goes out.
        adapter.plug_in();
        eventually(Duration::from_secs(15), "the zero-speed stop", || {
            (sim.drive(1)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        let event = wait_for(
            &mut ws,
            Duration::from_secs(10),
            "the lease-stop event",
            |v| v["type"] == "lease-stop",
        )
        .await;
        assert_eq!(event["stopped"], true, "{event:#}");
        let p = api
            .post_empty("/api/v1/drives/conveyor/lease/renew")
            .await
            .expect_problem(409, "no-lease");
        assert!(
            p["detail"]
                .as_str()
                .unwrap()
                .contains("confirmed by the drive"),
            "{p:#}"
        );
        d.stop().await;
        adapter.unplug().await;
    })
    .await
    .expect("test finished in time");
}

/// Behind the stream's cancelled commands and the queue allowance, the last
/// line: a leased setpoint the drive confirms after its lease has ended,
/// and its stop has gone out, has the stop sent again. Driven through the
/// control core itself, since the daemon's own faces no longer let a
/// setpoint land so late (a stream's are dropped with it; a REST one
/// expires in the queue before its lease's allowance runs out).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_confirmed_after_its_lease_ended_is_stopped_again() {
    use drivegate::bus::SourceId;
    use drivegate::control::{Caller, ControlRequest, Face, Role};
    use drivegate::drive::DriveRequest;

    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&slow_bus_with_brake_on_expiry()).await;
        let api = Api::new(d.http, None);
        let sim = d.sim();
        let bus = d.plant.buses()[0].handle.clone();
        api.activate_in("conveyor", "speed").await;
        polled_active(&bus).await;
        let control = d.control().clone();
        let target = control.target("conveyor").unwrap();

        // A lease over a session, whose setpoint waits behind a request
        // holding the wire when the session closes: the stop (the brake)
        // is queued at emergency priority and goes first.
        let (session, _notices) = control.open_session("its WebSocket closed", None);
        let caller = Caller::new(
            Face::WebSocket,
            "a stream client",
            Role::Operator,
            SourceId::new_unique(),
        )
        .in_session(Face::WebSocket, session.id());
        let blocker = hold_the_wire(&bus).await;
        let request = ControlRequest::drive(DriveRequest::Speed { rpm: 200 })
            .with_lease(Some(Duration::from_secs(60)));
        let mut pending = control.submit(&caller, target, request).await.unwrap();
        drop(session);
        // Then the setpoint lands, after the brake, and releases it ...
        pending.wait().await;
        assert!(pending.finish().is_ok());
        drop(blocker);
        // ... and the brake is applied again.
        eventually(Duration::from_secs(10), "the brake applied again", || {
            let conveyor = sim.drive(1)?;
            (conveyor.braking && conveyor.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "the conveyor standing", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
