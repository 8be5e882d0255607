//! The fleet benchmark: 16 drivegate daemons (processes of the built
//! binary), each with one simulated bus of 8 drives at 115200 baud polled
//! as fast as the wire allows, all publishing Sparkplug B to one mosquitto
//! on this machine, and one host subscribed to the whole group.
//!
//! It measures what a SCADA host sees:
//! - births: how long after the daemons were started every NBIRTH and
//!   every DBIRTH had arrived;
//! - DDATA: messages and metrics per second over the measured window, with
//!   every drive turning (so every poll changes the angle beyond its
//!   deadband);
//! - latency from the poll on the wire to the message at the host: each
//!   DDATA metric carries the poll's time as its Sparkplug timestamp (ms),
//!   compared with the host's clock when the message arrives (same
//!   machine, same clock); p50, p99 and the maximum;
//! - CPU (share of one core) and resident memory of each daemon, from
//!   `/proc/<pid>/stat` and `/proc/<pid>/status`;
//! - a broker restart: mosquitto stopped for 5 s and started again; the
//!   data of those seconds comes back from each daemon's store marked
//!   historical. For each drive, the largest gap between the data
//!   timestamps the host holds around the outage, live and historical
//!   together, against the largest gap in the quiet window: a gap much
//!   longer than the poll period is data lost.
//!
//! `cargo bench --bench mqtt_fleet`; environment: `DRIVEGATE_BENCH_SECS`
//! (the measured window, default 10), `DRIVEGATE_FLEET_DAEMONS` (16),
//! `DRIVEGATE_FLEET_SVG` (a path: the host's view of the fleet drawn
//! there, as in `docs/mqtt-fleet.svg`). Needs Debian's `mosquitto`.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use drivegate::mqtt::sparkplug_b::Payload;
use prost::Message;
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};

const DRIVES: u8 = 8;
const BAUD: u32 = 115_200;
const GROUP: &str = "fleet";
/// The outage of the broker restart.
const OUTAGE: Duration = Duration::from_secs(5);
/// Speed setpoint of every drive, rpm.
const SPEED_RPM: i64 = 100;

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// mosquitto on a loopback port.
struct Broker {
    conf: PathBuf,
    port: u16,
    child: Option<Child>,
}

impl Broker {
    fn new(dir: &Path) -> Broker {
        let port = free_port();
        let conf = dir.join("mosquitto.conf");
        // The host must not be cut off for being slow: no limit on the
        // messages queued for it.
        std::fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\nallow_anonymous true\nmax_queued_messages 0\nmax_inflight_messages 0\n"
            ),
        )
        .unwrap();
        let mut b = Broker {
            conf,
            port,
            child: None,
        };
        b.start();
        b
    }

    fn start(&mut self) {
        let child = Command::new("/usr/sbin/mosquitto")
            .arg("-c")
            .arg(&self.conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto (apt-get install mosquitto)");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < deadline, "mosquitto did not listen");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(c.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
            let _ = c.wait();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.stop();
    }
}

/// One daemon of the fleet.
struct Daemon {
    http: u16,
    child: Child,
}

impl Daemon {
    fn spawn(dir: &Path, i: usize, broker: u16) -> Daemon {
        let node = format!("gw{i:02}");
        let http = free_port();
        let state = dir.join(&node);
        std::fs::create_dir_all(&state).unwrap();
        let mut toml = format!(
            "[http]\nlisten = \"127.0.0.1:{http}\"\n[modbus_tcp]\nenabled = false\n\
             [log]\nlevel = \"warn\"\n\
             [safety]\nstate_dir = \"{}\"\non_shutdown = \"none\"\n\
             [mqtt]\nbroker = \"mqtt://127.0.0.1:{broker}\"\ngroup_id = \"{GROUP}\"\nnode_id = \"{node}\"\n\
             [[bus]]\nname = \"line\"\nport = \"sim\"\nbaud = {BAUD}\npoll_interval_ms = 0\n\
             [bus.sim]\nseed = {i}\n",
            state.display()
        );
        for unit in 1..=DRIVES {
            let _ = write!(toml, "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\n");
        }
        let file = dir.join(format!("{node}.toml"));
        std::fs::write(&file, toml).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .args(["serve", "--config"])
            .arg(&file)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join(format!("{node}.log"))).unwrap())
            .spawn()
            .unwrap();
        Daemon { http, child }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    /// CPU seconds (user + system) so far.
    fn cpu_s(&self) -> f64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.pid())).unwrap_or_default();
        // Fields after the command's closing parenthesis; utime and stime
        // are the 14th and 15th of the whole line.
        let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
        let f: Vec<&str> = rest.split_whitespace().collect();
        let ticks: f64 = f.get(11).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0)
            + f.get(12).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        // /proc counts in USER_HZ, 100 on Linux whatever the kernel's HZ.
        ticks / 100.0
    }

    /// Resident memory, MiB.
    fn rss_mib(&self) -> f64 {
        let status =
            std::fs::read_to_string(format!("/proc/{}/status", self.pid())).unwrap_or_default();
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|kb| kb.parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    }

    fn stop(&mut self) {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.pid() as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
        let _ = self.child.wait();
    }
}

/// What the host has seen.
#[derive(Default)]
struct Seen {
    nbirth: HashMap<String, Instant>,
    dbirth: HashMap<(String, String), Instant>,
    /// DDATA messages (live, historical) and metrics.
    ddata: u64,
    historical: u64,
    metrics: u64,
    /// Live DDATA latencies, ms, while `measuring`.
    latencies: Vec<i64>,
    measuring: bool,
    /// Per drive, the data timestamps (ms) and whether historical.
    samples: HashMap<(String, String), Vec<(u64, bool)>>,
    /// DDATA messages received while measuring.
    window_ddata: u64,
    window_metrics: u64,
}

async fn host(port: u16, seen: Arc<Mutex<Seen>>) {
    let mut options = MqttOptions::new("fleet-host", "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(5));
    options.set_max_packet_size(1 << 20, 1 << 20);
    let (client, mut events) = AsyncClient::new(options, 100_000);
    let filter = format!("spBv1.0/{GROUP}/#");
    loop {
        match events.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                // A clean session: subscribe on every connection.
                client
                    .subscribe(filter.clone(), QoS::AtMostOnce)
                    .await
                    .unwrap();
            }
            Ok(Event::Incoming(Packet::Publish(p))) => {
                let now = unix_ms();
                let at = Instant::now();
                let parts: Vec<&str> = p.topic.split('/').collect();
                let (Some(kind), Some(node)) = (parts.get(2), parts.get(3)) else {
                    continue;
                };
                let device = parts.get(4).map(|d| d.to_string());
                let mut s = seen.lock().unwrap();
                match (*kind, device) {
                    ("NBIRTH", _) => {
                        s.nbirth.entry(node.to_string()).or_insert(at);
                    }
                    ("DBIRTH", Some(d)) => {
                        s.dbirth.entry((node.to_string(), d)).or_insert(at);
                    }
                    ("DDATA", Some(d)) => {
                        let Ok(payload) = Payload::decode(&p.payload[..]) else {
                            continue;
                        };
                        let historical = payload
                            .metrics
                            .iter()
                            .any(|m| m.is_historical == Some(true));
                        let ts = payload.metrics.iter().filter_map(|m| m.timestamp).max();
                        s.ddata += 1;
                        s.metrics += payload.metrics.len() as u64;
                        if historical {
                            s.historical += 1;
                        }
                        if s.measuring {
                            s.window_ddata += 1;
                            s.window_metrics += payload.metrics.len() as u64;
                            if let (false, Some(ts)) = (historical, ts) {
                                s.latencies.push(now as i64 - ts as i64);
                            }
                        }
                        // Only the drive's own polls (not command results).
                        let polled = payload
                            .metrics
                            .iter()
                            .any(|m| m.name.as_deref().is_some_and(|n| n.starts_with("status/")));
                        if let (true, Some(ts)) = (polled, ts) {
                            s.samples
                                .entry((node.to_string(), d))
                                .or_default()
                                .push((ts, historical));
                        }
                    }
                    _ => {}
                }
            }
            Ok(_) => {}
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

/// Activates every drive of a daemon and turns it at [`SPEED_RPM`].
async fn turn(client: &reqwest::Client, d: &Daemon) {
    for unit in 1..=DRIVES {
        let base = format!("http://127.0.0.1:{}/api/v1/drives/d{unit}", d.http);
        for attempt in 0..50 {
            let ok = async {
                let a = client
                    .post(format!("{base}/commands/activate"))
                    .send()
                    .await
                    .ok()?;
                if !a.status().is_success() {
                    return Some(Err(format!("activate: {}", a.text().await.ok()?)));
                }
                let m = client
                    .put(format!("{base}/mode"))
                    .json(&serde_json::json!({ "mode": "speed" }))
                    .send()
                    .await
                    .ok()?;
                if !m.status().is_success() {
                    return Some(Err(format!("mode: {}", m.text().await.ok()?)));
                }
                let s = client
                    .put(format!("{base}/setpoint"))
                    .json(&serde_json::json!({ "speed_rpm": SPEED_RPM }))
                    .send()
                    .await
                    .ok()?;
                if !s.status().is_success() {
                    return Some(Err(format!("setpoint: {}", s.text().await.ok()?)));
                }
                Some(Ok(()))
            }
            .await;
            match ok {
                Some(Ok(())) => break,
                Some(Err(e)) if attempt == 49 => panic!("d{unit} does not turn: {e}"),
                _ => {}
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

/// A series of `drivegate_*` from a daemon's `/metrics` (summed over labels).
async fn metric(client: &reqwest::Client, d: &Daemon, name: &str) -> Option<f64> {
    let text = client
        .get(format!("http://127.0.0.1:{}/metrics", d.http))
        .send()
        .await
        .ok()?
        .text()
        .await
        .ok()?;
    let mut sum = None;
    for line in text.lines() {
        let Some(rest) = line.strip_prefix(name) else {
            continue;
        };
        if !(rest.starts_with(' ') || rest.starts_with('{')) {
            continue;
        }
        let v: f64 = rest.rsplit(' ').next()?.parse().ok()?;
        *sum.get_or_insert(0.0) += v;
    }
    sum
}

fn percentile(sorted: &[i64], p: f64) -> i64 {
    if sorted.is_empty() {
        return 0;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

/// The largest gap between consecutive data timestamps in `[from, to]`.
fn largest_gap(samples: &[(u64, bool)], from: u64, to: u64) -> u64 {
    let mut ts: Vec<u64> = samples
        .iter()
        .map(|(t, _)| *t)
        .filter(|t| (from..=to).contains(t))
        .collect();
    ts.sort_unstable();
    ts.dedup();
    let mut gap = 0;
    let mut last = from;
    for t in ts {
        gap = gap.max(t - last);
        last = t;
    }
    gap.max(to - last)
}

fn main() {
    let secs: u64 = env("DRIVEGATE_BENCH_SECS", 10);
    let n: usize = env("DRIVEGATE_FLEET_DAEMONS", 16);
    let svg: Option<PathBuf> = std::env::var_os("DRIVEGATE_FLEET_SVG").map(PathBuf::from);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut broker = Broker::new(dir.path());
    println!(
        "MQTT fleet benchmark: {n} daemons x {DRIVES} simulated drives at {BAUD} baud (polled flat out), \
         one mosquitto on 127.0.0.1:{}, {secs} s measured; load average before: {}",
        broker.port,
        load_average()
    );
    let seen = Arc::new(Mutex::new(Seen::default()));
    runtime.spawn(host(broker.port, seen.clone()));
    // The host is subscribed before the first daemon starts.
    std::thread::sleep(Duration::from_millis(500));

    let start = Instant::now();
    let mut daemons: Vec<Daemon> = (0..n)
        .map(|i| Daemon::spawn(dir.path(), i, broker.port))
        .collect();
    let births = loop {
        {
            let s = seen.lock().unwrap();
            if s.nbirth.len() == n && s.dbirth.len() == n * DRIVES as usize {
                let last_n = s.nbirth.values().max().unwrap().duration_since(start);
                let last_d = s.dbirth.values().max().unwrap().duration_since(start);
                break Some((last_n, last_d));
            }
        }
        if start.elapsed() > Duration::from_secs(120) {
            let s = seen.lock().unwrap();
            println!(
                "births: only {} NBIRTH and {} DBIRTH within 120 s",
                s.nbirth.len(),
                s.dbirth.len()
            );
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    if let Some((nb, db)) = births {
        println!(
            "births: all {n} NBIRTH within {:.2} s of start, all {} DBIRTH within {:.2} s",
            nb.as_secs_f64(),
            n * DRIVES as usize,
            db.as_secs_f64()
        );
    }

    let http = reqwest::Client::new();
    runtime.block_on(async {
        futures_util::future::join_all(daemons.iter().map(|d| turn(&http, d))).await;
    });
    // Let the drives reach their speed.
    std::thread::sleep(Duration::from_secs(2));

    // The quiet window.
    let cpu0: Vec<f64> = daemons.iter().map(Daemon::cpu_s).collect();
    let window_start = unix_ms();
    seen.lock().unwrap().measuring = true;
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_secs(secs));
    seen.lock().unwrap().measuring = false;
    let elapsed = t0.elapsed().as_secs_f64();
    let window_end = unix_ms();
    let cpu: Vec<f64> = daemons
        .iter()
        .zip(&cpu0)
        .map(|(d, c0)| (d.cpu_s() - c0) / elapsed)
        .collect();
    let rss: Vec<f64> = daemons.iter().map(Daemon::rss_mib).collect();
    let load_during = load_average();
    {
        let mut s = seen.lock().unwrap();
        s.latencies.sort_unstable();
        let l = &s.latencies;
        println!(
            "DDATA: {:.0} messages/s, {:.0} metrics/s over {elapsed:.1} s ({:.0} per daemon, {:.1} per drive)",
            s.window_ddata as f64 / elapsed,
            s.window_metrics as f64 / elapsed,
            s.window_ddata as f64 / elapsed / n as f64,
            s.window_ddata as f64 / elapsed / (n * DRIVES as usize) as f64,
        );
        println!(
            "latency, poll to host (ms, metric timestamps in ms): p50 {} p99 {} max {} over {} messages",
            percentile(l, 0.5),
            percentile(l, 0.99),
            l.last().copied().unwrap_or(0),
            l.len()
        );
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    println!(
        "per daemon: CPU {:.1} % of a core (max {:.1} %), resident memory {:.1} MiB (max {:.1} MiB); load average during: {load_during}",
        100.0 * mean(&cpu),
        100.0 * max(&cpu),
        mean(&rss),
        max(&rss)
    );
    let quiet_gap: u64 = {
        let s = seen.lock().unwrap();
        s.samples
            .values()
            .map(|v| largest_gap(v, window_start, window_end))
            .max()
            .unwrap_or(0)
    };

    // The broker restart.
    let historical_before = seen.lock().unwrap().historical;
    let outage_start = unix_ms();
    broker.stop();
    std::thread::sleep(OUTAGE);
    broker.start();
    let outage_end = unix_ms();
    let back = Instant::now();
    // Until every daemon is connected again and its store empty.
    let replayed = runtime.block_on(async {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let mut done = true;
            for d in &daemons {
                let connected = metric(&http, d, "drivegate_mqtt_connected").await;
                let stored = metric(&http, d, "drivegate_mqtt_store_messages").await;
                if connected != Some(1.0) || stored != Some(0.0) {
                    done = false;
                    break;
                }
            }
            if done {
                return Some(Instant::now());
            }
            if Instant::now() > deadline {
                return None;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    });
    // What was handed to the broker last reaches the host.
    std::thread::sleep(Duration::from_secs(1));
    let dropped = runtime.block_on(async {
        let mut sum = 0.0;
        for d in &daemons {
            sum += metric(&http, d, "drivegate_mqtt_store_dropped_total")
                .await
                .unwrap_or(0.0);
        }
        sum
    });
    let (gaps, historical) = {
        let s = seen.lock().unwrap();
        let from = outage_start.saturating_sub(2000);
        let to = outage_end + 2000;
        let mut gaps: Vec<(u64, String)> = s
            .samples
            .iter()
            .map(|((node, d), v)| (largest_gap(v, from, to), format!("{node}/{d}")))
            .collect();
        gaps.sort_unstable();
        (gaps, s.historical - historical_before)
    };
    let worst = gaps.last().cloned().unwrap_or_default();
    let lossy = gaps
        .iter()
        .filter(|(g, _)| *g > 3 * quiet_gap.max(50))
        .count();
    println!(
        "broker restart: stopped {:.1} s; every store empty {} after the restart; {historical} historical DDATA replayed, \
         {dropped} dropped by the stores; largest gap in a drive's data around the outage {} ms ({}), \
         in the quiet window {quiet_gap} ms; drives with a gap over 3x that: {lossy} of {}",
        (outage_end - outage_start) as f64 / 1e3,
        replayed.map_or("not within 120 s".to_string(), |t| format!(
            "{:.1} s",
            t.duration_since(back).as_secs_f64()
        )),
        worst.0,
        worst.1,
        gaps.len()
    );
    println!("load average after: {}", load_average());

    if let Some(path) = svg {
        let s = seen.lock().unwrap();
        std::fs::write(&path, plot(&s, outage_start, outage_end, n)).unwrap();
        println!("the host's view written to {}", path.display());
    }
    for d in &mut daemons {
        d.stop();
    }
    drop(broker);
}

/// The host's view of the fleet around the broker restart: for each
/// daemon, a row of 100 ms cells by data time, blue where live data
/// arrived, orange where historical data filled the outage, empty where
/// nothing did.
fn plot(s: &Seen, outage_start: u64, outage_end: u64, n: usize) -> String {
    let from = outage_start.saturating_sub(3000);
    let to = outage_end + 3000;
    let cell = 100u64;
    let cells = (to - from).div_ceil(cell) as usize;
    let mut rows: BTreeMap<String, Vec<(u32, u32)>> = BTreeMap::new();
    for ((node, _), v) in &s.samples {
        let row = rows
            .entry(node.clone())
            .or_insert_with(|| vec![(0, 0); cells]);
        for &(t, historical) in v {
            if (from..to).contains(&t) {
                let c = ((t - from) / cell) as usize;
                if historical {
                    row[c].1 += 1;
                } else {
                    row[c].0 += 1;
                }
            }
        }
    }
    let (left, top, w, h) = (60.0, 36.0, 6.0, 14.0);
    let width = left + cells as f64 * w + 20.0;
    let height = top + n.max(rows.len()) as f64 * h + 50.0;
    let mut svg = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width:.0}\" height=\"{height:.0}\" font-family=\"sans-serif\" font-size=\"11\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n\
         <text x=\"4\" y=\"14\">A Sparkplug host's view of {n} gateways x {DRIVES} drives around a broker outage</text>\n\
         <text x=\"4\" y=\"26\" font-size=\"10\">each drive's data by its own timestamp, 100 ms cells: blue live, orange historical (replayed from the gateways' stores)</text>\n"
    );
    for (i, (node, row)) in rows.iter().enumerate() {
        let y = top + i as f64 * h;
        let _ = writeln!(svg, "<text x=\"4\" y=\"{:.0}\">{node}</text>", y + h - 4.0);
        // Runs of cells of one colour are one rectangle each.
        let colour = |&(live, hist): &(u32, u32)| match (live, hist) {
            (_, 1..) => Some("#f28e2b"),
            (1.., 0) => Some("#4e79a7"),
            _ => None,
        };
        let mut c = 0;
        while c < row.len() {
            let this = colour(&row[c]);
            let run = row[c..].iter().take_while(|x| colour(x) == this).count();
            if let Some(fill) = this {
                let _ = writeln!(
                    svg,
                    "<rect x=\"{:.0}\" y=\"{y:.0}\" width=\"{:.0}\" height=\"{:.0}\" fill=\"{fill}\"/>",
                    left + c as f64 * w,
                    run as f64 * w,
                    h - 2.0
                );
            }
            c += run;
        }
    }
    let axis = top + rows.len() as f64 * h + 14.0;
    let x = |t: u64| left + (t - from) as f64 / cell as f64 * w;
    let _ = writeln!(
        svg,
        "<line x1=\"{0:.0}\" y1=\"{top}\" x2=\"{0:.0}\" y2=\"{axis}\" stroke=\"black\" stroke-dasharray=\"3,3\"/>\n\
         <line x1=\"{1:.0}\" y1=\"{top}\" x2=\"{1:.0}\" y2=\"{axis}\" stroke=\"black\" stroke-dasharray=\"3,3\"/>\n\
         <text x=\"{0:.0}\" y=\"{2:.0}\">broker stopped</text>\n\
         <text x=\"{1:.0}\" y=\"{3:.0}\">broker back</text>\n\
         <text x=\"{left}\" y=\"{3:.0}\">-3 s</text>",
        x(outage_start),
        x(outage_end),
        axis + 12.0,
        axis + 26.0,
    );
    svg.push_str("</svg>\n");
    svg
}
