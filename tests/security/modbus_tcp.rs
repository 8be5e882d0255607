//! Access control of the Modbus TCP listener, which has no authentication
//! of its own: clients outside `allowed_networks` are closed before a byte
//! of theirs is read (IPv4 and IPv6 loopback told apart), a read-only
//! listener refuses every function code that is not a read, broadcasts
//! included, without any of them reaching the bus, and the connection limit
//! holds under a flood while the clients already connected are served.

use std::net::SocketAddr;
use std::time::Duration;

use crate::support::config::ConfigBuilder;
use crate::support::input::writes_on_wire;
use crate::support::metrics::counter;
use crate::support::modbus_tcp::{Raw, frame, read, registers, write};
use crate::support::{TestDaemon, eventually};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const LIMIT: Duration = Duration::from_secs(60);
/// STALLED_DURATION_MS: a harmless register to try writing.
const STALL_MS: u16 = 0x000E;

/// A daemon whose Modbus TCP listener is on `listen` with `keys`.
async fn daemon(listen: &str, keys: &str) -> TestDaemon {
    let toml = ConfigBuilder::four_drives()
        .modbus_tcp_listen(listen)
        .modbus_tcp(keys)
        .toml();
    TestDaemon::start(&toml).await
}

/// Connects and sends a write of the stall time at once: the reply (its
/// echo, 12 bytes with the header), or `None` when the server closed the
/// connection without a byte.
async fn try_write(addr: SocketAddr) -> Option<Vec<u8>> {
    let mut s = TcpStream::connect(addr).await.unwrap();
    let _ = s.write_all(&frame(1, 2, &write(STALL_MS, 4321))).await;
    let mut got = Vec::new();
    let mut chunk = [0u8; 64];
    let until = tokio::time::Instant::now() + Duration::from_secs(10);
    while got.len() < 12 {
        match tokio::time::timeout_at(until, s.read(&mut chunk)).await {
            Ok(Ok(0) | Err(_)) => break,
            Ok(Ok(n)) => got.extend_from_slice(&chunk[..n]),
            Err(_) => panic!("neither a reply nor a close within 10 s"),
        }
    }
    (!got.is_empty()).then_some(got)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_clients_of_the_allowed_networks_get_in() {
    tokio::time::timeout(LIMIT, async {
        for (listen, allowed, comes_from, admitted) in [
            // IPv6 loopback allowed; an IPv4 loopback client is not.
            ("[::1]:0", "::1/128", "::1", true),
            ("127.0.0.1:0", "::1/128", "127.0.0.1", false),
            // And the other way round.
            ("127.0.0.1:0", "127.0.0.0/8", "127.0.0.1", true),
            ("[::1]:0", "127.0.0.0/8", "::1", false),
            // A list of plant networks that leaves loopback out.
            (
                "127.0.0.1:0",
                "10.0.0.0/8\", \"192.168.0.0/16\", \"fd00::/8",
                "127.0.0.1",
                false,
            ),
            // Nobody at all.
            ("127.0.0.1:0", "", "127.0.0.1", false),
        ] {
            let allowed_list = if allowed.is_empty() {
                "allowed_networks = []".to_string()
            } else {
                format!("allowed_networks = [\"{allowed}\"]")
            };
            let d = daemon(listen, &allowed_list).await;
            let addr = d.modbus_tcp.unwrap();
            assert_eq!(addr.ip().to_string(), comes_from, "the client's address");
            let writes = writes_on_wire(&d.plant);
            let answer = try_write(addr).await;
            let case = format!("{allowed_list} with a client at {comes_from}");
            if admitted {
                let (t, u, pdu) = (
                    u16::from_be_bytes([answer.as_ref().unwrap()[0], answer.as_ref().unwrap()[1]]),
                    answer.as_ref().unwrap()[6],
                    answer.as_ref().unwrap()[7..].to_vec(),
                );
                assert_eq!((t, u, pdu), (1, 2, write(STALL_MS, 4321)), "{case}");
                assert_eq!(d.sim().drive(2).unwrap().settings.stall_duration_ms, 4321);
            } else {
                assert_eq!(answer, None, "{case}: the refused client got an answer");
                assert_eq!(
                    writes_on_wire(&d.plant),
                    writes,
                    "{case}: a refused client wrote"
                );
                assert_eq!(d.sim().drive(2).unwrap().settings.stall_duration_ms, 3000);
                assert_eq!(
                    counter(
                        &d,
                        "drivegate_modbus_tcp_connections_rejected_total{reason=\"not_allowed\"}"
                    ),
                    1.0,
                    "{case}"
                );
                assert_eq!(
                    counter(&d, "drivegate_modbus_tcp_connections_accepted_total"),
                    0.0
                );
            }
            d.stop().await;
        }
    })
    .await
    .expect("test finished in time");
}

/// A request for function `code` that is well formed for the codes the
/// specification defines, and a few plausible bytes for the others.
fn request_for(code: u8) -> Vec<u8> {
    match code {
        0x05 => vec![0x05, 0x00, 0x01, 0xFF, 0x00],
        0x06 => write(STALL_MS, 1111),
        0x0F => vec![0x0F, 0x00, 0x00, 0x00, 0x08, 0x01, 0xFF],
        0x10 => vec![0x10, 0x00, 0x0E, 0x00, 0x01, 0x02, 0x04, 0x57],
        0x14 => vec![0x14, 0x07, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02],
        0x15 => vec![
            0x15, 0x09, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x01, 0x06, 0xAF,
        ],
        0x18 => vec![0x18, 0x04, 0xDE],
        0x16 => vec![0x16, 0x00, 0x0E, 0xFF, 0xFF, 0x00, 0x00],
        0x17 => vec![
            0x17, 0x00, 0xC0, 0x00, 0x01, 0x00, 0x0E, 0x00, 0x01, 0x02, 0x04, 0x57,
        ],
        0x2B => vec![0x2B, 0x0D, 0x00],
        _ => vec![code, 0x00, 0xC0, 0x00, 0x01],
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_only_listener_lets_no_function_but_reads_through() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon("127.0.0.1:0", "read_only = true\nbroadcast_reply = true").await;
        let addr = d.modbus_tcp.unwrap();
        let mut c = Raw::connect(addr).await;
        let reads = [0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18];
        let writes = writes_on_wire(&d.plant);
        let broadcasts = d.sim().stats().broadcasts;
        let mut refused = 0;
        // Every function code a request may carry, to a drive and as a
        // broadcast.
        // The gateway's refusals are told from the drive's own 0x01 (for
        // codes it lacks) by the outcome they are counted under: a viewer's
        // write (`read_only`), or, for every role, a code the control core
        // cannot decode (`not_decoded`).
        let read_only = |code: u8| {
            ["read_only", "not_decoded"]
                .iter()
                .map(|outcome| {
                    counter(
                        &d,
                        &format!("drivegate_modbus_tcp_requests_total{{function=\"0x{code:02x}\",outcome=\"{outcome}\"}}"),
                    )
                })
                .sum::<f64>()
        };
        for code in 0x01..=0x7Fu8 {
            let pdu = request_for(code);
            let answer = c.ask(1, &pdu).await;
            if reads.contains(&code) {
                assert_eq!(read_only(code), 0.0, "read 0x{code:02X} refused: {answer:02X?}");
            } else {
                assert_eq!(answer, [code | 0x80, 0x01], "0x{code:02X} was not refused");
                assert_eq!(read_only(code), 1.0, "0x{code:02X}");
                refused += 1;
            }
            let answer = c.ask(0, &pdu).await;
            assert_eq!(answer, [code | 0x80, 0x01], "broadcast 0x{code:02X}");
        }
        // Device identification (0x2B, MEI 0x0E) is a read.
        let before = read_only(0x2B);
        c.ask(1, &[0x2B, 0x0E, 0x01, 0x00]).await;
        assert_eq!(read_only(0x2B), before, "device identification refused");
        assert_eq!(writes_on_wire(&d.plant), writes, "a write reached the bus");
        assert_eq!(d.sim().stats().broadcasts, broadcasts, "a broadcast reached the bus");
        let drive = d.sim().drive(1).unwrap();
        assert_eq!(drive.settings.stall_duration_ms, 3000);
        assert!(!drive.active);
        // Reads still work.
        assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
        println!("read-only listener: {refused} function codes refused (and 127 broadcasts), {} reads let through", reads.len());
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_connection_limit_holds_under_a_flood() {
    tokio::time::timeout(LIMIT, async {
        // One address: its cap raised to the whole limit.
        let d = daemon(
            "127.0.0.1:0",
            "max_connections = 4\nmax_connections_per_address = 4",
        )
        .await;
        let addr = d.modbus_tcp.unwrap();
        let mut held = Vec::new();
        for _ in 0..4 {
            let mut c = Raw::connect(addr).await;
            assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
            held.push(c);
        }
        // Refused by the limit, or first by the cap of their address (the
        // same as the four's), which is the same size here.
        let rejected = || {
            counter(
                &d,
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"limit\"}",
            ) + counter(
                &d,
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"per_address\"}",
            )
        };
        let before = rejected();
        // 200 more at once, each with a write: none is served, none writes.
        let writes = writes_on_wire(&d.plant);
        let flood: Vec<_> = (0..200).map(|_| tokio::spawn(try_write(addr))).collect();
        let mut peak: f64 = 0.0;
        for f in flood {
            peak = peak.max(counter(&d, "drivegate_modbus_tcp_connections"));
            assert_eq!(
                f.await.unwrap(),
                None,
                "a connection over the limit was served"
            );
        }
        assert!(peak <= 4.0, "{peak} connections open at once");
        eventually(Duration::from_secs(5), "200 refusals counted", || {
            (rejected() == before + 200.0).then_some(())
        })
        .await;
        assert_eq!(writes_on_wire(&d.plant), writes);
        // The four still work.
        for c in &mut held {
            assert_eq!(registers(&c.ask(2, &read(0xC0, 7)).await).len(), 7);
        }
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
