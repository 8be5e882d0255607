//! Every rule of the control core through every face, from one table: the
//! same request by the same role over HTTP, the WebSocket stream and
//! Modbus TCP gets the same decision (carried out, or refused by the same
//! rule), each face rendering it in its own terms. A rule that held for one
//! face and not another would show here as a row that differs.
//!
//! HTTP and the stream take the role of a token; Modbus TCP the role of the
//! client's network: the client connects from 127.0.0.2 (viewer),
//! 127.0.0.3 (operator), 127.0.0.1 (admin, the default allowed network) or
//! 127.0.0.4 (admin, allowed to save while moving: the face's override,
//! which HTTP and the stream give with `"force": true`).
//!
//! MQTT has one role per daemon (`[mqtt] commands`), here `operator`: the
//! operator's rows that MQTT can say (setpoints, the brake) go through it
//! too, as a host's DCMD, and its answer is the drive's
//! `command/last_result` (the viewer's refusals over MQTT:
//! `tests/mqtt/commands.rs`).

use std::net::{Ipv4Addr, SocketAddr};
use std::time::Duration;

use serde_json::{Value, json};

use crate::support::api::{Api, Ws, connect, send_json, wait_for};
use crate::support::input::{ADMIN, OPERATOR, VIEWER, config};
use crate::support::modbus_tcp::{Raw, write};
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{self, Host};
use crate::support::{TestDaemon, eventually};
use drivegate::mqtt::sparkplug_b::payload::Metric;

const LIMIT: Duration = Duration::from_secs(120);
const CONFIG: u16 = 0x0002;

/// What the core decides, whichever face asked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Decision {
    /// Carried out, confirmed by the drive.
    Done,
    /// Refused: the caller's role does not allow it.
    Role,
    /// Refused: it needs standstill and the motor turns.
    Moving,
    /// Refused: an address broadcast without the confirmation that one
    /// drive is connected.
    Address,
    /// Refused: a lease outside `[safety] lease_min_ms` to `lease_max_ms`.
    LeaseLength,
    /// Refused: a setpoint to a drive that is not active.
    NotActive,
}

impl Decision {
    /// HTTP: the status and problem type.
    fn http(self) -> (u16, &'static str) {
        match self {
            Decision::Done => (200, ""),
            Decision::Role => (403, "forbidden"),
            Decision::Moving => (409, "drive-moving"),
            Decision::Address => (409, "confirmation-required"),
            Decision::LeaseLength => (422, "out-of-range"),
            Decision::NotActive => (409, "drive-not-active"),
        }
    }

    /// Modbus TCP: the exception code (`None`: the normal reply).
    fn modbus(self) -> Option<u8> {
        match self {
            Decision::Done => None,
            Decision::Role | Decision::Address => Some(0x01),
            Decision::NotActive => Some(0x04),
            Decision::Moving => Some(0x06),
            Decision::LeaseLength => unreachable!("a Modbus TCP client asks for no lease length"),
        }
    }

    /// MQTT: what `command/last_result` says (empty: confirmed).
    fn mqtt(self) -> &'static str {
        match self {
            Decision::Done => "",
            Decision::Role => "needs the operator role",
            Decision::NotActive => "is not active",
            Decision::Moving | Decision::Address | Decision::LeaseLength => {
                unreachable!("MQTT has no such request")
            }
        }
    }
}

/// Who asks: a role, and whether the face's override of the still-check
/// is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Who {
    Viewer,
    Operator,
    Admin,
    AdminForcing,
}

impl Who {
    fn token(self) -> &'static str {
        match self {
            Who::Viewer => VIEWER,
            Who::Operator => OPERATOR,
            Who::Admin | Who::AdminForcing => ADMIN,
        }
    }

    /// The loopback address its Modbus TCP client connects from.
    fn source(self) -> Ipv4Addr {
        match self {
            Who::Viewer => Ipv4Addr::new(127, 0, 0, 2),
            Who::Operator => Ipv4Addr::new(127, 0, 0, 3),
            Who::Admin => Ipv4Addr::new(127, 0, 0, 1),
            Who::AdminForcing => Ipv4Addr::new(127, 0, 0, 4),
        }
    }
}

/// One request, as each face says it.
struct Case {
    what: &'static str,
    who: Who,
    /// Method, path and body over HTTP.
    http: (&'static str, &'static str, Value),
    /// The stream's command: op, `drive` or `bus` field, body.
    stream: (&'static str, (&'static str, &'static str), Value),
    /// Unit and PDU over Modbus TCP (`None`: the face has no such request).
    modbus: Option<(u8, Vec<u8>)>,
    /// Device and DCMD metric over MQTT (`None`: the face has no such
    /// request).
    mqtt: Option<(&'static str, Metric)>,
    expect: Decision,
}

/// The inertia message (manual 1.11) with its save flag, as one block.
fn inertia_saved(ratio: u16) -> Vec<u8> {
    let mut pdu = vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04];
    pdu.extend_from_slice(&ratio.to_be_bytes());
    pdu.extend_from_slice(&[0x00, 0x01]);
    pdu
}

fn cases() -> Vec<Case> {
    let setpoint = |who, speed: i64, drive: &'static str, unit: u8, expect| Case {
        what: "a speed setpoint without a lease",
        who,
        http: (
            "PUT",
            match drive {
                "lift" => "/api/v1/drives/lift/setpoint",
                _ => "/api/v1/drives/turntable/setpoint",
            },
            json!({"speed_rpm": speed}),
        ),
        stream: ("setpoint", ("drive", drive), json!({"speed_rpm": speed})),
        modbus: Some((unit, write(0x0006, u16::try_from(speed).unwrap()))),
        mqtt: Some((
            drive,
            sparkplug::double_metric("setpoint/speed_rpm", speed as f64),
        )),
        expect,
    };
    let save = |who, drive: &'static str, unit: u8, expect| {
        let force = who == Who::AdminForcing;
        Case {
            what: "load inertia saved to flash",
            who,
            http: (
                "PUT",
                match drive {
                    "lift" => "/api/v1/drives/lift/inertia",
                    _ => "/api/v1/drives/conveyor/inertia",
                },
                json!({"ratio": 3, "save": true, "force": force}),
            ),
            stream: (
                "inertia",
                ("drive", drive),
                json!({"ratio": 3, "save": true, "force": force}),
            ),
            modbus: Some((unit, inertia_saved(3))),
            mqtt: None,
            expect,
        }
    };
    let address = |who, expect| Case {
        what: "an address broadcast without the single-drive confirmation",
        who,
        http: ("POST", "/api/v1/buses/sim/address", json!({"address": 9})),
        stream: ("set-address", ("bus", "sim"), json!({"address": 9})),
        modbus: Some((0, write(0x0000, 9))),
        mqtt: None,
        expect,
    };
    let brake = |who, expect| Case {
        what: "the emergency brake",
        who,
        http: ("POST", "/api/v1/drives/lift/commands/brake", Value::Null),
        stream: ("brake", ("drive", "lift"), json!({})),
        modbus: Some((2, write(CONFIG, 5))),
        mqtt: Some(("lift", sparkplug::bool_metric("command/brake", true))),
        expect,
    };
    vec![
        // Roles, from the meaning of each write.
        setpoint(Who::Viewer, 0, "lift", 2, Decision::Role),
        setpoint(Who::Operator, 0, "lift", 2, Decision::Done),
        save(Who::Viewer, "lift", 2, Decision::Role),
        save(Who::Operator, "lift", 2, Decision::Role),
        save(Who::Admin, "lift", 2, Decision::Done),
        address(Who::Operator, Decision::Role),
        // A save while the motor turns, and the face's override.
        save(Who::Admin, "conveyor", 1, Decision::Moving),
        save(Who::AdminForcing, "conveyor", 1, Decision::Done),
        // One address rule, on a bus of four drives.
        address(Who::Admin, Decision::Address),
        // Lease bounds: only the faces that ask for a lease length.
        Case {
            what: "a setpoint with a lease shorter than lease_min_ms",
            who: Who::Operator,
            http: (
                "PUT",
                "/api/v1/drives/lift/setpoint",
                json!({"speed_rpm": 0, "lease_ms": 5}),
            ),
            stream: (
                "setpoint",
                ("drive", "lift"),
                json!({"speed_rpm": 0, "lease_ms": 5}),
            ),
            modbus: None,
            mqtt: None,
            expect: Decision::LeaseLength,
        },
        // A setpoint only to an active drive.
        setpoint(Who::Operator, 10, "turntable", 3, Decision::NotActive),
        // The brake is operator work.
        brake(Who::Viewer, Decision::Role),
        brake(Who::Operator, Decision::Done),
    ]
}

/// A Modbus TCP client connecting from `source`.
async fn modbus_from(addr: SocketAddr, source: Ipv4Addr) -> Raw {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(SocketAddr::from((source, 0))).unwrap();
    let stream = tokio::time::timeout(Duration::from_secs(10), socket.connect(addr))
        .await
        .expect("connect in time")
        .expect("connect");
    Raw::from_stream(stream)
}

/// A stream command with `field` (`drive` or `bus`), and its reply.
async fn stream_command(ws: &mut Ws, id: u64, case: &Case) -> Value {
    let (op, (field, name), body) = &case.stream;
    let mut message = json!({"type": "command", "id": id, "op": op, "body": body});
    message[*field] = json!(name);
    send_json(ws, message).await;
    wait_for(ws, Duration::from_secs(20), "the reply", |v| {
        v["type"] == "reply" && v["id"] == id
    })
    .await
}

async fn http_request(api: &Api, case: &Case) -> crate::support::api::Reply {
    let (method, path, body) = &case.http;
    match (*method, body) {
        ("PUT", body) => api.put(path, body.clone()).await,
        ("POST", Value::Null) => api.post_empty(path).await,
        ("POST", body) => api.post(path, body.clone()).await,
        (other, _) => panic!("no {other} in the table"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_rule_decides_the_same_through_every_face() {
    tokio::time::timeout(LIMIT, async {
        let networks = "broadcast_reply = true\n\
            [[modbus_tcp.clients]]\nnetwork = \"127.0.0.2/32\"\nrole = \"viewer\"\n\
            [[modbus_tcp.clients]]\nnetwork = \"127.0.0.3/32\"\nrole = \"operator\"\n\
            [[modbus_tcp.clients]]\nnetwork = \"127.0.0.4/32\"\nrole = \"admin\"\nallow_saves_while_moving = true\n";
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "every-face-host", None).await;
        let mqtt = format!(
            "[mqtt]\nbroker = \"{}\"\ngroup_id = \"plant\"\nnode_id = \"gw1\"\ncommands = \"operator\"\nunauthenticated_commands = true\n",
            broker.url()
        );
        let d = TestDaemon::start(&config("", networks, true, &mqtt)).await;
        host.next(LIMIT, "the node's births", |m| m.is("DBIRTH", Some("feeder")))
            .await;
        let admin = Api::new(d.http, Some(ADMIN));
        let tcp = d.modbus_tcp.unwrap();

        // The conveyor turns, the lift is active and stands, the turntable
        // is not active.
        admin.activate_in("conveyor", "speed").await;
        admin
            .put(
                "/api/v1/drives/conveyor/setpoint",
                json!({"speed_rpm": 200}),
            )
            .await
            .expect(200);
        admin.activate_in("lift", "speed").await;
        admin.command("turntable", "deactivate").await;
        eventually(LIMIT, "the conveyor turning, and polled so", || {
            let (_, bus) = d.plant.drive("conveyor").ok()?;
            (d.sim().drive(1)?.speed_rpm > 50.0 && bus.drive(1)?.status?.speed_rpm != 0)
                .then_some(())
        })
        .await;
        eventually(LIMIT, "the lift active in the poll", || {
            let (_, bus) = d.plant.drive("lift").ok()?;
            bus.drive(2)?.status?.active().then_some(())
        })
        .await;

        let mut streams = Vec::new();
        for who in [Who::Viewer, Who::Operator, Who::Admin] {
            streams.push((who, connect(d.http, "", Some(who.token())).await));
        }
        let mut id = 0;
        let mut over_mqtt = 0;
        for case in cases() {
            let label = format!("{} by {:?}", case.what, case.who);
            let (status, kind) = case.expect.http();

            // HTTP.
            let api = Api::new(d.http, Some(case.who.token()));
            let r = http_request(&api, &case).await;
            assert_eq!(
                (r.status, r.problem()),
                (status, kind),
                "HTTP: {label}: {:#}",
                r.body
            );

            // The stream, with the same token.
            id += 1;
            let ws = &mut streams
                .iter_mut()
                .find(|(w, _)| w.token() == case.who.token())
                .unwrap()
                .1;
            let reply = stream_command(ws, id, &case).await;
            assert_eq!(
                reply["ok"],
                case.expect == Decision::Done,
                "stream: {label}: {reply:#}"
            );
            if case.expect != Decision::Done {
                assert_eq!(
                    reply["problem"]["type"],
                    format!("urn:drivegate:problem:{kind}"),
                    "stream: {label}: {reply:#}"
                );
            }

            // Modbus TCP, from the network of the same role.
            if let Some((unit, pdu)) = &case.modbus {
                let mut plc = modbus_from(tcp, case.who.source()).await;
                let answer = plc.ask(*unit, pdu).await;
                match case.expect.modbus() {
                    Some(code) => assert_eq!(
                        answer,
                        [pdu[0] | 0x80, code],
                        "Modbus TCP: {label}"
                    ),
                    // 0x06 echoes the request; 0x10 answers address and count.
                    None => assert_eq!(answer.as_slice(), &pdu[..5], "Modbus TCP: {label}"),
                }
            }

            // MQTT, whose role is the operator's.
            if let Some((device, metric)) = &case.mqtt
                && case.who == Who::Operator
            {
                over_mqtt += 1;
                host.dcmd("plant", "gw1", device, vec![metric.clone()]).await;
                let m = host
                    .next(Duration::from_secs(20), "the command's result", |m| {
                        m.is("DDATA", Some(device)) && m.metric("command/last_result").is_some()
                    })
                    .await;
                let Some(drivegate::mqtt::metric::Value::Text(words)) =
                    m.value("command/last_result")
                else {
                    panic!("MQTT: {label}: {:?}", m.names());
                };
                match case.expect.mqtt() {
                    "" => assert_eq!(words, "", "MQTT: {label}"),
                    part => assert!(words.contains(part), "MQTT: {label}: {words}"),
                }
            }
        }

        assert_eq!(over_mqtt, 3, "the operator's setpoints and brake over MQTT");

        // What the table did to the drives: a setpoint without a lease left
        // none; the forced saves (one per face) reached flash while the
        // conveyor turned; nothing moved the turntable; no drive took
        // address 9.
        assert!(
            admin.get("/api/v1/drives/lift").await.expect(200)["lease"].is_null(),
            "a setpoint without a lease took one"
        );
        let conveyor = d.sim().drive(1).unwrap();
        assert_eq!(conveyor.saves_while_moving, 3);
        assert_eq!(conveyor.flash.settings.inertia_ratio, 3);
        assert_eq!(d.sim().drive(3).unwrap().setpoints.speed_rpm, 0);
        assert!(d.sim().drive(9).is_none());
        assert!(d.sim().drive(2).unwrap().braking);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
