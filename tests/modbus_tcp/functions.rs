//! Function codes the drive's manual does not use, sent as an attacker
//! would, with raw MBAP frames and with pymodbus's own requests: a mask
//! write (0x16) and a read/write multiple (0x17) are decided by the control
//! core as the writes they make (a factory reset refused while the motor
//! turns, an address broadcast refused, a setpoint taking the network's
//! communication-loss lease, the audit line, the bus monitor's source),
//! and what the core cannot decode (coils, files, diagnostics that restart
//! or silence a device, vendor codes) never reaches the wire unless
//! `raw_functions` lists it for an admin.
//!
//! The wire is checked on the simulator's own counters: a drive answers
//! every function but 0x03, 0x06 and 0x10 with an exception, and a
//! broadcast is counted, so a request that reached it shows there whatever
//! the daemon's own figures say. The first test runs the simulator as a
//! process of its own (`drivegate sim --link`) on a pty, as a bus of real
//! drives would be.

use std::process::Stdio;
use std::time::Duration;

use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, BufReader, Lines};
use tokio::process::{Child, ChildStdout, Command};

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::modbus_tcp::{Raw, pymodbus, read, registers};
use crate::support::{TestDaemon, bounded, eventually};

const LIMIT: Duration = Duration::from_secs(120);
const CONFIG: [u8; 2] = [0x00, 0x02];
const INERTIA: u16 = 0x0024;
const FRAMES: &str = "/api/v1/buses/sim/monitor/frames";

/// `drivegate sim` in a process of its own, on a pty behind a link.
struct ExternalSim {
    child: Child,
    stdout: Lines<BufReader<ChildStdout>>,
    link: std::path::PathBuf,
    _dir: tempfile::TempDir,
}

impl ExternalSim {
    async fn start(units: &str) -> ExternalSim {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("rs485");
        let mut child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["sim", "--units", units, "--link"])
            .arg(&link)
            .stdout(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let mut stdout = BufReader::new(child.stdout.take().unwrap()).lines();
        tokio::time::timeout(Duration::from_secs(10), stdout.next_line())
            .await
            .expect("the simulator prints its pty within 10 s")
            .unwrap()
            .expect("the pty line");
        ExternalSim {
            child,
            stdout,
            link,
            _dir: dir,
        }
    }

    /// Stops it (SIGTERM); the counters it prints on exit.
    async fn counters(mut self) -> String {
        let pid = self.child.id().unwrap().to_string();
        let killed = std::process::Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap();
        assert!(killed.success());
        tokio::time::timeout(Duration::from_secs(10), self.child.wait())
            .await
            .expect("the simulator stops within 10 s of SIGTERM")
            .unwrap();
        self.stdout
            .next_line()
            .await
            .unwrap()
            .expect("its counters")
    }
}

/// A counter of the simulator's exit line (`requests=12 replies=12 ...`).
fn counter(line: &str, name: &str) -> u64 {
    line.split_whitespace()
        .find_map(|kv| kv.strip_prefix(&format!("{name}=")))
        .unwrap_or_else(|| panic!("no {name} in {line}"))
        .parse()
        .unwrap()
}

/// A mask write of `register`.
fn mask_write(register: [u8; 2], and: u16, or: u16) -> Vec<u8> {
    let mut pdu = vec![0x16, register[0], register[1]];
    pdu.extend_from_slice(&and.to_be_bytes());
    pdu.extend_from_slice(&or.to_be_bytes());
    pdu
}

/// A read/write multiple: reads `count` at `read_at`, writes `values` at
/// `write_at`.
fn read_write(read_at: u16, count: u16, write_at: u16, values: &[u16]) -> Vec<u8> {
    let mut pdu = vec![0x17];
    pdu.extend_from_slice(&read_at.to_be_bytes());
    pdu.extend_from_slice(&count.to_be_bytes());
    pdu.extend_from_slice(&write_at.to_be_bytes());
    pdu.extend_from_slice(&(values.len() as u16).to_be_bytes());
    pdu.push((values.len() * 2) as u8);
    for v in values {
        pdu.extend_from_slice(&v.to_be_bytes());
    }
    pdu
}

/// Writes an inertia ratio of `ratio`, not saved (0x10 at 0x0024).
fn inertia(ratio: u16) -> Vec<u8> {
    let mut pdu = vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04];
    pdu.extend_from_slice(&ratio.to_be_bytes());
    pdu.extend_from_slice(&[0, 0]);
    pdu
}

/// pymodbus's own requests at `tcp`: the factory reset and what cannot be
/// decoded, to the turning conveyor (unit 1), refused; the same framings
/// at work on the standing lift (unit 2), and a read the drive lacks,
/// which reaches it (the counters' control).
async fn pymodbus_attacks(tcp: std::net::SocketAddr) {
    // pymodbus's own requests.
    let names = [
        "mask-write-reset",
        "read-write-reset",
        "mask-write-keeping-bits",
        "write-coil",
        "write-coils",
        "write-file-record",
        "diag-restart",
        "diag-listen-only",
        "diag-clear-counters",
    ];
    let mut args = vec!["calls", "1"];
    args.extend(names);
    let out = pymodbus(tcp, &args).await;
    let expected = json!({
        "mask-write-reset": {"exception": 6},
        "read-write-reset": {"exception": 6},
        "mask-write-keeping-bits": {"exception": 1},
        "write-coil": {"exception": 1},
        "write-coils": {"exception": 1},
        "write-file-record": {"exception": 1},
        "diag-restart": {"exception": 1},
        "diag-listen-only": {"exception": 1},
        "diag-clear-counters": {"exception": 1},
    });
    assert_eq!(out, expected, "{out:#}");

    // On the lift, standing, the same framings do their work; a read
    // the drive lacks reaches it (and is its exception: the counter's
    // control).
    let out = pymodbus(
        tcp,
        &[
            "calls",
            "2",
            "read-write-inertia-5",
            "mask-write-inertia-9",
            "read-input-registers",
        ],
    )
    .await;
    assert_eq!(
        out["read-write-inertia-5"],
        json!({"ok": true, "registers": [5]}),
        "{out:#}"
    );
    assert_eq!(out["mask-write-inertia-9"]["ok"], true, "{out:#}");
    assert_eq!(
        out["read-input-registers"],
        json!({"exception": 1}),
        "{out:#}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_turning_drive_cannot_be_reset_or_readdressed_by_another_function_code() {
    bounded(LIMIT, async {
        let sim = ExternalSim::start("1-2").await;
        // No stop at the end: a zero speed to the inactive lift would be
        // its exception on the counters.
        let toml = ConfigBuilder::new()
            .modbus_tcp("broadcast_reply = true")
            .section("safety", "on_shutdown = \"none\"")
            .bus("sim", |b| {
                b.port(&sim.link.to_string_lossy())
                    .drive(1, "conveyor")
                    .drive(2, "lift")
            })
            .toml();
        let d = TestDaemon::start(&toml).await;
        let tcp = d.modbus_tcp.unwrap();
        let admin = Api::new(d.http, None);
        // The conveyor turns at 200 rpm, its inertia ratio 7 in RAM (a
        // factory reset would put back the factory's).
        let mut c = Raw::connect(tcp).await;
        assert_eq!(c.ask(1, &inertia(7)).await, [0x10, 0x00, 0x24, 0x00, 0x02]);
        admin.activate_in("conveyor", "speed").await;
        admin
            .put(
                "/api/v1/drives/conveyor/setpoint",
                json!({"speed_rpm": 200}),
            )
            .await
            .expect(200);
        let (_, bus) = d.plant.drive("conveyor").unwrap();
        eventually(LIMIT, "the conveyor turning, and polled so", || {
            (bus.drive(1)?.status?.speed_rpm > 100).then_some(())
        })
        .await;

        // Raw frames, as the loopback admin: the factory reset and the
        // address, framed as a mask write and a read/write multiple.
        let status_and_reset = read_write(0x00C0, 7, 0x0002, &[6]);
        assert_eq!(c.ask(1, &status_and_reset).await, [0x97, 0x06], "moving");
        assert_eq!(c.ask(1, &mask_write(CONFIG, 0, 6)).await, [0x96, 0x06]);
        assert_eq!(
            c.ask(1, &mask_write(CONFIG, 0xFFF0, 6)).await,
            [0x96, 0x01],
            "a mask keeping bits of a value nobody read"
        );
        assert_eq!(c.ask(0, &mask_write([0, 0], 0, 9)).await, [0x96, 0x01]);
        assert_eq!(c.ask(0, &mask_write([0, 0], 0xFF00, 9)).await, [0x96, 0x01]);
        // What the core cannot decode, for the admin too.
        for pdu in [
            vec![0x05, 0x00, 0x01, 0xFF, 0x00],
            vec![0x0F, 0x00, 0x00, 0x00, 0x0A, 0x02, 0xFF, 0x03],
            vec![
                0x15, 0x09, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x01, 0x06, 0xAF,
            ],
            vec![0x08, 0x00, 0x04, 0x00, 0x00],
            vec![0x08, 0x00, 0x01, 0x00, 0x00],
            vec![0x41, 0x00, 0x02, 0x00, 0x06],
            vec![0x64],
            vec![0x2B, 0x0D, 0x00, 0x01],
        ] {
            assert_eq!(c.ask(1, &pdu).await, [pdu[0] | 0x80, 0x01], "{pdu:02X?}");
        }

        pymodbus_attacks(tcp).await;
        assert_eq!(registers(&c.ask(2, &read(INERTIA, 1)).await), [9]);
        // The conveyor still turns, with its inertia of 7: no reset reached it.
        assert_eq!(registers(&c.ask(1, &read(INERTIA, 1)).await), [7]);
        assert!(bus.drive(1).unwrap().status.unwrap().speed_rpm > 100);
        admin
            .put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": 0}))
            .await
            .expect(200);
        d.stop().await;

        // The simulator saw one exception (the read it lacks) and no
        // broadcast: none of the refused requests reached its wire.
        let counters = sim.counters().await;
        assert_eq!(counter(&counters, "exceptions"), 1, "{counters}");
        assert_eq!(counter(&counters, "broadcasts"), 0, "{counters}");
        assert_eq!(counter(&counters, "bad_crc_requests"), 0, "{counters}");
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_write_multiple_setpoint_is_a_setpoint_for_every_rule() {
    capture_logs();
    bounded(LIMIT, async {
        // Loopback is an operator network with a communication-loss time.
        let toml = ConfigBuilder::four_drives()
            .modbus_tcp(
                "allowed_networks = []\n[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"\ncomm_loss_ms = 2000",
            )
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        let peer = plc.stream.local_addr().unwrap().to_string();
        // Activate and speed mode, as mask writes of CONFIG (AND 0).
        assert_eq!(
            plc.ask(4, &mask_write(CONFIG, 0, 0x0000)).await,
            mask_write(CONFIG, 0, 0x0000)
        );
        assert_eq!(
            plc.ask(4, &mask_write(CONFIG, 0, 0x000A)).await,
            mask_write(CONFIG, 0, 0x000A)
        );
        // 150 rpm and the status back, in one request (transaction 0x0717).
        let reply = plc
            .ask_as(0x0717, 4, &read_write(0x00C0, 7, 0x0006, &[150]))
            .await;
        assert_eq!(reply[..2], [0x17, 14], "{reply:02X?}");
        // The operator may not commission: a saved inertia is an admin's.
        let saved = read_write(0x00C0, 7, INERTIA, &[3, 1]);
        assert_eq!(plc.ask(4, &saved).await, [0x97, 0x01]);

        // The setpoint took the network's communication-loss lease.
        let drive = api.get("/api/v1/drives/feeder").await.expect(200);
        assert_eq!(drive["lease"]["owner"], format!("modbus-tcp {peer}"), "{drive:#}");
        assert_eq!(drive["lease"]["comm_loss"], true, "{drive:#}");
        eventually(Duration::from_secs(20), "the feeder turning", || {
            (d.sim().drive(4)?.speed_rpm > 50.0).then_some(())
        })
        .await;

        // The bus monitor shows the write and the read as this request's.
        let frames = api
            .get(&format!("{FRAMES}?unit=4&source=modbus-tcp&limit=100000"))
            .await
            .expect(200);
        let requests: Vec<&Value> = frames["frames"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|f| f["direction"] == "request" && f["source_ref"] == 0x0717)
            .collect();
        let mut functions: Vec<u64> = requests
            .iter()
            .map(|f| f["function"].as_u64().unwrap())
            .collect();
        // (a retry on a loaded machine repeats a frame)
        functions.dedup();
        assert_eq!(functions, [0x10, 0x03], "the write first: {requests:#?}");
        assert!(requests.iter().all(|f| f["source_who"] == peer.as_str()));

        // The audit log: the setpoint in words, what was sent, and the
        // operator's refused save.
        let lines = eventually(Duration::from_secs(5), "the audit lines", || {
            let lines: Vec<String> = log_text()
                .lines()
                .filter(|l| l.contains("drivegate::audit") && l.contains(&peer))
                .map(str::to_string)
                .collect();
            (lines.len() >= 4).then_some(lines)
        })
        .await;
        assert!(
            lines.iter().any(|l| l.contains("write confirmed")
                && l.contains("SPEED_REF=150")
                && l.contains("sent as 10 00 06 00 01 02 00 96")),
            "{lines:#?}"
        );
        assert!(
            lines
                .iter()
                .any(|l| l.contains("write failed") && l.contains("needs the admin role")),
            "{lines:#?}"
        );

        // The PLC goes away: its lease ends with its stop.
        drop(plc);
        eventually(Duration::from_secs(20), "the feeder stopped", || {
            (d.sim().drive(4)?.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn raw_functions_let_an_admin_send_a_listed_code_unchecked_to_one_unit() {
    capture_logs();
    bounded(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .modbus_tcp(
                "broadcast_reply = true\nraw_functions = [0x41, 0x05]\n[[modbus_tcp.clients]]\nnetwork = \"127.0.0.3/32\"\nrole = \"operator\"",
            )
            .toml();
        let d = TestDaemon::start(&toml).await;
        let tcp = d.modbus_tcp.unwrap();
        let mut admin = Raw::connect(tcp).await;
        let who = admin.stream.local_addr().unwrap().to_string();
        let exceptions = || d.sim().stats().exceptions;

        // Listed, from the admin, to one unit: on the wire, where the drive
        // answers it does not know 0x41.
        let before = exceptions();
        assert_eq!(admin.ask(2, &[0x41, 0x12, 0x34]).await, [0xC1, 0x01]);
        assert_eq!(exceptions(), before + 1, "0x41 reached the drive");
        // Not to unit 0, not from an operator, and not a code not listed.
        assert_eq!(admin.ask(0, &[0x41, 0x12, 0x34]).await, [0xC1, 0x01]);
        assert_eq!(admin.ask(0, &[0x05, 0x00, 0x01, 0xFF, 0x00]).await, [0x85, 0x01]);
        assert_eq!(admin.ask(2, &[0x42, 0x12, 0x34]).await, [0xC2, 0x01]);
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind("127.0.0.3:0".parse().unwrap()).unwrap();
        let mut operator = Raw::from_stream(socket.connect(tcp).await.unwrap());
        assert_eq!(operator.ask(2, &[0x41, 0x12, 0x34]).await, [0xC1, 0x01]);
        assert_eq!(exceptions(), before + 1, "nothing else reached the wire");
        assert_eq!(d.sim().stats().broadcasts, 0);

        // The audit log says it went unchecked, and why the others did not go.
        let log = eventually(Duration::from_secs(5), "the audit lines", || {
            let lines: Vec<String> = log_text()
                .lines()
                .filter(|l| l.contains("drivegate::audit") && l.contains(&who))
                .map(str::to_string)
                .collect();
            (lines.len() >= 4).then_some(lines)
        })
        .await;
        assert!(
            log[0].contains("Modbus 0x41 user-defined, not checked [41 12 34]")
                && log[0].contains("unit=2"),
            "{log:#?}"
        );
        assert!(log[1].contains("never as a broadcast"), "{log:#?}");
        assert!(log[3].contains("raw_functions"), "{log:#?}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_pipelined_after_a_read_write_multiple_does_not_come_between() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&ConfigBuilder::four_drives().toml()).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        const STALL_MS: u16 = 0x000E;
        // In one segment: write 1111 and read it back (0x17), then write
        // 2222 (0x06). The read is the 0x17's own: 1111.
        let mut both =
            crate::support::modbus_tcp::frame(1, 2, &read_write(STALL_MS, 1, STALL_MS, &[1111]));
        both.extend(crate::support::modbus_tcp::frame(
            2,
            2,
            &crate::support::modbus_tcp::write(STALL_MS, 2222),
        ));
        c.send_bytes(&both).await;
        let (t, _, first) = c.recv().await.unwrap();
        assert_eq!((t, first), (1, vec![0x17, 2, 0x04, 0x57]), "1111 read back");
        let (t, _, second) = c.recv().await.unwrap();
        assert_eq!(t, 2);
        assert_eq!(second, crate::support::modbus_tcp::write(STALL_MS, 2222));
        assert_eq!(d.sim().drive(2).unwrap().settings.stall_duration_ms, 2222);
        d.stop().await;
    })
    .await;
}
