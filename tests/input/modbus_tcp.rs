//! Attacks on the Modbus TCP listener, over real sockets, while a
//! well-behaved client keeps reading drive 1's status on a connection of its
//! own: random garbage, frames cut short, huge length fields, requests
//! trickled a byte at a time, headers followed by nothing, and thousands of
//! connections opened and dropped. Nothing crashes, the well-behaved client
//! gets every answer right, every attacking connection is closed and
//! counted, nothing reaches a drive, and no socket or task is left behind.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use crate::support::input::{Baseline, Bystander, config, writes_on_wire};
use crate::support::metrics::counter;
use crate::support::modbus_tcp::{frame, read, write};
use crate::support::{TestDaemon, eventually};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const LIMIT: Duration = Duration::from_secs(60);

/// STALLED_DURATION_MS: a harmless register to try writing.
const STALL_MS: u16 = 0x000E;

async fn daemon(modbus: &str) -> TestDaemon {
    TestDaemon::start(&config("", modbus, false, "")).await
}

/// Reads and discards until the server closes the connection; false if it
/// is still open after `limit`.
async fn closed_within(stream: &mut TcpStream, limit: Duration) -> bool {
    let mut sink = [0u8; 1024];
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, stream.read(&mut sink)).await {
            Ok(Ok(0) | Err(_)) => return true,
            Ok(Ok(_)) => {}
            Err(_) => return false,
        }
    }
}

async fn connect(addr: SocketAddr) -> TcpStream {
    tokio::time::timeout(Duration::from_secs(5), TcpStream::connect(addr))
        .await
        .expect("connect in time")
        .expect("connect")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_and_huge_lengths_close_only_their_connection() {
    tokio::time::timeout(LIMIT, async {
        // A long idle timeout: a connection closed here was closed for what
        // it sent, not for going quiet.
        let d = daemon("idle_timeout_ms = 30000").await;
        let addr = d.modbus_tcp.unwrap();
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::modbus(addr);
        bystander.wait_for(3).await;
        let writes = writes_on_wire(&d.plant);
        let malformed = counter(&d, "drivegate_modbus_tcp_malformed_frames_total");

        // Headers no body can follow: a length of 0, 1, 255 or 65535, a
        // protocol id that is not Modbus, a function code of 0 or an
        // exception code. Each is refused as soon as it arrives.
        let headers: Vec<Vec<u8>> = vec![
            vec![0, 1, 0, 0, 0xFF, 0xFF, 1],
            vec![0, 1, 0, 0, 0x00, 0xFF, 1],
            vec![0, 1, 0, 0, 0x01, 0x00, 1],
            vec![0, 1, 0, 0, 0, 0, 1],
            vec![0, 1, 0, 0, 0, 1, 1],
            vec![0, 1, 0x12, 0x34, 0, 6, 1],
            vec![0, 1, 0xFF, 0xFF, 0, 6, 1],
            vec![0, 1, 0, 0, 0, 6, 1, 0x00],
            vec![0, 1, 0, 0, 0, 6, 1, 0x83],
            vec![0, 1, 0, 0, 0, 6, 1, 0xFF],
        ];
        for header in &headers {
            let mut s = connect(addr).await;
            s.write_all(header).await.unwrap();
            assert!(
                closed_within(&mut s, Duration::from_secs(10)).await,
                "{header:02X?} did not close the connection"
            );
        }

        // Random bytes, 64 connections of up to 600 bytes each, reproducible
        // by seed; some are valid frames by chance (and answered), the rest
        // close their connection. Either way the connection ends with the
        // client's close.
        let mut rng = StdRng::seed_from_u64(0x6d62_6170);
        let mut refused = headers.len();
        for _ in 0..64 {
            let mut bytes = vec![0u8; rng.random_range(1..600)];
            rng.fill(&mut bytes[..]);
            // Never a valid header by chance: protocol id 0 would need two
            // zero bytes here, and a valid one may write a drive.
            if let Some(b) = bytes.get_mut(2) {
                *b |= 0x01;
            }
            let mut s = connect(addr).await;
            let _ = s.write_all(&bytes).await;
            // Under six bytes there is no header to refuse yet: the client
            // just leaves.
            if bytes.len() >= 6 {
                assert!(closed_within(&mut s, Duration::from_secs(10)).await);
                refused += 1;
            }
        }
        // An HTTP request, a TLS hello: not Modbus either.
        for bytes in [
            &b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"[..],
            &[
                0x16, 0x03, 0x01, 0x02, 0x00, 0x01, 0x00, 0x01, 0xFC, 0x03, 0x03,
            ][..],
        ] {
            let mut s = connect(addr).await;
            s.write_all(bytes).await.unwrap();
            assert!(closed_within(&mut s, Duration::from_secs(10)).await);
            refused += 1;
        }

        // Each was counted as malformed and closed; none reached a drive.
        let malformed_now = counter(&d, "drivegate_modbus_tcp_malformed_frames_total");
        assert_eq!(malformed_now - malformed, refused as f64);
        assert_eq!(writes_on_wire(&d.plant), writes, "garbage wrote to a drive");
        eventually(
            Duration::from_secs(5),
            "only the bystander connected",
            || (counter(&d, "drivegate_modbus_tcp_connections") == 1.0).then_some(()),
        )
        .await;
        let (ok, slowest) = bystander.finish(3, "garbage").await;
        println!(
            "Modbus TCP garbage: {refused} connections refused as malformed; well-behaved client: {ok} answers, slowest {slowest:?}"
        );
        baseline
            .assert_back(Duration::from_secs(5), "garbage and huge lengths")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn truncated_frames_trickled_bytes_and_stalled_headers_time_out() {
    tokio::time::timeout(LIMIT, async {
        // Every client is on loopback: the per-address cap raised to the
        // limit, so that each is closed by its timeout, not refused.
        let d = daemon("idle_timeout_ms = 400\nmax_connections_per_address = 64").await;
        let addr = d.modbus_tcp.unwrap();
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::modbus(addr);
        bystander.wait_for(3).await;
        let writes = writes_on_wire(&d.plant);

        // A write cut at every length: the client goes away (nothing is
        // sent to the drive), or stays (closed as idle).
        let whole = frame(7, 2, &write(STALL_MS, 1234));
        let mut stalled = Vec::new();
        for cut in 1..whole.len() {
            let mut s = connect(addr).await;
            s.write_all(&whole[..cut]).await.unwrap();
            if cut % 2 == 0 {
                drop(s);
            } else {
                stalled.push(s);
            }
        }
        // Twenty clients trickling a read a byte at a time, one byte every
        // 100 ms: the whole frame would take 1.1 s, far over the idle
        // timeout, which counts whole requests only. A header then nothing.
        let request = frame(9, 1, &read(0xC0, 7));
        let mut trickles = Vec::new();
        for _ in 0..20 {
            let request = request.clone();
            trickles.push(tokio::spawn(async move {
                // Taken before connecting: the server's clock starts at
                // its accept, which may come before `connect` returns.
                let opened = Instant::now();
                let mut s = connect(addr).await;
                for byte in &request {
                    if s.write_all(&[*byte]).await.is_err() {
                        break;
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                let closed = closed_within(&mut s, Duration::from_secs(10)).await;
                (closed, opened.elapsed())
            }));
        }
        let opened = Instant::now();
        let mut header_only = connect(addr).await;
        header_only.write_all(&request[..7]).await.unwrap();
        assert!(closed_within(&mut header_only, Duration::from_secs(10)).await);
        assert!(opened.elapsed() >= Duration::from_millis(400));
        for s in &mut stalled {
            assert!(closed_within(s, Duration::from_secs(10)).await);
        }
        for t in trickles {
            let (closed, after) = t.await.unwrap();
            assert!(closed, "a trickling client kept its connection");
            assert!(
                after >= Duration::from_millis(400),
                "closed after {after:?}"
            );
        }
        // A client slower than one frame per idle timeout but sending whole
        // frames is served.
        let mut slow = crate::support::modbus_tcp::Raw::connect(addr).await;
        for _ in 0..3 {
            let reply = slow.ask(3, &read(0xC0, 7)).await;
            assert_eq!(crate::support::modbus_tcp::registers(&reply).len(), 7);
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        drop((slow, stalled, header_only));

        assert_eq!(
            writes_on_wire(&d.plant),
            writes,
            "a cut frame wrote to a drive"
        );
        assert_eq!(d.sim().drive(2).unwrap().settings.stall_duration_ms, 3000);
        let (ok, slowest) = bystander.finish(3, "truncated and trickled frames").await;
        println!("Modbus TCP cut and trickled frames; well-behaved client: {ok} answers, slowest {slowest:?}");
        eventually(Duration::from_secs(5), "every connection closed", || {
            (counter(&d, "drivegate_modbus_tcp_connections") == 0.0).then_some(())
        })
        .await;
        baseline
            .assert_back(Duration::from_secs(5), "truncated and trickled frames")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thousands_of_connections_opened_and_dropped() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon("").await;
        let addr = d.modbus_tcp.unwrap();
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::modbus(addr);
        let max: f64 = 64.0;

        // 3000 connections in waves of 100 at once (over max_connections,
        // 64): each closes at once, or sends half a request first, or a
        // whole request and leaves before its answer.
        let total = 3000;
        let mut opened = 0;
        bystander.wait_for(3).await;
        let before = bystander.answers();
        let flood = Instant::now();
        for wave in 0..total / 100 {
            let mut clients = Vec::new();
            for i in 0..100 {
                clients.push(tokio::spawn(async move {
                    let Ok(mut s) = TcpStream::connect(addr).await else {
                        return false;
                    };
                    match (wave + i) % 3 {
                        0 => {}
                        1 => {
                            let _ = s.write_all(&frame(1, 1, &read(0xC0, 7))[..5]).await;
                        }
                        _ => {
                            let _ = s.write_all(&frame(1, 2, &read(0xC0, 7))).await;
                        }
                    }
                    true
                }));
            }
            for c in clients {
                opened += u32::from(c.await.unwrap());
            }
            // The gauge never goes over the limit.
            let open = counter(&d, "drivegate_modbus_tcp_connections");
            assert!(open <= max, "{open} connections open");
        }
        assert_eq!(opened, total, "connections could not be opened");

        // Every one is accounted for: accepted (and closed since) or refused
        // over the limit; only the well-behaved client's is still open.
        // (At most the well-behaved client's; if it left, its failure is
        // reported below.)
        eventually(Duration::from_secs(10), "every connection closed", || {
            (counter(&d, "drivegate_modbus_tcp_connections") <= 1.0).then_some(())
        })
        .await;
        let accepted = counter(&d, "drivegate_modbus_tcp_connections_accepted_total");
        // All from one address: refused near the limit as the address
        // holding the most, or at the limit.
        let refused: f64 = ["limit", "per_address", "heaviest", "files"]
            .iter()
            .map(|reason| {
                counter(
                    &d,
                    &format!("drivegate_modbus_tcp_connections_rejected_total{{reason=\"{reason}\"}}"),
                )
            })
            .sum();
        // Each was seen by the daemon: accepted (and closed since) or
        // refused. (A client may reset its connection before the daemon
        // accepts it, which the kernel may hide from it: allow a few.)
        let seen = accepted + refused;
        assert!(
            seen <= f64::from(total) + 1.0 && seen >= f64::from(total) * 0.99,
            "accepted {accepted}, refused {refused} of {total}"
        );
        let during = bystander.answers() - before;
        let (ok, slowest) = bystander.finish(3, "3000 connections").await;
        println!(
            "Modbus TCP: {total} connections opened and dropped in {:?} ({accepted} accepted, {refused} refused over the limits); well-behaved client: {during} answers meanwhile, {ok} in all, slowest {slowest:?}", flood.elapsed()
        );
        // A new client is served as before.
        let mut after = crate::support::modbus_tcp::Raw::connect(addr).await;
        let reply = after.ask(4, &read(0xC0, 7)).await;
        assert_eq!(crate::support::modbus_tcp::registers(&reply).len(), 7);
        drop(after);
        baseline
            .assert_back(Duration::from_secs(10), "3000 connections")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
