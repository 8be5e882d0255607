//! Every rule of the control core through every face, from one table: the
//! same request by the same role over HTTP, the WebSocket stream and
//! Modbus TCP gets the same decision (carried out, or refused by the same
//! rule), each face rendering it in its own terms. A rule that held for one
//! face and not another would show here as a row that differs.
//!
//! Over Modbus TCP each write goes in every framing the specification
//! allows for it: as the manual's 0x06 or 0x10, as a mask write (0x16, AND
//! mask 0) and as the write of a read/write multiple (0x17); each must come
//! out the same. A second table sends every function code the Modbus
//! application protocol defines, from each role, and checks on the
//! simulator's own counters what reached the wire.
//!
//! HTTP and the stream take the role of a token; Modbus TCP the role of the
//! client's network: the client connects from 127.0.0.2 (viewer),
//! 127.0.0.3 (operator), 127.0.0.1 (admin, the default allowed network) or
//! 127.0.0.4 (admin, allowed to save while moving: the face's override,
//! which HTTP and the stream give with `"force": true`).
//!
//! OPC UA signs in with the role's token (user name = the token's name,
//! password = the token): setpoints as writes of `SpeedSetpoint`, the
//! brake as `Brake()`, a save as `Settings.Save()` (it has no override of
//! the still-check, nor an address broadcast); its answer is the status
//! code.
//!
//! MQTT has one role per daemon (`[mqtt] commands`), here `operator`: the
//! operator's rows that MQTT can say (setpoints, the brake) go through it
//! too, as a host's DCMD, and its answer is the drive's
//! `command/last_result` (the viewer's refusals over MQTT:
//! `tests/mqtt/commands.rs`).

use std::net::{Ipv4Addr, SocketAddr};
use std::time::Duration;

use serde_json::{Value, json};

use super::opcua::Table;
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

    /// OPC UA: the status code of the write or the method call.
    fn opcua(self) -> &'static str {
        match self {
            Decision::Done => "Good",
            Decision::Role => "BadUserAccessDenied",
            Decision::Moving | Decision::NotActive => "BadInvalidState",
            Decision::Address | Decision::LeaseLength => {
                unreachable!("OPC UA has no such request")
            }
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

    /// Its OPC UA user name (its token's name; the password is the token).
    fn user(self) -> &'static str {
        match self {
            Who::Viewer => "dashboard",
            Who::Operator => "scada",
            Who::Admin | Who::AdminForcing => "commissioning",
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
    /// Unit and PDU over Modbus TCP in the manual's framing (`None`: the
    /// face has no such request); sent in every framing of [`framings`].
    modbus: Option<(u8, Vec<u8>)>,
    /// Device and DCMD metric over MQTT (`None`: the face has no such
    /// request).
    mqtt: Option<(&'static str, Metric)>,
    /// The write or method call over OPC UA (`None`: the face has no such
    /// request).
    opcua: Option<Value>,
    expect: Decision,
}

/// The inertia message (manual 1.11) with its save flag, as one block.
fn inertia_saved(ratio: u16) -> Vec<u8> {
    let mut pdu = vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04];
    pdu.extend_from_slice(&ratio.to_be_bytes());
    pdu.extend_from_slice(&[0x00, 0x01]);
    pdu
}

/// Every framing of the write `pdu` (a 0x06 or a 0x10 of the manual) that
/// the specification has: itself; a 0x06 as a mask write with an AND mask
/// of 0; to one unit, the write of a read/write multiple that reads the
/// status block after it (unit 0 cannot be sent a read).
fn framings(unit: u8, pdu: &[u8]) -> Vec<Vec<u8>> {
    let mut out = vec![pdu.to_vec()];
    if pdu[0] == 0x06 {
        out.push(vec![0x16, pdu[1], pdu[2], 0, 0, pdu[3], pdu[4]]);
    }
    if unit != 0 {
        let mut rw = vec![0x17, 0x00, 0xC0, 0x00, 0x07];
        if pdu[0] == 0x06 {
            rw.extend_from_slice(&[pdu[1], pdu[2], 0x00, 0x01, 0x02, pdu[3], pdu[4]]);
        } else {
            rw.extend_from_slice(&pdu[1..]);
        }
        out.push(rw);
    }
    out
}

/// The reply a write in framing `pdu` gets when it is carried out.
fn done(pdu: &[u8]) -> Vec<u8> {
    match pdu[0] {
        // 0x06 and 0x16 echo the request; 0x10 answers address and count.
        0x06 | 0x16 => pdu.to_vec(),
        0x10 => pdu[..5].to_vec(),
        // 0x17: the status block read after the write.
        _ => vec![0x17, 14],
    }
}

/// A save of the load inertia to flash by `who` on `drive` (`unit`).
fn save(who: Who, drive: &'static str, unit: u8, expect: Decision) -> Case {
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
        // No override of the still-check over OPC UA.
        opcua: (!force).then(|| {
            json!({"op": "call", "object": format!("{drive}/Settings"), "method": format!("{drive}/Settings/Save")})
        }),
        expect,
    }
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
        opcua: Some(
            json!({"op": "write", "path": format!("{drive}/SpeedSetpoint"), "value": speed}),
        ),
        expect,
    };
    let address = |who, expect| Case {
        what: "an address broadcast without the single-drive confirmation",
        who,
        http: ("POST", "/api/v1/buses/sim/address", json!({"address": 9})),
        stream: ("set-address", ("bus", "sim"), json!({"address": 9})),
        modbus: Some((0, write(0x0000, 9))),
        mqtt: None,
        opcua: None,
        expect,
    };
    let brake = |who, expect| Case {
        what: "the emergency brake",
        who,
        http: ("POST", "/api/v1/drives/lift/commands/brake", Value::Null),
        stream: ("brake", ("drive", "lift"), json!({})),
        modbus: Some((2, write(CONFIG, 5))),
        mqtt: Some(("lift", sparkplug::bool_metric("command/brake", true))),
        opcua: Some(json!({"op": "call", "object": "lift", "method": "lift/Brake"})),
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
            opcua: None,
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

/// `case` over Modbus TCP, from the network of its role, in every framing
/// of its write `manual` to `unit`.
async fn modbus_case(tcp: SocketAddr, case: &Case, unit: u8, manual: &[u8], label: &str) {
    let mut plc = modbus_from(tcp, case.who.source()).await;
    for pdu in framings(unit, manual) {
        let answer = plc.ask(unit, &pdu).await;
        let label = format!("{label} as 0x{:02X}", pdu[0]);
        match case.expect.modbus() {
            Some(code) => assert_eq!(answer, [pdu[0] | 0x80, code], "Modbus TCP: {label}"),
            None => {
                let want = done(&pdu);
                assert_eq!(&answer[..want.len()], want, "Modbus TCP: {label}")
            }
        }
    }
}

/// `case` over OPC UA, if the face can say it; whether it could.
async fn opcua_case(ua: &mut Table, case: &Case, label: &str) -> bool {
    let Some(request) = &case.opcua else {
        return false;
    };
    let mut request = request.clone();
    request["user"] = json!(case.who.user());
    request["password"] = json!(case.who.token());
    let status = ua.ask(request).await;
    assert_eq!(status, case.expect.opcua(), "OPC UA: {label}");
    true
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
        let dir = tempfile::tempdir().unwrap();
        let opcua = format!("[opcua]\n{}\n", super::opcua::section(dir.path()));
        let d = TestDaemon::start(&config("", networks, true, &format!("{mqtt}{opcua}"))).await;
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
        let addr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        let mut ua = Table::start(&format!("opc.tcp://{addr}/")).await;
        let mut id = 0;
        let mut over_mqtt = 0;
        let mut over_opcua = 0;
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

            // Modbus TCP, from the network of the same role, in every framing.
            if let Some((unit, manual)) = &case.modbus {
                modbus_case(tcp, &case, *unit, manual, &label).await;
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

            // OPC UA, signed in as the role's token (name and token).
            over_opcua += usize::from(opcua_case(&mut ua, &case, &label).await);
        }

        assert_eq!(over_mqtt, 3, "the operator's setpoints and brake over MQTT");
        assert_eq!(over_opcua, 9, "every row OPC UA can say");

        what_the_table_did(&d, &admin).await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// What the table did to the drives, whichever face sent it.
async fn what_the_table_did(d: &TestDaemon, admin: &Api) {
    // What the table did to the drives: a setpoint without a lease left
    // none; the forced saves (HTTP, the stream, Modbus TCP's 0x10 and
    // 0x17) reached flash while the conveyor turned; nothing moved the
    // turntable; no drive took address 9.
    assert!(
        admin.get("/api/v1/drives/lift").await.expect(200)["lease"].is_null(),
        "a setpoint without a lease took one"
    );
    let conveyor = d.sim().drive(1).unwrap();
    assert_eq!(conveyor.saves_while_moving, 4);
    assert_eq!(conveyor.flash.settings.inertia_ratio, 3);
    assert_eq!(d.sim().drive(3).unwrap().setpoints.speed_rpm, 0);
    assert!(d.sim().drive(9).is_none());
    assert!(d.sim().drive(2).unwrap().braking);
}

/// What becomes of a function code, whoever sends it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fate {
    /// A read: passed to the drive for every role (the drive has 0x03
    /// only, and answers the others with its own 0x01, on the wire).
    Read,
    /// A register write the core decodes, here a setting (STALLED_DURATION_MS):
    /// an admin's work, carried out; 0x01 for the others, off the wire.
    Setting,
    /// What the core cannot decode: 0x01 for every role, off the wire.
    NotDecoded,
    /// Listed in `raw_functions`: an admin's goes to the drive unchecked
    /// (which answers 0x01 on the wire); 0x01 for the others, off the wire.
    Raw,
}

/// Every function code of the Modbus application protocol V1.1b3 (and the
/// sub-functions of 0x08 and the MEI types of 0x2B), with its fate. A
/// setting's value is `STALL` + its row, so each write can be told on the
/// drive.
fn function_codes() -> Vec<(String, Vec<u8>, Fate)> {
    let mut rows: Vec<(String, Vec<u8>, Fate)> = vec![
        (
            "0x01".into(),
            vec![0x01, 0x00, 0x00, 0x00, 0x08],
            Fate::Read,
        ),
        (
            "0x02".into(),
            vec![0x02, 0x00, 0x00, 0x00, 0x08],
            Fate::Read,
        ),
        (
            "0x03".into(),
            vec![0x03, 0x00, 0xC0, 0x00, 0x07],
            Fate::Read,
        ),
        (
            "0x04".into(),
            vec![0x04, 0x00, 0xC0, 0x00, 0x07],
            Fate::Read,
        ),
        (
            "0x05".into(),
            vec![0x05, 0x00, 0x01, 0xFF, 0x00],
            Fate::NotDecoded,
        ),
        ("0x06".into(), vec![0x06, 0x00, 0x0E], Fate::Setting),
        ("0x07".into(), vec![0x07], Fate::Read),
        (
            "0x08/0000".into(),
            vec![0x08, 0x00, 0x00, 0xA5, 0x37],
            Fate::Read,
        ),
        ("0x0B".into(), vec![0x0B], Fate::Read),
        ("0x0C".into(), vec![0x0C], Fate::Read),
        (
            "0x0F".into(),
            vec![0x0F, 0x00, 0x00, 0x00, 0x0A, 0x02, 0xFF, 0x03],
            Fate::NotDecoded,
        ),
        (
            "0x10".into(),
            vec![0x10, 0x00, 0x0E, 0x00, 0x01, 0x02],
            Fate::Setting,
        ),
        ("0x11".into(), vec![0x11], Fate::Read),
        (
            "0x14".into(),
            vec![0x14, 0x07, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02],
            Fate::Read,
        ),
        (
            "0x15".into(),
            vec![
                0x15, 0x09, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x01, 0x06, 0xAF,
            ],
            Fate::NotDecoded,
        ),
        (
            "0x16".into(),
            vec![0x16, 0x00, 0x0E, 0x00, 0x00],
            Fate::Setting,
        ),
        (
            "0x16 keeping bits".into(),
            vec![0x16, 0x00, 0x0E, 0xFF, 0x00, 0x00, 0x05],
            Fate::NotDecoded,
        ),
        (
            "0x17".into(),
            vec![0x17, 0x00, 0x0E, 0x00, 0x01, 0x00, 0x0E, 0x00, 0x01, 0x02],
            Fate::Setting,
        ),
        ("0x18".into(), vec![0x18, 0x04, 0xDE], Fate::Read),
        ("0x2B/0E".into(), vec![0x2B, 0x0E, 0x01, 0x00], Fate::Read),
        (
            "0x2B/0D".into(),
            vec![0x2B, 0x0D, 0x00, 0x01],
            Fate::NotDecoded,
        ),
        ("0x41 listed".into(), vec![0x41, 0x12, 0x34], Fate::Raw),
    ];
    rows.extend(diagnostics_and_others());
    rows
}

/// The rows of diagnostics' sub-functions (those that return data are
/// reads; restart, delimiter, listen only, the clears and the reserved
/// ones are not), the user-defined codes (but 0x41, listed), the reserved
/// ones, and codes the specification does not define.
fn diagnostics_and_others() -> Vec<(String, Vec<u8>, Fate)> {
    let diag = |sub: u16| {
        let [hi, lo] = sub.to_be_bytes();
        vec![0x08, hi, lo, 0x00, 0x00]
    };
    let mut rows = Vec::new();
    // Diagnostics: the sub-functions that return data are reads; restart,
    // delimiter, listen only, the clears and the reserved ones are not.
    for sub in [0x02, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12] {
        rows.push((format!("0x08/{sub:04X}"), diag(sub), Fate::Read));
    }
    for sub in [0x01, 0x03, 0x04, 0x05, 0x0A, 0x13, 0x14, 0x15] {
        rows.push((format!("0x08/{sub:04X}"), diag(sub), Fate::NotDecoded));
    }
    // User-defined (but 0x41, listed), reserved, and codes the
    // specification does not define.
    let others = (0x42..=0x48)
        .chain(0x64..=0x6E)
        .chain([
            0x09, 0x0A, 0x0D, 0x0E, 0x29, 0x2A, 0x5A, 0x5B, 0x7D, 0x7E, 0x7F,
        ])
        .chain([0x12, 0x19, 0x20, 0x30, 0x50, 0x7B]);
    for code in others {
        rows.push((
            format!("0x{code:02X}"),
            vec![code, 0x00, 0x01],
            Fate::NotDecoded,
        ));
    }
    rows
}

/// STALLED_DURATION_MS's value of row `row`: distinct, in range.
fn stall_value(row: usize, who: Who) -> u16 {
    1000 + 10 * row as u16 + who as u16
}

/// `pdu` of a setting row completed with `value` (for a mask write, its
/// OR mask).
fn with_value(pdu: &[u8], value: u16) -> Vec<u8> {
    let mut pdu = pdu.to_vec();
    pdu.extend_from_slice(&value.to_be_bytes());
    pdu
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_function_code_of_the_specification_is_decided_by_the_core() {
    tokio::time::timeout(LIMIT, async {
        let networks = "raw_functions = [0x41]\n\
            [[modbus_tcp.clients]]\nnetwork = \"127.0.0.2/32\"\nrole = \"viewer\"\n\
            [[modbus_tcp.clients]]\nnetwork = \"127.0.0.3/32\"\nrole = \"operator\"\n";
        let d = TestDaemon::start(&config("", networks, false, "")).await;
        let tcp = d.modbus_tcp.unwrap();
        const LIFT: u8 = 2;
        // The simulator's own count of the exceptions it answered: every
        // function but 0x03, 0x06 and 0x10 that reaches a drive is one.
        let on_wire = || d.sim().stats().exceptions;
        let mut checked = 0;
        for who in [Who::Viewer, Who::Operator, Who::Admin] {
            let mut plc = modbus_from(tcp, who.source()).await;
            for (row, (name, pdu, fate)) in function_codes().into_iter().enumerate() {
                let label = format!("{name} by {who:?}");
                let value = stall_value(row, who);
                let pdu = match fate {
                    Fate::Setting => with_value(&pdu, value),
                    _ => pdu,
                };
                let before = on_wire();
                let answer = plc.ask(LIFT, &pdu).await;
                let refused = [pdu[0] | 0x80, 0x01];
                match (fate, who) {
                    (Fate::Read, _) if pdu[0] == 0x03 => {
                        assert_eq!(answer[..2], [0x03, 14], "{label}");
                        assert_eq!(on_wire(), before, "{label}");
                    }
                    // The drive's own 0x01, on the wire.
                    (Fate::Read, _) | (Fate::Raw, Who::Admin) => {
                        assert_eq!(answer, refused, "{label}");
                        assert_eq!(on_wire(), before + 1, "{label}: on the wire");
                    }
                    (Fate::Setting, Who::Admin) => {
                        assert_eq!(answer[0], pdu[0], "{label}: {answer:02X?}");
                        let written = d.sim().drive(LIFT).unwrap().settings.stall_duration_ms;
                        assert_eq!(written, value, "{label}: the drive took it");
                    }
                    // Refused by the core, before the wire.
                    _ => {
                        assert_eq!(answer, refused, "{label}");
                        assert_eq!(on_wire(), before, "{label}: off the wire");
                        let stall = d.sim().drive(LIFT).unwrap().settings.stall_duration_ms;
                        assert_ne!(stall, value, "{label}: the drive took it");
                    }
                }
                checked += 1;
            }
        }
        assert_eq!(checked, 3 * function_codes().len());
        // Nothing the core refused was sent as a broadcast either.
        let mut admin = modbus_from(tcp, Who::Admin.source()).await;
        for pdu in [
            vec![0x05, 0x00, 0x01, 0xFF, 0x00],
            vec![0x41, 0x12, 0x34],
            vec![0x08, 0x00, 0x04, 0x00, 0x00],
        ] {
            admin.send(9, 0, &pdu).await;
        }
        assert_eq!(
            registers_of(&admin.ask(LIFT, &[0x03, 0x00, 0xC0, 0x00, 0x01]).await),
            1
        );
        assert_eq!(d.sim().stats().broadcasts, 0);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// How many registers a 0x03 reply carries.
fn registers_of(reply: &[u8]) -> usize {
    assert_eq!(reply[0], 0x03, "{reply:02X?}");
    usize::from(reply[1]) / 2
}
