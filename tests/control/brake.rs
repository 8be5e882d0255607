//! A brake holds, whichever face sent it and whichever face holds the
//! lease: the scenario of a vertical axis in torque mode under a lease,
//! braked by a PLC over Modbus TCP, run with the lease taken over HTTP, over
//! the WebSocket stream, and with the PLC alone. The lease ends when the
//! brake is confirmed (at once in `GET /api/v1/drives/{drive}` and on the
//! stream), and no write follows the brake: nothing releases it. A
//! deactivation from each face ends a lease the same way, and a setpoint
//! the bus let overtake by the brake has the brake applied again.

use std::time::Duration;

use crate::support::api::{Api, Ws, connect, messages_within, next_json, wait_for, ws_command};
use crate::support::bus::hold_the_wire;
use crate::support::config::ConfigBuilder;
use crate::support::modbus_tcp::{Raw, write, writes_handled};
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(60);
const LIFT: u8 = 2;
const CONFIG: u16 = 0x0002;
const IQ_REF: u16 = 0x000A;
const BRAKE: u16 = 0x0005;
const DEACTIVATE: u16 = 0x0001;
const ACTIVATE: u16 = 0x0000;
const TORQUE_MODE: u16 = 0x000C;
/// The lease of the scenario.
const LEASE_MS: u64 = 1500;

/// The lease's time and a margin pass; the brake still holds the lift, no
/// write reached the bus after it, and no lease expired.
async fn the_brake_holds(d: &TestDaemon, ws: &mut Ws, writes_after_brake: u64) {
    let bus = d.plant.buses()[0].handle.clone();
    // Absence can only be watched for: past the lease's deadline, by a
    // second more than the lease itself.
    let seen = messages_within(ws, Duration::from_millis(LEASE_MS + 1000)).await;
    assert!(
        !seen
            .iter()
            .any(|v| v["type"] == "lease-expired" || v["type"] == "lease-stop"),
        "a stop followed the brake: {seen:#?}"
    );
    assert_eq!(
        writes_handled(&bus),
        writes_after_brake,
        "a write followed the brake"
    );
    let lift = d.sim().drive(LIFT).unwrap();
    assert!(lift.braking, "the brake was released");
    assert_eq!(lift.setpoints.current_counts, 0);
}

/// The PLC's brake, confirmed by the drive's echo.
async fn plc_brake(plc: &mut Raw) {
    let brake = write(CONFIG, BRAKE);
    assert_eq!(
        plc.ask(LIFT, &brake).await,
        brake,
        "the brake was not echoed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_brake_ends_an_http_lease_and_nothing_releases_it() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        let mut ws = connect(d.http, "?drives=lift", None).await;
        assert_eq!(next_json(&mut ws, LIMIT).await["type"], "subscribed");
        api.activate_in("lift", "torque").await;
        let r = api
            .put(
                "/api/v1/drives/lift/setpoint",
                json!({"torque_a": 1.0, "lease_ms": LEASE_MS}),
            )
            .await
            .expect(200);
        assert_eq!(r["lease"]["lease_ms"], LEASE_MS);
        assert_eq!(d.sim().drive(LIFT).unwrap().setpoints.current_counts, 128);

        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        let plc_addr = plc.stream.local_addr().unwrap().to_string();
        plc_brake(&mut plc).await;
        let after = writes_handled(&bus);
        // At once, not at some later poll.
        assert!(api.get("/api/v1/drives/lift").await.expect(200)["lease"].is_null());
        let ended = wait_for(&mut ws, LIMIT, "lease-ended", |v| {
            v["type"] == "lease-ended"
        })
        .await;
        assert_eq!(ended["drive"], "lift");
        let reason = ended["reason"].as_str().unwrap();
        assert_eq!(
            reason,
            format!("the brake from {plc_addr} over Modbus TCP was confirmed")
        );
        api.post_empty("/api/v1/drives/lift/lease/renew")
            .await
            .expect_problem(409, "no-lease");
        the_brake_holds(&d, &mut ws, after).await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_brake_ends_a_websocket_lease_and_nothing_releases_it() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        api.activate_in("lift", "torque").await;
        let mut ws = connect(d.http, "", None).await;
        let reply = ws_command(
            &mut ws,
            1,
            "setpoint",
            "lift",
            json!({"torque_a": 1.0, "lease_ms": LEASE_MS}),
        )
        .await;
        assert_eq!(reply["result"]["lease"]["websocket"], true, "{reply:#}");

        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        plc_brake(&mut plc).await;
        let after = writes_handled(&bus);
        assert!(api.get("/api/v1/drives/lift").await.expect(200)["lease"].is_null());
        // The session that held the lease is told, without subscribing.
        let ended = wait_for(&mut ws, LIMIT, "lease-ended", |v| {
            v["type"] == "lease-ended"
        })
        .await;
        assert!(
            ended["reason"]
                .as_str()
                .unwrap()
                .ends_with("over Modbus TCP was confirmed"),
            "{ended:#}"
        );
        the_brake_holds(&d, &mut ws, after).await;
        // The socket closing ends no lease any more: nothing is sent.
        drop(ws);
        let mut watch = connect(d.http, "?drives=lift", None).await;
        let seen = messages_within(&mut watch, Duration::from_millis(500)).await;
        assert!(!seen.iter().any(|v| v["type"] == "lease-expired"));
        assert_eq!(writes_handled(&bus), after);
        assert!(d.sim().drive(LIFT).unwrap().braking);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_alone_brakes_and_the_brake_holds() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let bus = d.plant.buses()[0].handle.clone();
        let mut ws = connect(d.http, "?drives=lift", None).await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        for (register, value) in [(CONFIG, ACTIVATE), (CONFIG, TORQUE_MODE), (IQ_REF, 128)] {
            let pdu = write(register, value);
            assert_eq!(plc.ask(LIFT, &pdu).await, pdu);
        }
        eventually(LIMIT, "the lift pushing", || {
            (d.sim().drive(LIFT)?.current_a.abs() > 0.5).then_some(())
        })
        .await;
        plc_brake(&mut plc).await;
        let after = writes_handled(&bus);
        the_brake_holds(&d, &mut ws, after).await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_setpoint_the_brake_overtook_has_the_brake_applied_again() {
    tokio::time::timeout(LIMIT, async {
        // A second of response timeout: the wire can be held long enough
        // for both writes to be queued behind it.
        let toml = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.timing(1000, 50))
            .toml();
        let d = TestDaemon::start(&toml).await;
        let bus = d.plant.buses()[0].handle.clone();
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        for (register, value) in [(CONFIG, ACTIVATE), (CONFIG, TORQUE_MODE)] {
            let pdu = write(register, value);
            assert_eq!(plc.ask(LIFT, &pdu).await, pdu);
        }
        // The poll cache shows the drive active, so the setpoint's
        // active-check needs no read of its own (which would wait behind
        // the held wire, and hold the brake back with it).
        eventually(LIMIT, "lift polled active", || {
            bus.drive(LIFT)
                .and_then(|s| s.status)
                .is_some_and(|s| s.active())
                .then_some(())
        })
        .await;
        let before = writes_handled(&bus);
        // The PLC pipelines a setpoint and then the brake. Both wait behind
        // the held wire; the brake, at emergency priority, goes first, and
        // the setpoint lands after it: that releases the brake ...
        let blocker = hold_the_wire(&bus).await;
        plc.send(1, LIFT, &write(IQ_REF, 128)).await;
        plc.send(2, LIFT, &write(CONFIG, BRAKE)).await;
        eventually(LIMIT, "both writes queued", || {
            (bus.queue_depths()[..2].iter().sum::<usize>() == 2).then_some(())
        })
        .await;
        drop(blocker);
        let (t1, _, r1) = plc.recv().await.unwrap();
        let (t2, _, r2) = plc.recv().await.unwrap();
        assert_eq!((t1, t2), (1, 2), "replies in request order");
        assert_eq!((r1, r2), (write(IQ_REF, 128), write(CONFIG, BRAKE)));
        // ... so the brake is applied again, and holds.
        eventually(LIMIT, "the brake applied again", || {
            (writes_handled(&bus) == before + 3).then_some(())
        })
        .await;
        let lift = d.sim().drive(LIFT).unwrap();
        assert!(lift.braking, "the setpoint released the brake");
        assert_eq!(lift.setpoints.current_counts, 0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// `drive`'s lease, taken over HTTP, ends when `stop` is confirmed from a
/// face, and no stop follows.
async fn ends_the_lease(
    d: &TestDaemon,
    api: &Api,
    drive: &str,
    unit: u8,
    stop: impl AsyncFnOnce(),
) {
    let bus = d.plant.buses()[0].handle.clone();
    api.activate_in(drive, "speed").await;
    api.put(
        &format!("/api/v1/drives/{drive}/setpoint"),
        json!({"speed_rpm": 50, "lease_ms": 600}),
    )
    .await
    .expect(200);
    stop().await;
    let after = writes_handled(&bus);
    assert!(
        api.get(&format!("/api/v1/drives/{drive}"))
            .await
            .expect(200)["lease"]
            .is_null(),
        "{drive}: the lease is still there"
    );
    tokio::time::sleep(Duration::from_millis(1200)).await;
    assert_eq!(writes_handled(&bus), after, "{drive}: a stop followed");
    let view = d.sim().drive(unit).unwrap();
    assert!(
        !view.active || view.braking,
        "{drive}: neither braked nor deactivated"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_brake_or_deactivation_from_each_face_ends_a_lease() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "", None).await;
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        // Deactivation over Modbus TCP, HTTP and the stream.
        ends_the_lease(&d, &api, "conveyor", 1, async || {
            let pdu = write(CONFIG, DEACTIVATE);
            assert_eq!(plc.ask(1, &pdu).await, pdu);
        })
        .await;
        ends_the_lease(&d, &api, "turntable", 3, async || {
            api.command("turntable", "deactivate").await;
        })
        .await;
        ends_the_lease(&d, &api, "feeder", 4, async || {
            let r = ws_command(&mut ws, 1, "deactivate", "feeder", json!({})).await;
            assert_eq!(r["ok"], true, "{r:#}");
        })
        .await;
        // The brake over the stream (HTTP's and Modbus TCP's are above and
        // in the api_leases tests).
        ends_the_lease(&d, &api, "lift", 2, async || {
            let r = ws_command(&mut ws, 2, "brake", "lift", json!({})).await;
            assert_eq!(r["ok"], true, "{r:#}");
        })
        .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
