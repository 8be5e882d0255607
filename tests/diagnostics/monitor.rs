//! The bus monitor against the daemon on the simulator, over real sockets:
//! every frame says who caused it (the poller, an HTTP token, a WebSocket
//! session, a Modbus TCP peer and transaction); filters; the CSV parses
//! with its columns; `tshark` reads the PCAP and decodes the units and
//! functions that were on the wire; a live client that never reads does
//! not slow the bus and is told what it lost; and with 5 % of the replies
//! corrupted the per-attempt CRC counter matches the simulator's count.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use crate::support::api::{Api, connect, next_json, ws_command};
use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::csv::csv_fields;
use crate::support::modbus_tcp::Raw;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::sim::FaultRates;
use futures_util::StreamExt;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

const LIMIT: Duration = Duration::from_secs(150);
const FRAMES: &str = "/api/v1/buses/sim/monitor/frames";

fn frames(reply: &Value) -> Vec<Value> {
    reply["frames"].as_array().unwrap().clone()
}

/// The reply frame that follows the request frame `request` (same unit,
/// attempt and source, next in the sequence).
fn reply_to<'a>(all: &'a [Value], request: &Value) -> &'a Value {
    let seq = request["seq"].as_u64().unwrap();
    let reply = all
        .iter()
        .find(|f| f["seq"].as_u64() == Some(seq + 1))
        .unwrap_or_else(|| panic!("no frame after {request:#}"));
    assert_eq!(reply["direction"], "reply", "{reply:#}");
    assert_eq!(reply["unit"], request["unit"]);
    assert_eq!(reply["source"], request["source"]);
    reply
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_frame_says_who_caused_it() {
    bounded(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .http_token("panel", "operator", "panel-token")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, Some("panel-token"));

        // REST: activate the conveyor with the token "panel".
        api.command("conveyor", "activate").await;
        // WebSocket: activate the lift from a stream session.
        let mut ws = connect(d.http, "", Some("panel-token")).await;
        let reply = ws_command(&mut ws, 1, "activate", "lift", json!({})).await;
        assert_eq!(reply["ok"], true, "{reply:#}");
        // Modbus TCP: activate the feeder (unit 4), transaction 0x0042.
        let mut tcp = Raw::connect(d.modbus_tcp.unwrap()).await;
        let peer = tcp.stream.local_addr().unwrap().to_string();
        let echo = tcp.ask_as(0x42, 4, &[0x06, 0x00, 0x02, 0x00, 0x00]).await;
        assert_eq!(echo, [0x06, 0x00, 0x02, 0x00, 0x00]);

        let all = frames(&api.get(&format!("{FRAMES}?limit=100000")).await.expect(200));
        let writes: Vec<&Value> = all
            .iter()
            .filter(|f| f["direction"] == "request" && f["function"] == 6)
            .collect();
        assert_eq!(writes.len(), 3, "{writes:#?}");
        let by_unit = |unit: u64| *writes.iter().find(|f| f["unit"] == unit).unwrap();

        let rest = by_unit(1);
        assert_eq!(
            (rest["source"].as_str(), rest["source_who"].as_str()),
            (Some("http"), Some("panel"))
        );
        assert_eq!(rest["meaning"], "command activate");
        assert_eq!(rest["bytes"], "01 06 00 02 00 00 28 0A");
        assert_eq!(
            (rest["crc"].as_str(), rest["decoded_as"].as_str()),
            (Some("ok"), Some("drive"))
        );
        let answer = reply_to(&all, rest);
        assert_eq!(answer["outcome"], "ok");
        assert_eq!(answer["meaning"], "confirmed: command activate");
        assert!(answer["turnaround_us"].as_u64().is_some());

        let stream = by_unit(2);
        assert_eq!(stream["source"], "websocket");
        assert_eq!(stream["source_who"], "panel");
        assert!(stream["source_ref"].as_u64().is_some(), "the session");
        assert!(
            stream["source_text"]
                .as_str()
                .unwrap()
                .starts_with("WebSocket panel (session ")
        );

        let scada = by_unit(4);
        assert_eq!(scada["source"], "modbus-tcp");
        assert_eq!(scada["source_who"], peer);
        assert_eq!(scada["source_ref"], 0x42);
        assert_eq!(
            scada["source_text"],
            format!("Modbus TCP {peer} (transaction 66)")
        );
        assert_eq!(
            reply_to(&all, scada)["meaning"],
            "confirmed: command activate"
        );

        // The poller's frames: the status read and the status.
        let poll = all
            .iter()
            .find(|f| f["source"] == "poller" && f["direction"] == "request" && f["unit"] == 3)
            .unwrap();
        assert_eq!(poll["meaning"], "read status");
        let status = reply_to(&all, poll);
        assert!(
            status["meaning"].as_str().unwrap().starts_with("status: "),
            "{status:#}"
        );

        // Filters: a unit and a source; an unknown outcome is refused.
        let only = frames(
            &api.get(&format!("{FRAMES}?unit=4&source=modbus-tcp"))
                .await
                .expect(200),
        );
        assert_eq!(only.len(), 2, "the write and its echo: {only:#?}");
        assert!(
            only.iter()
                .all(|f| f["unit"] == 4 && f["source"] == "modbus-tcp")
        );
        let who = frames(&api.get(&format!("{FRAMES}?who=panel")).await.expect(200));
        assert_eq!(who.len(), 4);
        let p = api
            .get(&format!("{FRAMES}?outcome=late"))
            .await
            .expect_problem(400, "invalid-request");
        assert!(p["detail"].as_str().unwrap().contains("crc_error"));

        // Paging: from a sequence number on.
        let first = frames(&api.get(&format!("{FRAMES}?limit=5")).await.expect(200));
        let from = first[0]["seq"].as_u64().unwrap();
        let page = api
            .get(&format!("{FRAMES}?from={from}&limit=3"))
            .await
            .expect(200);
        let seqs: Vec<u64> = frames(&page)
            .iter()
            .map(|f| f["seq"].as_u64().unwrap())
            .collect();
        assert_eq!(seqs, [from, from + 1, from + 2]);
        assert_eq!(page["next"], from + 3);

        // The monitor's own view: the per-attempt counters of every drive.
        let view = api.get("/api/v1/buses/sim/monitor").await.expect(200);
        assert_eq!(view["enabled"], true);
        assert_eq!(view["ring_frames"], 10_000);
        let units: Vec<u64> = view["units"]
            .as_array()
            .unwrap()
            .iter()
            .map(|u| u["unit"].as_u64().unwrap())
            .collect();
        assert_eq!(units, [1, 2, 3, 4]);
        assert!(view["units"][0]["attempts"].as_u64().unwrap() > 0);
        assert_eq!(view["units"][0]["drive"], "conveyor");

        // A lease that runs out: its stop is the lease's, naming its owner.
        api.put("/api/v1/drives/conveyor/mode", json!({"mode": "speed"}))
            .await
            .expect(200);
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 50, "lease_ms": 200}),
        )
        .await
        .expect(200);
        let deadline = Instant::now() + Duration::from_secs(10);
        let stop = loop {
            let found = frames(
                &api.get(&format!(
                    "{FRAMES}?source=lease-expiry&outcome=sent&function=6"
                ))
                .await
                .expect(200),
            );
            if let Some(f) = found.into_iter().next() {
                break f;
            }
            assert!(Instant::now() < deadline, "no stop from the lease's end");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert_eq!(stop["source_who"], "panel");
        assert_eq!(stop["meaning"], "speed setpoint 0 rpm");

        // The shutdown's safe stop of a moving drive.
        api.put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": 30}))
            .await
            .expect(200);
        let monitor = d.plant.buses()[0].monitor().clone();
        d.stop().await;
        let clock = *monitor.clock();
        let last: Vec<_> = monitor
            .last(200)
            .iter()
            .map(|r| drivegate::monitor::view::FrameView::new(r, &clock))
            .collect();
        assert!(
            last.iter().any(|f| f.source == "shutdown"
                && f.direction == "request"
                && f.meaning == "speed setpoint 0 rpm"),
            "no safe stop from the shutdown among the last frames"
        );
    })
    .await;
}

async fn text(url: String) -> (String, Vec<u8>) {
    let response = reqwest::get(url).await.unwrap();
    assert_eq!(response.status(), 200);
    let content_type = response
        .headers()
        .get("content-type")
        .unwrap()
        .to_str()
        .unwrap()
        .to_string();
    (content_type, response.bytes().await.unwrap().to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn csv_and_a_pcap_that_tshark_decodes() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);
        // Three function codes on the wire: polls (0x03), a command (0x06)
        // and a protection block (0x10).
        api.command("conveyor", "activate").await;
        api.put(
            "/api/v1/drives/lift/protection",
            json!({"limit_a": 10.0, "stall_ms": 2000}),
        )
        .await
        .expect(200);
        let json = api.get(&format!("{FRAMES}?limit=300")).await.expect(200);
        let listed = frames(&json);
        let from = listed[0]["seq"].as_u64().unwrap();
        let selection = format!("from={from}&limit={}", listed.len());

        // CSV: the header, and every line with as many fields.
        let (content_type, body) = text(d.url(&format!("{FRAMES}.csv?{selection}"))).await;
        assert!(content_type.starts_with("text/csv"), "{content_type}");
        let csv = String::from_utf8(body).unwrap();
        let mut lines = csv.lines();
        let header = csv_fields(lines.next().unwrap());
        assert_eq!(
            header,
            [
                "seq",
                "time",
                "time_us",
                "direction",
                "unit",
                "function",
                "bytes",
                "length",
                "meaning",
                "decoded_as",
                "crc",
                "outcome",
                "detail",
                "attempt",
                "turnaround_us",
                "wire_us",
                "source",
                "source_who",
                "source_ref",
                "silence_us"
            ]
        );
        let rows: Vec<Vec<String>> = lines.map(csv_fields).collect();
        assert_eq!(rows.len(), listed.len());
        for (row, frame) in rows.iter().zip(&listed) {
            assert_eq!(row.len(), header.len(), "{row:?}");
            assert_eq!(row[0], frame["seq"].to_string());
            assert_eq!(row[8], frame["meaning"].as_str().unwrap());
            assert!(row[1].ends_with('Z'));
            let _: u64 = row[2].parse().unwrap();
            assert!(["request", "reply", "noise"].contains(&row[3].as_str()));
            let bytes = row[6].split(' ').count();
            assert_eq!(row[7].parse::<usize>().unwrap(), bytes);
        }
        assert!(
            rows.iter()
                .any(|r| r[8].contains("over-current protection 10.00 A for 2000 ms"))
        );

        // PCAP: what tshark makes of it.
        let (content_type, pcap) = text(d.url(&format!("{FRAMES}.pcap?{selection}"))).await;
        assert_eq!(content_type, "application/vnd.tcpdump.pcap");
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("sim.pcap");
        std::fs::write(&file, &pcap).unwrap();
        let out = tokio::time::timeout(
            Duration::from_secs(30),
            tokio::process::Command::new("tshark")
                .arg("-r")
                .arg(&file)
                .args([
                    "-o",
                    "mbrtu.udp.port:502",
                    "-T",
                    "fields",
                    "-E",
                    "separator=,",
                ])
                .args([
                    "-e",
                    "udp.dstport",
                    "-e",
                    "mbrtu.unit_id",
                    "-e",
                    "modbus.func_code",
                ])
                .args(["-e", "mbrtu.crc16.status", "-e", "_ws.col.Info"])
                .kill_on_drop(true)
                .output(),
        )
        .await
        .expect("tshark in time")
        .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("tshark", &e)));
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let decoded = String::from_utf8(out.stdout).unwrap();
        let packets: Vec<Vec<&str>> = decoded
            .lines()
            .map(|l| l.splitn(5, ',').collect())
            .collect();
        let on_wire: Vec<&Value> = listed.iter().filter(|f| f["length"] != 0).collect();
        assert_eq!(packets.len(), on_wire.len(), "{decoded}");
        let mut seen = BTreeSet::new();
        for (packet, frame) in packets.iter().zip(&on_wire) {
            let request = frame["direction"] == "request";
            assert_eq!(
                packet[0],
                if request { "502" } else { "49152" },
                "{packet:?}"
            );
            assert_eq!(packet[1], frame["unit"].to_string(), "{packet:?} {frame:#}");
            assert_eq!(
                packet[2],
                frame["function"].to_string(),
                "{packet:?} {frame:#}"
            );
            assert!(
                packet[4].contains(if request { "Query" } else { "Response" }),
                "{packet:?}"
            );
            seen.insert((packet[1].to_string(), packet[2].to_string()));
        }
        for wanted in [("1", "6"), ("2", "16"), ("3", "3"), ("4", "3")] {
            assert!(
                seen.contains(&(wanted.0.to_string(), wanted.1.to_string())),
                "tshark did not see unit {} function {}: {seen:?}",
                wanted.0,
                wanted.1
            );
        }
        d.stop().await;
    })
    .await;
}

/// Opens the live feed on a socket with a small receive buffer (16 KiB), so
/// that a client that does not read is stuck within a fraction of a
/// second. Not the smallest the kernel allows: a buffer smaller than a
/// segment (1 KiB asked, 2.3 KiB given) never advertises an open window
/// when its reader empties it, so the daemon's kernel can only send
/// through it by its window probes, a few hundred bytes every 0.2 s. A
/// message of a few hundred frames (tens of kilobytes) queued before the
/// client stopped reading then takes longer to arrive than the test waits,
/// whatever the daemon does.
async fn live_stuck(addr: std::net::SocketAddr, query: &str) -> crate::support::api::Ws {
    let socket = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
    socket.set_recv_buffer_size(16 * 1024).unwrap();
    socket.connect(&addr.into()).unwrap();
    socket.set_nonblocking(true).unwrap();
    let stream = tokio::net::TcpStream::from_std(socket.into()).unwrap();
    let request = format!("ws://{addr}/api/v1/buses/sim/monitor/live{query}")
        .into_client_request()
        .unwrap();
    let (ws, _) =
        tokio_tungstenite::client_async(request, tokio_tungstenite::MaybeTlsStream::Plain(stream))
            .await
            .expect("WebSocket connects");
    ws
}

/// Status polls per second of the bus over the last `window` of frames,
/// from the times the bus thread gave them.
async fn poll_rate(api: &Api, after: u64) -> (f64, u64) {
    let page = api
        .get(&format!(
            "{FRAMES}?from={after}&outcome=sent&function=3&limit=100000"
        ))
        .await
        .expect(200);
    let times: Vec<u64> = frames(&page)
        .iter()
        .map(|f| f["time_us"].as_u64().unwrap())
        .collect();
    let span = (times.last().unwrap() - times[0]) as f64 / 1e6;
    (
        (times.len() - 1) as f64 / span,
        page["next"].as_u64().unwrap(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_live_client_that_never_reads_loses_frames_not_the_bus_its_pace() {
    bounded(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .http("send_buffer_bytes = 4096")
            .section("monitor", "ring_frames = 256")
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        let monitor = d.plant.buses()[0].monitor().clone();
        let frames_seen = || monitor.frames();

        // The bus's pace with no client: one second of polls.
        let start = frames_seen();
        eventually(Duration::from_secs(10), "a second of frames", || {
            (frames_seen() > start + 300).then_some(())
        })
        .await;
        let (alone, _) = poll_rate(&api, start).await;

        // One client that never reads, one that reads.
        let mut stuck = live_stuck(d.http, "?backlog=0").await;
        let (mut reader, _) = tokio_tungstenite::connect_async(format!(
            "ws://{}/api/v1/buses/sim/monitor/live?backlog=0",
            d.http
        ))
        .await
        .unwrap();
        assert_eq!(
            next_json(&mut reader, Duration::from_secs(5)).await["type"],
            "state"
        );
        eventually(Duration::from_secs(5), "two live clients", || {
            (monitor.clients() == 2).then_some(())
        })
        .await;

        // While the stuck client holds its socket unread, the ring goes
        // round several times and the reading client loses nothing.
        let during = frames_seen();
        let mut read = 0u64;
        while frames_seen() < during + 5 * 256 {
            let m = next_json(&mut reader, Duration::from_secs(5)).await;
            if m["type"] == "frames" {
                assert_eq!(m["lost"], 0, "{m:#}");
                read += m["frames"].as_array().unwrap().len() as u64;
            }
        }
        assert!(read > 3 * 256, "the reading client got {read} frames");
        // The bus went on at its pace: a coarse check, as a loaded machine
        // moves both figures (benches/scope.rs measures the cost of live
        // clients); what cannot move is that the ring went round five times
        // while the stuck client held its socket.
        let (with_clients, _) = poll_rate(&api, frames_seen() - 256).await;
        assert!(
            with_clients > 0.5 * alone,
            "{with_clients:.1} polls/s with a stuck client, {alone:.1} without"
        );

        // When it reads again, it is told how many it lost. Its socket
        // was full for as long as the ring took to go round (longer on a
        // loaded machine): what the daemon queued before is read first.
        let deadline = Instant::now() + Duration::from_secs(60);
        let lost = loop {
            assert!(Instant::now() < deadline, "never told what it lost");
            let m = tokio::time::timeout(Duration::from_secs(30), stuck.next())
                .await
                .expect("a message")
                .unwrap()
                .unwrap();
            let Message::Text(text) = m else { continue };
            let m: Value = serde_json::from_str(text.as_str()).unwrap();
            if m["type"] == "frames" && m["lost"].as_u64().unwrap() > 0 {
                break m["lost_total"].as_u64().unwrap();
            }
        };
        assert!(lost > 256, "lost {lost}");
        assert!(monitor.lost() >= lost);
        let text = d.metrics.render();
        assert!(
            text.lines().any(
                |l| l.starts_with("drivegate_monitor_lost_frames_total{bus=\"sim\"}")
                    && !l.ends_with(" 0")
            ),
            "the lost frames are in /metrics"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_five_percent_corrupted_the_per_attempt_count_matches_the_simulator() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let bus = d.plant.buses()[0].handle.clone();
        let sim = d.sim();
        let before = (sim.stats().corrupted, bus.stats());
        let monitor = d.plant.buses()[0].monitor().clone();
        let counted = || -> u64 { (1..=4).map(|u| monitor.counters().unit(u).crc_errors).sum() };
        let counted_before = counted();
        sim.set_fault_rates(FaultRates {
            crc_error_rate: 0.05,
            ..FaultRates::default()
        })
        .unwrap();
        // About 2000 replies: 12 s on an idle machine, much longer on a
        // loaded one, whose timers stretch every transaction.
        eventually(Duration::from_secs(100), "100 corrupted replies", || {
            (sim.stats().corrupted - before.0 >= 100).then_some(())
        })
        .await;
        sim.set_fault_rates(FaultRates::default()).unwrap();
        // The reply in flight has landed once the master sent two more
        // requests: it keeps one frame in flight.
        let requests = sim.stats().requests;
        eventually(Duration::from_secs(10), "two more requests", || {
            (sim.stats().requests >= requests + 2).then_some(())
        })
        .await;
        let injected = sim.stats().corrupted - before.0;
        let per_attempt = counted() - counted_before;
        let diff = (per_attempt as f64 - injected as f64).abs();
        assert!(
            diff <= 0.03 * injected as f64 + 2.0,
            "the simulator corrupted {injected} replies, the per-attempt counter says {per_attempt}"
        );
        // The transaction outcome hides most of them: the retry made good.
        let per_transaction = bus.stats().count(drivegate::bus::stats::Outcome::CrcError)
            - before.1.count(drivegate::bus::stats::Outcome::CrcError);
        assert!(
            (per_transaction as f64) < 0.2 * injected as f64,
            "{per_transaction} transactions ended with a CRC error"
        );
        // The same count in /metrics.
        let text = d.metrics.render();
        let exported: f64 = text
            .lines()
            .filter(|l| {
                l.starts_with("drivegate_bus_wire_errors_total{")
                    && l.contains("error=\"crc_error\"")
            })
            .map(|l| l.rsplit(' ').next().unwrap().parse::<f64>().unwrap())
            .sum();
        assert_eq!(exported as u64, counted());
        d.stop().await;
    })
    .await;
}
