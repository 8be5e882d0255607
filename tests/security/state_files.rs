//! State files cannot stall a start: a 200 MB alarm file, safety journal
//! or MQTT store (made here, of valid records) is read within what the
//! daemon keeps, and the daemon serves within 2 s in under 100 MB
//! resident; SIGTERM is honoured within 2 s at any point of the start.
//!
//! Measured on the real binary in a process of its own (its memory is its
//! own: VmHWM, the peak resident set, from `/proc/<pid>/status`), from the
//! spawn to the first answer of `GET /healthz`.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use drivegate::control::alarms::book::{Alarm, AlarmKind};
use drivegate::control::alarms::file::{ALARM_FILE, AlarmRecord, FILE as ALARMS};
use drivegate::control::journal::format::{self, Action, HolderKind, ModeName, Record, crc32};
use drivegate::mqtt::store::frame;
use tokio::io::AsyncBufReadExt;
use tokio::time::Instant;

use crate::support::config::ConfigBuilder;
use crate::support::input::raw_http;

const MB: u64 = 1_000_000;
const SIZE: u64 = 200 * MB;
const LIMIT: Duration = Duration::from_secs(120);

/// Writes `header`, then frames of `record(i)` (a JSON payload whose
/// `digits` wide number at `at` is `i`, so each record is another) until
/// the file holds `SIZE` bytes.
fn write_frames(path: &Path, header: &[u8], template: &[u8], at: usize, digits: usize) {
    use std::io::Write;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path).unwrap());
    out.write_all(header).unwrap();
    let mut written = header.len() as u64;
    let mut payload = template.to_vec();
    let mut i = 10u64.pow(digits as u32 - 1);
    while written < SIZE {
        let text = i.to_string();
        payload[at..at + digits].copy_from_slice(text.as_bytes());
        out.write_all(&(payload.len() as u32).to_le_bytes())
            .unwrap();
        out.write_all(&crc32(&payload).to_le_bytes()).unwrap();
        out.write_all(&payload).unwrap();
        written += 8 + payload.len() as u64;
        i += 1;
    }
    out.flush().unwrap();
}

/// `alarms.journal` of distinct alarms, each as last written (cleared).
fn alarm_file(state: &Path) -> PathBuf {
    let alarm = Alarm {
        id: 1_000_000_000,
        kind: AlarmKind::Offline,
        bus: "sim".into(),
        drive: Some("conveyor".into()),
        code: 0,
        text: "drive \"conveyor\" does not answer its status polls".into(),
        help: "check the drive's power, its address and the RS-485 wiring".into(),
        raised_ms: 1_700_000_000_000,
        cleared_ms: Some(1_700_000_060_000),
        ack: None,
        count: 1,
        last_ms: 1_700_000_000_000,
    };
    let json = serde_json::to_vec(&AlarmRecord::Alarm(alarm)).unwrap();
    let at = find(&json, b"1000000000");
    let path = state.join(ALARMS);
    write_frames(&path, &format::header_of(ALARM_FILE), &json, at, 10);
    path
}

/// `safety.journal` of lease renewals without a clean stop (deadlines
/// long past).
fn journal(state: &Path) -> PathBuf {
    let lease = Record::Lease {
        drive: "conveyor".into(),
        owner: "scada".into(),
        holder: HolderKind::Http,
        deadline_ms: 1_000_000_000_000,
        length_ms: 1000,
        action: Action::ZeroSpeed,
        mode: ModeName::Speed,
    };
    let json = serde_json::to_vec(&lease).unwrap();
    let at = find(&json, b"1000000000000");
    let path = state.join(drivegate::control::journal::FILE);
    write_frames(&path, &format::header(), &json, at, 13);
    path
}

/// One segment of the MQTT store, of DDATA bodies.
fn mqtt_store(state: &Path) -> PathBuf {
    let dir = state.join(drivegate::mqtt::store::DIR);
    std::fs::create_dir_all(&dir).unwrap();
    let message = frame::StoredMessage {
        topic: "conveyor".into(),
        payload: vec![0x5A; 90],
        at_ms: 0,
    };
    // The body is the frame without its head; its time, 8 bytes LE, is
    // written as ASCII digits: any bytes are a valid time.
    let body = frame::encode(&message).unwrap()[8..].to_vec();
    let path = dir.join("seg-0000000000000000.mqs");
    write_frames(&path, &frame::header(), &body, 0, 8);
    path
}

fn find(haystack: &[u8], needle: &[u8]) -> usize {
    haystack
        .windows(needle.len())
        .position(|w| w == needle)
        .unwrap()
}

/// A daemon run as its own process, its log read as it comes.
struct Spawned {
    child: tokio::process::Child,
    lines: tokio::sync::mpsc::UnboundedReceiver<String>,
    log: Vec<String>,
    http: u16,
    spawned: Instant,
}

impl Spawned {
    /// `drivegate serve` of the simulated plant with its state in `state`
    /// and `extra` tables.
    fn start(dir: &Path, state: &Path, extra: &str) -> Spawned {
        let http = crate::support::ports::free_port();
        let toml = ConfigBuilder::four_drives()
            .http_listen(&format!("127.0.0.1:{http}"))
            .modbus_tcp_listen("127.0.0.1:0")
            .section("safety", &format!("state_dir = \"{}\"", state.display()))
            .tables(extra)
            .toml();
        let path = dir.join("drivegate.toml");
        std::fs::write(&path, toml).unwrap();
        let spawned = Instant::now();
        let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .arg("serve")
            .arg("--config")
            .arg(&path)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, lines) = tokio::sync::mpsc::unbounded_channel();
        tokio::spawn(async move {
            let mut read = tokio::io::BufReader::new(stderr).lines();
            while let Ok(Some(line)) = read.next_line().await {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Spawned {
            child,
            lines,
            log: Vec::new(),
            http,
            spawned,
        }
    }

    /// Waits for a log line containing `text`.
    async fn line(&mut self, text: &str) {
        if self.log.iter().any(|l| l.contains(text)) {
            return;
        }
        let found = tokio::time::timeout(Duration::from_secs(30), async {
            while let Some(line) = self.lines.recv().await {
                let found = line.contains(text);
                self.log.push(line);
                if found {
                    return true;
                }
            }
            false
        })
        .await;
        assert!(
            matches!(found, Ok(true)),
            "no log line with {text:?}: {:#?}",
            self.log
        );
    }

    /// Time from the spawn to the first `200` of `GET /healthz`.
    async fn serves(&mut self) -> Duration {
        let addr = format!("127.0.0.1:{}", self.http).parse().unwrap();
        loop {
            let answer = raw_http(
                addr,
                b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n",
            )
            .await;
            if answer.is_ok_and(|a| a.status == 200) {
                return self.spawned.elapsed();
            }
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("drivegate exited ({status}) before serving");
            }
            assert!(self.spawned.elapsed() < Duration::from_secs(30));
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// `(VmHWM, VmRSS)` of the daemon, MB.
    fn memory(&self) -> (f64, f64) {
        let pid = self.child.id().unwrap();
        let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
        let kb = |key: &str| -> f64 {
            status
                .lines()
                .find_map(|l| l.strip_prefix(key))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
                .unwrap()
        };
        (kb("VmHWM:") * 1024.0 / 1e6, kb("VmRSS:") * 1024.0 / 1e6)
    }

    /// `GET /metrics`, the value of `series`.
    async fn metric(&self, series: &str) -> f64 {
        let addr = format!("127.0.0.1:{}", self.http).parse().unwrap();
        let answer = raw_http(
            addr,
            b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n",
        )
        .await
        .unwrap();
        crate::support::metrics::exported(&answer.text(), series)
    }

    /// SIGTERM, then the time until the process exited (successfully).
    async fn terminate(mut self) -> (Duration, Vec<String>) {
        let pid = nix::unistd::Pid::from_raw(i32::try_from(self.child.id().unwrap()).unwrap());
        let sent = Instant::now();
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
        let status = tokio::time::timeout(Duration::from_secs(10), self.child.wait())
            .await
            .expect("drivegate exits within 10 s of SIGTERM")
            .unwrap();
        let took = sent.elapsed();
        while let Ok(Some(line)) =
            tokio::time::timeout(Duration::from_secs(2), self.lines.recv()).await
        {
            self.log.push(line);
        }
        assert!(status.success(), "{status}: {:#?}", self.log);
        (took, self.log)
    }
}

/// Starts the daemon on `state` (`extra` tables), checks it serves within
/// 2 s in under 100 MB resident and that `skipped` says most of the file
/// was skipped; returns the figures in words.
async fn serves_within_bounds(what: &str, state: &Path, extra: &str, skipped: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let mut d = Spawned::start(dir.path(), state, extra);
    let took = d.serves().await;
    // The MQTT store is opened as its face starts, after the API.
    let mut skipped_bytes = d.metric(skipped).await;
    while skipped_bytes == 0.0 && d.spawned.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(20)).await;
        skipped_bytes = d.metric(skipped).await;
    }
    let (peak, now) = d.memory();
    let figures = format!(
        "{what}: served in {} ms, VmHWM {peak:.1} MB, VmRSS {now:.1} MB, {skipped} {:.1} MB",
        took.as_millis(),
        skipped_bytes / 1e6
    );
    println!("{figures}");
    assert!(took < Duration::from_secs(2), "{figures}");
    assert!(peak < 100.0, "{figures}");
    assert!(skipped_bytes > (SIZE - 16 * MB) as f64, "{figures}");
    let (stopped, log) = d.terminate().await;
    assert!(
        stopped < Duration::from_secs(2),
        "{figures}; stopped in {stopped:?}"
    );
    assert!(
        log.iter().any(|l| l.contains("skipped")),
        "the skipping is logged: {log:#?}"
    );
    figures
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_200_mb_alarm_file_is_served_within_2_s_in_under_100_mb() {
    tokio::time::timeout(LIMIT, async {
        let state = tempfile::tempdir().unwrap();
        let path = alarm_file(state.path());
        serves_within_bounds(
            "200 MB alarm file",
            state.path(),
            "",
            "drivegate_alarm_file_skipped_bytes",
        )
        .await;
        // Compacted to the alarms kept (500 by default).
        let left = std::fs::metadata(&path).unwrap().len();
        assert!(left < 500 * 1024, "{left}");
        let opened = drivegate::control::alarms::file::AlarmFile::open(Some(state.path()), 500);
        assert_eq!(opened.alarms.len(), 500);
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_200_mb_safety_journal_is_served_within_2_s_in_under_100_mb() {
    tokio::time::timeout(LIMIT, async {
        let state = tempfile::tempdir().unwrap();
        let path = journal(state.path());
        serves_within_bounds(
            "200 MB safety journal",
            state.path(),
            "",
            "drivegate_safety_journal_skipped_bytes",
        )
        .await;
        assert!(std::fs::metadata(&path).unwrap().len() < 64 * 1024);
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_200_mb_mqtt_store_is_served_within_2_s_in_under_100_mb() {
    tokio::time::timeout(LIMIT, async {
        let state = tempfile::tempdir().unwrap();
        let path = mqtt_store(state.path());
        // A broker that is not there: the store is opened all the same.
        serves_within_bounds(
            "200 MB MQTT store",
            state.path(),
            "[mqtt]\nbroker = \"mqtt://127.0.0.1:1\"\nnode_id = \"gw1\"\n",
            "drivegate_mqtt_store_skipped_bytes",
        )
        .await;
        // Cut to a segment of the default bound (64 MB / 8).
        let left = std::fs::metadata(&path).unwrap().len();
        assert!(left <= 9 * 1024 * 1024, "{left}");
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_is_honoured_at_any_point_of_the_start() {
    tokio::time::timeout(LIMIT, async {
        // Big state files of all three kinds, copied afresh for each start
        // (a start compacts them).
        let big = tempfile::tempdir().unwrap();
        let files = [
            alarm_file(big.path()),
            journal(big.path()),
            mqtt_store(big.path()),
        ];
        let mqtt = "[mqtt]\nbroker = \"mqtt://127.0.0.1:1\"\nnode_id = \"gw1\"\n";
        let mut figures = Vec::new();
        // Each a moment of the start, by the log line that marks it.
        for at in [
            "built-in simulator running",
            "reading it from its end",
            concat!("drivegate ", env!("CARGO_PKG_VERSION"), " running"),
            "HTTP API listening",
            "Modbus TCP listening",
        ] {
            let state = tempfile::tempdir().unwrap();
            for f in &files {
                let to = state.path().join(f.strip_prefix(big.path()).unwrap());
                std::fs::create_dir_all(to.parent().unwrap()).unwrap();
                std::fs::copy(f, to).unwrap();
            }
            let dir = tempfile::tempdir().unwrap();
            let mut d = Spawned::start(dir.path(), state.path(), mqtt);
            d.line(at).await;
            let (took, log) = d.terminate().await;
            figures.push(format!("{at:?}: {} ms", took.as_millis()));
            assert!(
                took < Duration::from_secs(2),
                "SIGTERM at {at:?} took {took:?}: {log:#?}"
            );
            assert!(
                log.iter()
                    .any(|l| l.contains("stopped") || l.contains("during the start")),
                "{log:#?}"
            );
        }
        println!(
            "SIGTERM during the start, to the exit: {}",
            figures.join(", ")
        );
    })
    .await
    .expect("test finished in time");
}
