//! Modbus TCP connections under stress, byte by byte: pipelining and reply
//! order, disconnects while queued, malformed frames, idle timeout,
//! connection limit, a full listener making room for another address,
//! the fair share under 500 idle sockets from one address, allowed
//! networks, read-only listeners, passthrough of reads the drive lacks,
//! fairness between connections.

use std::time::{Duration, Instant};

use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::{exported, metric};
use crate::support::modbus_tcp::{Raw, four_drives_with, read, registers, write};
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::stats::Outcome;

/// Every test ends within this, whatever happens.
const LIMIT: Duration = Duration::from_secs(60);

/// STALLED_DURATION_MS: read/write, 0..60000, harmless while standing still.
const STALL_MS: u16 = 0x000E;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pipelined_requests_are_answered_in_order() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        d.sim().set_silent(4, true);
        let mut raw = Raw::connect(d.modbus_tcp.unwrap()).await;
        // One write carrying 12 requests: slow ones (a silent unit), instant
        // ones (a unit on no bus, a malformed quantity) and reads of several
        // lengths, interleaved. Replies must come in this order.
        let requests: Vec<(u16, u8, Vec<u8>)> = vec![
            (1, 1, read(0xC0, 7)),
            (2, 4, read(0xC0, 7)),  // silent: 0x0B after the retries
            (3, 77, read(0xC0, 7)), // no bus: 0x0A at once, but after #2
            (4, 2, read(0xC2, 1)),
            (5, 3, write(STALL_MS, 1234)),
            (6, 3, read(STALL_MS, 1)),
            (7, 1, read(0xC0, 0)), // quantity 0: 0x03 from the gateway
            (8, 2, read(0xC4, 3)),
            (9, 1, vec![0x04, 0x00, 0xC0, 0x00, 0x07]), // the drive lacks 0x04
            (10, 3, write(STALL_MS, 4321)),
            (11, 3, read(STALL_MS, 1)),
            (12, 2, read(0xC0, 5)),
        ];
        let bytes: Vec<u8> = requests
            .iter()
            .flat_map(|(t, u, pdu)| crate::support::modbus_tcp::frame(*t, *u, pdu))
            .collect();
        raw.send_bytes(&bytes).await;
        let mut replies = Vec::new();
        for _ in &requests {
            replies.push(raw.recv().await.expect("a reply"));
        }
        let ids: Vec<(u16, u8)> = replies.iter().map(|(t, u, _)| (*t, *u)).collect();
        let expected: Vec<(u16, u8)> = requests.iter().map(|(t, u, _)| (*t, *u)).collect();
        assert_eq!(ids, expected, "replies out of order");
        let pdu = |i: usize| replies[i].2.clone();
        assert_eq!(registers(&pdu(0)).len(), 7);
        assert_eq!(pdu(1), [0x83, 0x0B]);
        assert_eq!(pdu(2), [0x83, 0x0A]);
        assert_eq!(registers(&pdu(3)).len(), 1);
        assert_eq!(pdu(4), write(STALL_MS, 1234));
        assert_eq!(registers(&pdu(5)), [1234]);
        assert_eq!(pdu(6), [0x83, 0x03]);
        assert_eq!(registers(&pdu(7)).len(), 3);
        assert_eq!(pdu(8), [0x84, 0x01]);
        assert_eq!(pdu(9), write(STALL_MS, 4321));
        assert_eq!(registers(&pdu(10)), [4321]);
        assert_eq!(registers(&pdu(11)).len(), 5);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_disconnects_has_its_queued_requests_dropped_unsent() {
    bounded(LIMIT, async {
        // A long response timeout: whatever is on the wire when B sends stays
        // there for half a second, far longer than B takes to disconnect.
        let toml = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.keys("response_timeout_ms = 500").auto_guard())
            .toml();
        let d = TestDaemon::start(&toml).await;
        let addr = d.modbus_tcp.unwrap();
        let (_, bus) = d.plant.drive("lift").unwrap();
        d.sim().set_silent(4, true);
        // A holds the wire: a request to a silent unit takes two response
        // timeouts and a guard time (a poll of it, at least one timeout).
        let mut a = Raw::connect(addr).await;
        let unanswered = d.sim().stats().unanswered;
        a.send(1, 4, &read(0xC0, 7)).await;
        eventually(Duration::from_secs(5), "A's request on the wire", || {
            (d.sim().stats().unanswered > unanswered).then_some(())
        })
        .await;
        // B pipelines 40 writes behind it, more than max_pipelined (16) can
        // queue, and disconnects at once.
        let dropped = bus.stats().count(Outcome::Dropped);
        let mut b = Raw::connect(addr).await;
        let bytes: Vec<u8> = (0..40u16)
            .flat_map(|t| crate::support::modbus_tcp::frame(100 + t, 2, &write(STALL_MS, 4242)))
            .collect();
        b.send_bytes(&bytes).await;
        drop(b);
        assert_eq!(a.recv().await.map(|r| r.2), Some(vec![0x83, 0x0B]));
        // The 16 queued jobs were dropped by the bus before the wire, the
        // 24 still in the socket were never queued...
        eventually(Duration::from_secs(5), "16 dropped jobs", || {
            (bus.stats().count(Outcome::Dropped) == dropped + 16).then_some(())
        })
        .await;
        let text = d.metrics.render();
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_requests_total{function=\"0x06\",outcome=\"cancelled\"}"
            ),
            16.0,
            "{text}"
        );
        // ...and the drive never saw the value.
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_eq!(d.sim().drive(2).unwrap().settings.stall_duration_ms, 3000);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_frame_closes_only_its_connection() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        let mut good = Raw::connect(addr).await;
        assert_eq!(registers(&good.ask(1, &read(0xC0, 7)).await).len(), 7);

        // Protocol id 1: not Modbus.
        let mut bad = Raw::connect(addr).await;
        bad.send_bytes(&[
            0x00, 0x01, 0x00, 0x01, 0x00, 0x06, 0x01, 0x03, 0x00, 0xC0, 0x00, 0x07,
        ])
        .await;
        assert!(bad.closed_by_server().await);

        // A valid request, then a length field of 0, in one write: the valid
        // one is answered, then the connection is closed.
        let mut mixed = Raw::connect(addr).await;
        let mut bytes = crate::support::modbus_tcp::frame(7, 2, &read(0xC0, 7));
        bytes.extend_from_slice(&[0x00, 0x08, 0x00, 0x00, 0x00, 0x00, 0x01]);
        mixed.send_bytes(&bytes).await;
        let (t, u, pdu) = mixed.recv().await.expect("the valid request's reply");
        assert_eq!((t, u, registers(&pdu).len()), (7, 2, 7));
        assert!(mixed.closed_by_server().await);

        // Garbage after a bad frame does not reset the connection before
        // the earlier reply is read.
        let mut noisy = Raw::connect(addr).await;
        let mut bytes = crate::support::modbus_tcp::frame(8, 3, &read(0xC0, 7));
        bytes.extend_from_slice(&[0xFF; 7]);
        noisy.send_bytes(&bytes).await;
        noisy.send_bytes(&[0xEE; 2000]).await;
        // Read only after the server has answered and closed.
        tokio::time::sleep(Duration::from_millis(200)).await;
        let (t, _, pdu) = noisy.recv().await.expect("the valid request's reply");
        assert_eq!((t, registers(&pdu).len()), (8, 7));
        assert!(noisy.closed_by_server().await);

        // An HTTP request on the Modbus port.
        let mut http = Raw::connect(addr).await;
        http.send_bytes(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(http.closed_by_server().await);

        let text = d.metrics.render();
        assert_eq!(
            metric(&text, "drivegate_modbus_tcp_malformed_frames_total"),
            4.0
        );
        // The first client never noticed.
        assert_eq!(registers(&good.ask(3, &read(0xC0, 7)).await).len(), 7);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_time_out() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with("idle_timeout_ms = 300")).await;
        let addr = d.modbus_tcp.unwrap();
        // Each instant is taken before the step that starts the server's
        // idle clock (its reply, its accept), so it can only be earlier.
        let mut quiet = Raw::connect(addr).await;
        let asked = Instant::now();
        assert_eq!(registers(&quiet.ask(1, &read(0xC0, 7)).await).len(), 7);
        // Half a frame, then nothing: idle as well.
        let opened = Instant::now();
        let mut stalled = Raw::connect(addr).await;
        stalled.send_bytes(&[0x00, 0x01, 0x00, 0x00, 0x00]).await;
        assert!(quiet.closed_by_server().await);
        assert!(asked.elapsed() >= Duration::from_millis(300));
        assert!(stalled.closed_by_server().await);
        assert!(opened.elapsed() >= Duration::from_millis(300));
        eventually(Duration::from_secs(2), "no connection open", || {
            let text = d.metrics.render();
            (metric(&text, "drivegate_modbus_tcp_connections") == 0.0).then_some(())
        })
        .await;
        // An active client is not idle: requests every 100 ms for a second.
        let mut busy = Raw::connect(addr).await;
        for _ in 0..10 {
            assert_eq!(registers(&busy.ask(2, &read(0xC0, 1)).await).len(), 1);
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixty_four_connections_are_served_at_once() {
    bounded(LIMIT, async {
        // All from one address, which may take every free slot short of the
        // last eighth (kept for other addresses): 70 of 80.
        let d = TestDaemon::start(&four_drives_with("max_connections = 80")).await;
        let addr = d.modbus_tcp.unwrap();
        let mut clients = Vec::new();
        for _ in 0..64 {
            clients.push(Raw::connect(addr).await);
        }
        // Every connection has a request queued at the same time; each
        // reads a different length so a crossed reply would show.
        for (i, c) in clients.iter_mut().enumerate() {
            let i = i as u16;
            c.send(i, (i % 4) as u8 + 1, &read(0xC0, i % 7 + 1)).await;
        }
        for (i, c) in clients.iter_mut().enumerate() {
            let i = i as u16;
            let (t, u, pdu) = c.recv().await.expect("a reply");
            assert_eq!((t, u), (i, (i % 4) as u8 + 1));
            assert_eq!(registers(&pdu).len(), usize::from(i % 7 + 1));
        }
        let text = d.metrics.render();
        assert_eq!(metric(&text, "drivegate_modbus_tcp_connections"), 64.0);
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"limit\"}"
            ),
            0.0
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_listener_closes_a_quiet_connection_of_the_heaviest_address_for_another() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with("max_connections = 2")).await;
        let addr = d.modbus_tcp.unwrap();
        // Both slots from 127.0.0.1; the first is the quieter one.
        let mut one = Raw::connect(addr).await;
        let mut two = Raw::connect(addr).await;
        assert_eq!(registers(&one.ask(1, &read(0xC0, 7)).await).len(), 7);
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert_eq!(registers(&two.ask(1, &read(0xC0, 7)).await).len(), 7);
        // Another address finds the listener full: the quietest connection
        // of the address holding the most is closed to make room.
        let mut three = Raw::from_stream(connect_from("127.0.0.2", addr).await);
        assert_eq!(registers(&three.ask(2, &read(0xC0, 7)).await).len(), 7);
        assert!(one.closed_by_server().await, "the quietest was closed");
        assert_eq!(registers(&two.ask(1, &read(0xC0, 7)).await).len(), 7);
        let text = d.metrics.render();
        assert_eq!(
            metric(
                &text,
                "drivegate_connections_closed_total{face=\"modbus_tcp\"}"
            ),
            1.0
        );
        assert_eq!(
            metric(
                &text,
                "drivegate_connections_turned_away_total{face=\"modbus_tcp\",address=\"127.0.0.1\"}"
            ),
            1.0
        );
        // Now each holds one: a full listener is full for both.
        let mut four = Raw::connect(addr).await;
        try_send(&mut four, 1, &read(0xC0, 7)).await;
        assert!(four.closed_by_server().await);
        assert_eq!(
            metric(
                &d.metrics.render(),
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"limit\"}"
            ),
            1.0
        );
        // A slot frees when a client leaves.
        drop(two);
        let mut again = None;
        for _ in 0..50 {
            let mut c = Raw::connect(addr).await;
            c.send(2, 1, &read(0xC0, 7)).await;
            if let Some((2, 1, pdu)) = c.recv().await {
                again = Some(pdu);
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert_eq!(
            registers(&again.expect("a connection after one closed")).len(),
            7
        );
        assert_eq!(registers(&three.ask(1, &read(0xC0, 7)).await).len(), 7);
        d.stop().await;
    })
    .await;
}

/// Sends a request to unit 1 on `c` as transaction `transaction`, if the
/// server has not closed it already (a refused connection may be reset
/// before the bytes go).
async fn try_send(c: &mut Raw, transaction: u16, pdu: &[u8]) {
    use tokio::io::AsyncWriteExt;
    let bytes = crate::support::modbus_tcp::frame(transaction, 1, pdu);
    let _ = c.stream.write_all(&bytes).await;
}

/// A connection from `source` to `addr`, without waiting for anything.
async fn connect_from(source: &str, addr: std::net::SocketAddr) -> tokio::net::TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    tokio::time::timeout(Duration::from_secs(10), socket.connect(addr))
        .await
        .expect("connect in time")
        .expect("connect")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn five_hundred_idle_connections_from_one_address_leave_room_for_the_others() {
    capture_logs();
    bounded(Duration::from_secs(120), async {
        // The defaults (four drives): 64 connections, no cap per address;
        // idle ones closed after 3 s.
        let d = TestDaemon::start(&four_drives_with("idle_timeout_ms = 3000")).await;
        let addr = d.modbus_tcp.unwrap();
        // A fresh /metrics has every refusal's series, and the outcome of
        // what the core cannot decode, at 0.
        let fresh = d.metrics.render();
        for reason in ["not_allowed", "per_address", "heaviest", "limit", "files"] {
            let series =
                format!("drivegate_modbus_tcp_connections_rejected_total{{reason=\"{reason}\"}}");
            assert_eq!(exported(&fresh, &series), 0.0);
        }
        assert_eq!(
            exported(
                &fresh,
                "drivegate_modbus_tcp_requests_total{function=\"0x06\",outcome=\"not_decoded\"}"
            ),
            0.0
        );
        // 500 sockets from one address (this test's own), that send nothing.
        let flood = "127.0.0.77";
        let mut idle = Vec::new();
        for _ in 0..500 {
            idle.push(connect_from(flood, addr).await);
        }
        // It takes the free slots short of the last eighth (56), then gives
        // way as the heaviest address.
        let heaviest = "drivegate_modbus_tcp_connections_rejected_total{reason=\"heaviest\"}";
        eventually(
            Duration::from_secs(20),
            "444 refused for the address",
            || (metric(&d.metrics.render(), heaviest) == 444.0).then_some(()),
        )
        .await;
        // Another address is served at once, and the listener's limit was
        // never reached.
        let started = Instant::now();
        let mut other = Raw::from_stream(connect_from("127.0.0.78", addr).await);
        assert_eq!(registers(&other.ask(1, &read(0xC0, 7)).await).len(), 7);
        let served_in = started.elapsed();
        let text = d.metrics.render();
        assert_eq!(metric(&text, "drivegate_modbus_tcp_connections"), 57.0);
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"limit\"}"
            ),
            0.0
        );
        // A few warnings for the burst (once per second at most), the
        // first naming the key.
        let lines: Vec<String> = log_text()
            .lines()
            .filter(|l| {
                l.contains("WARN")
                    && l.contains(&format!("from {flood} refused"))
                    && l.contains(&addr.to_string())
            })
            .map(str::to_string)
            .collect();
        assert!((1..=4).contains(&lines.len()), "{lines:#?}");
        assert!(
            lines[0].contains("[modbus_tcp] max_connections")
                && lines[0].contains("this address the most (56)"),
            "{}",
            lines[0]
        );
        // Its idle sockets time out; the address is served again within
        // the idle timeout.
        let mut again = None;
        for _ in 0..100 {
            let mut c = Raw::from_stream(connect_from(flood, addr).await);
            try_send(&mut c, 5, &read(0xC0, 7)).await;
            if let Some((5, 1, pdu)) = c.recv().await {
                again = Some(pdu);
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        assert_eq!(
            registers(&again.expect("served after the idle timeout")).len(),
            7
        );
        eprintln!(
            "500 idle connections from {flood}: 56 held, 444 refused, {} warning line(s); \
             another address served in {served_in:?}",
            lines.len()
        );
        drop(idle);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_outside_the_allowed_networks_are_refused() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with(
            "allowed_networks = [\"10.0.0.0/8\", \"fd00::/8\"]",
        ))
        .await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        c.send(1, 1, &read(0xC0, 7)).await;
        assert!(c.closed_by_server().await);
        let text = d.metrics.render();
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_connections_rejected_total{reason=\"not_allowed\"}"
            ),
            1.0
        );
        assert_eq!(
            metric(&text, "drivegate_modbus_tcp_connections_accepted_total"),
            0.0
        );
        d.stop().await;

        let d = TestDaemon::start(&four_drives_with("allowed_networks = [\"127.0.0.1/32\"]")).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_only_listener_refuses_writes_with_illegal_function() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with("read_only = true")).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let (_, bus) = d.plant.drive("conveyor").unwrap();
        // Reads pass.
        assert_eq!(registers(&c.ask(1, &read(0xC0, 7)).await).len(), 7);
        assert_eq!(registers(&c.ask(1, &read(STALL_MS, 1)).await), [3000]);
        // Writes of every kind are refused with 0x01, and never reach the bus.
        assert_eq!(c.ask(1, &write(STALL_MS, 1111)).await, [0x86, 0x01]);
        let block = [
            0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0x01, 0x2C, 0x07, 0xD0, 0x00, 0x00,
        ];
        assert_eq!(c.ask(1, &block).await, [0x90, 0x01]);
        assert_eq!(c.ask(1, &[0x41, 0x01, 0x02]).await, [0xC1, 0x01]);
        assert_eq!(
            c.ask(1, &[0x05, 0x00, 0x01, 0xFF, 0x00]).await,
            [0x85, 0x01]
        );
        // A broadcast is refused too (silently: broadcasts are not answered).
        c.send(9, 0, &write(0x0002, 0)).await;
        assert_eq!(registers(&c.ask(1, &read(STALL_MS, 1)).await), [3000]);
        let stats = bus.stats();
        for function in [0x06, 0x10, 0x41, 0x05] {
            assert!(
                !stats.transactions.keys().any(|(f, _)| *f == function),
                "function 0x{function:02X} reached the bus: {:?}",
                stats.transactions
            );
        }
        let view = d.sim().drive(1).unwrap();
        assert_eq!(view.settings.stall_duration_ms, 3000);
        assert!(!view.active);
        let text = d.metrics.render();
        assert_eq!(
            metric(
                &text,
                "drivegate_modbus_tcp_requests_total{function=\"0x06\",outcome=\"read_only\"}"
            ),
            2.0
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reads_the_drive_lacks_pass_through_and_bad_shapes_stay_off_the_bus() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let (_, bus) = d.plant.drive("conveyor").unwrap();
        // The drive answers 0x01 itself for reads it lacks: 0x04, 0x01. A
        // code nobody can decode (0x41, a vendor's) is refused with 0x01 by
        // the control core, for every role, and never reaches the wire.
        assert_eq!(
            c.ask(1, &[0x04, 0x00, 0xC0, 0x00, 0x07]).await,
            [0x84, 0x01]
        );
        assert_eq!(
            c.ask(1, &[0x01, 0x00, 0x00, 0x00, 0x08]).await,
            [0x81, 0x01]
        );
        assert_eq!(c.ask(1, &[0x41, 0x10, 0x20]).await, [0xC1, 0x01]);
        // An odd address is the drive's 0x02.
        assert_eq!(c.ask(1, &read(0xC1, 1)).await, [0x83, 0x02]);
        // Diagnostics "return query data" (sub-function 0000) echoes data of
        // any length, so requests of every even length reach the drive,
        // which lacks 0x08 and says so.
        assert_eq!(
            c.ask(1, &[0x08, 0x00, 0x00, 0xA5, 0x37]).await,
            [0x88, 0x01]
        );
        let query = [0x08, 0x00, 0x00, 0x12, 0x34, 0x56, 0x78, 0x9A, 0xBC];
        assert_eq!(c.ask(1, &query).await, [0x88, 0x01]);
        let stats = bus.stats();
        assert_eq!(
            stats.transactions.get(&(0x08, Outcome::Exception)),
            Some(&2),
            "both diagnostics requests on the wire"
        );
        for function in [0x04, 0x01] {
            assert_eq!(
                stats.transactions.get(&(function, Outcome::Exception)),
                Some(&1),
                "0x{function:02X} on the wire"
            );
        }
        assert!(
            !stats.transactions.keys().any(|(f, _)| *f == 0x41),
            "0x41 reached the wire: {:?}",
            stats.transactions
        );
        // Requests whose length or quantity cannot be right for their code
        // are answered 0x03 by the gateway, as the Modbus specification
        // has a server do, without costing bus time.
        let short_block = [0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0x01, 0x2C];
        assert_eq!(c.ask(1, &short_block).await, [0x90, 0x03]);
        assert_eq!(c.ask(1, &[0x06, 0x00, 0x06]).await, [0x86, 0x03]);
        assert_eq!(c.ask(1, &read(0xC0, 126)).await, [0x83, 0x03]);
        // Diagnostics data comes in whole words; other sub-functions take one.
        assert_eq!(
            c.ask(1, &[0x08, 0x00, 0x00, 0x12, 0x34, 0x56]).await,
            [0x88, 0x03]
        );
        assert_eq!(
            c.ask(1, &[0x08, 0x00, 0x0A, 0x00, 0x00, 0x00, 0x00]).await,
            [0x88, 0x03]
        );
        let stats = bus.stats();
        assert_eq!(
            stats.transactions.get(&(0x08, Outcome::Exception)),
            Some(&2)
        );
        assert!(
            !stats
                .transactions
                .keys()
                .any(|(f, _)| *f == 0x10 || *f == 0x06)
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn broadcasts_are_answered_when_configured() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&four_drives_with("broadcast_reply = true")).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let broadcasts = d.sim().stats().broadcasts;
        // CONFIG = activate to unit 0: answered with the write's echo once sent.
        assert_eq!(c.ask(0, &write(0x0002, 0)).await, write(0x0002, 0));
        eventually(Duration::from_secs(5), "the broadcast on the wire", || {
            (d.sim().stats().broadcasts == broadcasts + 1).then_some(())
        })
        .await;
        eventually(Duration::from_secs(5), "every drive active", || {
            (1..=4)
                .all(|u| d.sim().drive(u).is_some_and(|v| v.active))
                .then_some(())
        })
        .await;
        // A read has nobody to answer it; an address broadcast on a bus of
        // four drives would give them all the same address.
        assert_eq!(c.ask(0, &read(0xC0, 7)).await, [0x83, 0x01]);
        assert_eq!(c.ask(0, &write(0x0000, 9)).await, [0x86, 0x01]);
        assert_eq!(d.sim().stats().broadcasts, broadcasts + 1);
        assert!(d.sim().drive(1).is_some());
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flooding_connection_does_not_starve_another() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let addr = d.modbus_tcp.unwrap();
        let mut flood = Raw::connect(addr).await;
        let mut other = Raw::connect(addr).await;
        // 16 pipelined reads (the default max_pipelined) queue at once...
        let bytes: Vec<u8> = (0..16u16)
            .flat_map(|t| crate::support::modbus_tcp::frame(t, 1, &read(0xC0, 7)))
            .collect();
        flood.send_bytes(&bytes).await;
        tokio::time::sleep(Duration::from_millis(5)).await;
        // ...and one read from another connection goes next in turn, not
        // after the 16: the bus queue takes turns between connections.
        other.send(500, 2, &read(0xC0, 7)).await;
        let other_done = {
            let (t, _, pdu) = other.recv().await.expect("a reply");
            assert_eq!((t, registers(&pdu).len()), (500, 7));
            Instant::now()
        };
        let mut last = Instant::now();
        for t in 0..16u16 {
            let (tid, _, _) = flood.recv().await.expect("a reply");
            assert_eq!(tid, t);
            last = Instant::now();
        }
        assert!(
            other_done < last,
            "the other connection waited for the whole flood"
        );
        d.stop().await;
    })
    .await;
}
