//! The soak: several simulated buses of eight drives in one daemon, HTTP,
//! WebSocket and Modbus TCP clients all busy (and reconnecting now and
//! then), a Prometheus scraper, and wire faults injected on every bus.
//! While it runs it samples the process's resident memory, open file
//! descriptors and tokio's alive tasks, and the buses' poll counts.
//!
//! Every answer a client gets is checked: each drive holds its own angle
//! (a position signature set up before the clients start), so a status
//! delivered for the wrong drive shows; each client kind writes its own
//! setting with values never written before (HTTP the speed ramp, Modbus
//! TCP the position ramp, WebSocket the load inertia), so a confirmation
//! must be true in the simulator and a read must return the simulator's
//! value. A failure is a correct answer only when it is one of the errors
//! the daemon promises for a wire fault (drive did not answer, garbled
//! reply, busy).
//!
//! Used by `tests/soak/mod.rs` (a few seconds, in CI) and
//! `benches/soak.rs` (the long run, `cargo bench --bench soak`).

#![allow(dead_code, unreachable_pub, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use drivegate::bus::BusError;
use drivegate::bus::handle::JobOptions;
use drivegate::config::Config;
use drivegate::drive::{ConfigCommand, DriveRequest};
use drivegate::metrics::Metrics;
use drivegate::plant::Plant;
use drivegate::sim::FaultRates;
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_modbus::client::{Client, Reader, Writer};
use tokio_modbus::prelude::SlaveContext;
use tokio_tungstenite::tungstenite::Message;
use tokio_util::sync::CancellationToken;

/// Drives per bus.
pub const DRIVES: u8 = 8;
/// How far a held position may be from its signature, 0.01 degree.
const ANGLE_TOLERANCE: f64 = 30.0;
/// The guard time after a timeout: the late replies (70 ms) fall inside
/// timeout + guard with 80 ms to spare for the simulator's own scheduling
/// on a loaded machine (a reply later than timeout + guard cannot be told
/// apart on RTU; see docs/reliability.md).
const GUARD_MS: u64 = 150;
/// Late replies, ms after their time: past the 50 ms response timeout.
const LATE_MS: f64 = 70.0;
/// Longest a client waits for any one answer before calling it lost.
const ANSWER_LIMIT: Duration = Duration::from_secs(20);

/// What to run.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Simulated buses (each its own serial port, scheduler thread and
    /// simulator thread), eight drives each, 115200 baud.
    pub buses: usize,
    /// Stop once the buses carried this many transactions...
    pub transactions: u64,
    /// ... or after this long, whichever comes first.
    pub max_duration: Duration,
    /// Clients of each kind.
    pub http_clients: usize,
    pub ws_clients: usize,
    pub tcp_clients: usize,
    /// Each client drops its connection and opens a new one this often.
    pub reconnect_every: Duration,
    /// Pause between one client's requests.
    pub pace: Duration,
    /// Rate of each of the four wire faults (dropped, corrupted, late, noise).
    pub fault_rate: f64,
    /// How often resources are sampled.
    pub sample_every: Duration,
    /// Print a progress line this often.
    pub progress_every: Option<Duration>,
}

/// The process's resources at one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Resources {
    /// Resident memory, KiB.
    pub rss_kib: u64,
    /// Open file descriptors.
    pub fds: usize,
    /// Tasks alive on the runtime serving the faces and clients.
    pub tasks: usize,
}

impl Resources {
    /// Reads them now (inside the runtime).
    pub fn now() -> Self {
        let rss_kib = std::fs::read_to_string("/proc/self/status")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("VmRSS:"))
                    .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
            })
            .unwrap_or(0);
        let fds = std::fs::read_dir("/proc/self/fd")
            .map(|d| d.count())
            .unwrap_or(0);
        let tasks = tokio::runtime::Handle::current()
            .metrics()
            .num_alive_tasks();
        Resources {
            rss_kib,
            fds,
            tasks,
        }
    }
}

/// One sample over the run.
#[derive(Debug, Clone, Copy)]
pub struct Point {
    /// Since the clients started.
    pub at: Duration,
    pub resources: Resources,
    /// Status polls answered so far, all buses.
    pub polls: u64,
    /// Transactions on the wire so far, all buses.
    pub transactions: u64,
}

/// What one client kind saw.
#[derive(Debug, Default)]
pub struct Kind {
    /// Answers checked and correct.
    pub ok: AtomicU64,
    /// Failures reported as the daemon promises for a wire fault.
    pub failed: AtomicU64,
    /// Answers that were wrong, or none at all.
    pub wrong: AtomicU64,
    /// Connections opened.
    pub connections: AtomicU64,
}

impl Kind {
    fn get(&self) -> (u64, u64, u64, u64) {
        (
            self.ok.load(Ordering::Relaxed),
            self.failed.load(Ordering::Relaxed),
            self.wrong.load(Ordering::Relaxed),
            self.connections.load(Ordering::Relaxed),
        )
    }
}

/// The clients' tallies.
#[derive(Debug, Default)]
pub struct Clients {
    pub http: Kind,
    pub ws: Kind,
    pub tcp: Kind,
    pub scrapes: Kind,
    /// Status messages the WebSocket clients received and checked.
    pub ws_updates: AtomicU64,
    /// The first wrong answers, described.
    pub wrong_examples: Mutex<Vec<String>>,
}

impl Clients {
    fn wrong(&self, kind: &Kind, what: String) {
        kind.wrong.fetch_add(1, Ordering::Relaxed);
        let mut examples = self.wrong_examples.lock().unwrap();
        if examples.len() < 20 {
            examples.push(what);
        }
    }

    /// Wrong answers of every kind.
    pub fn wrong_total(&self) -> u64 {
        [&self.http, &self.ws, &self.tcp, &self.scrapes]
            .iter()
            .map(|k| k.wrong.load(Ordering::Relaxed))
            .sum()
    }
}

/// What a soak measured.
#[derive(Debug)]
pub struct Report {
    pub plan: Plan,
    /// Time the clients ran.
    pub elapsed: Duration,
    /// Resources before any client connected, and after they all left.
    pub before: Resources,
    pub after: Resources,
    pub points: Vec<Point>,
    pub clients: Arc<Clients>,
    /// Transactions on the wire during the run, all buses, and attempts
    /// beyond the first.
    pub transactions: u64,
    pub retries: u64,
    /// Polls answered during the run, all buses.
    pub polls: u64,
    /// Faults the simulators injected during the run, by kind.
    pub injected: BTreeMap<&'static str, u64>,
    /// Requests that broke the RTU silence (0 on a correct master).
    pub gap_violations: u64,
}

/// Limits a soak must keep.
#[derive(Debug, Clone, Copy)]
pub struct Bounds {
    /// The last third's highest RSS over the first third's (after the
    /// first tenth, the warm-up), as a fraction of growth...
    pub memory_growth: f64,
    /// ... plus this much, KiB (allocator rounding).
    pub memory_slack_kib: u64,
    /// The last third's poll rate over the first third's, at least (0:
    /// only that the buses still poll in the last third).
    pub poll_rate_kept: f64,
}

impl Report {
    fn third(&self, which: usize) -> Vec<Point> {
        let total = self.elapsed.as_secs_f64();
        let warm = total / 10.0;
        let span = (total - warm) / 3.0;
        let from = warm + span * which as f64;
        let to = from + span;
        self.points
            .iter()
            .filter(|p| (from..=to).contains(&p.at.as_secs_f64()))
            .copied()
            .collect()
    }

    fn max_rss(points: &[Point]) -> u64 {
        points
            .iter()
            .map(|p| p.resources.rss_kib)
            .max()
            .unwrap_or(0)
    }

    fn poll_rate(points: &[Point]) -> f64 {
        match (points.first(), points.last()) {
            (Some(a), Some(b)) if b.at > a.at => {
                (b.polls - a.polls) as f64 / (b.at - a.at).as_secs_f64()
            }
            _ => 0.0,
        }
    }

    /// The first and last thirds' highest RSS, KiB.
    pub fn memory(&self) -> (u64, u64) {
        (Self::max_rss(&self.third(0)), Self::max_rss(&self.third(2)))
    }

    /// The first and last thirds' poll rates, polls/s.
    pub fn poll_rates(&self) -> (f64, f64) {
        (
            Self::poll_rate(&self.third(0)),
            Self::poll_rate(&self.third(2)),
        )
    }

    /// What broke `bounds`, in words (empty: the soak held).
    pub fn broken(&self, bounds: &Bounds) -> Vec<String> {
        let mut broken = Vec::new();
        let wrong = self.clients.wrong_total();
        if wrong > 0 {
            broken.push(format!(
                "{wrong} wrong or missing answers, e.g. {:?}",
                self.clients.wrong_examples.lock().unwrap()
            ));
        }
        for (name, kind) in [
            ("HTTP", &self.clients.http),
            ("WebSocket", &self.clients.ws),
            ("Modbus TCP", &self.clients.tcp),
            ("metrics scrape", &self.clients.scrapes),
        ] {
            if kind.ok.load(Ordering::Relaxed) == 0 {
                broken.push(format!("no {name} request was answered"));
            }
        }
        if self.clients.ws_updates.load(Ordering::Relaxed) == 0 {
            broken.push("no status update reached a WebSocket client".into());
        }
        if self.after.fds > self.before.fds {
            broken.push(format!(
                "file descriptors: {} before the clients, {} after they left",
                self.before.fds, self.after.fds
            ));
        }
        if self.after.tasks > self.before.tasks {
            broken.push(format!(
                "tasks: {} before the clients, {} after they left",
                self.before.tasks, self.after.tasks
            ));
        }
        let (first, last) = self.memory();
        let limit = (first as f64 * (1.0 + bounds.memory_growth)) as u64 + bounds.memory_slack_kib;
        if first == 0 || last > limit {
            broken.push(format!(
                "memory: highest RSS {first} KiB in the first third, {last} KiB in the last (limit {limit})"
            ));
        }
        let (r0, r1) = self.poll_rates();
        if r0 <= 0.0 || r1 <= 0.0 || r1 < r0 * bounds.poll_rate_kept {
            broken.push(format!(
                "poll rate: {r0:.1}/s in the first third, {r1:.1}/s in the last"
            ));
        }
        if self.gap_violations > 0 {
            broken.push(format!("{} gap violations", self.gap_violations));
        }
        broken
    }

    /// The figures, for people.
    pub fn print(&self) {
        let secs = self.elapsed.as_secs_f64();
        let p = &self.plan;
        println!(
            "soak: {} bus(es) x {DRIVES} drives at 115200 baud, {:.0} s; clients: {} HTTP, {} WebSocket, {} Modbus TCP, \
             1 metrics scraper, each reconnecting every {:?}; faults: {:.2} % each of dropped, corrupted, late \
             ({LATE_MS} ms; timeout 50 ms, guard {GUARD_MS} ms), noise",
            p.buses,
            secs,
            p.http_clients,
            p.ws_clients,
            p.tcp_clients,
            p.reconnect_every,
            p.fault_rate * 100.0
        );
        println!(
            "bus: {} transactions ({:.0}/s, {:.0}/s per bus), {} retries, {} polls answered; injected {:?}; gap violations {}",
            self.transactions,
            self.transactions as f64 / secs,
            self.transactions as f64 / secs / p.buses as f64,
            self.retries,
            self.polls,
            self.injected,
            self.gap_violations
        );
        for (name, kind) in [
            ("HTTP", &self.clients.http),
            ("WebSocket commands", &self.clients.ws),
            ("Modbus TCP", &self.clients.tcp),
            ("metrics scrapes", &self.clients.scrapes),
        ] {
            let (ok, failed, wrong, connections) = kind.get();
            println!(
                "{name}: {ok} correct, {failed} failed as promised for a wire fault, {wrong} wrong, {connections} connections"
            );
        }
        println!(
            "WebSocket status updates checked: {}",
            self.clients.ws_updates.load(Ordering::Relaxed)
        );
        let (m0, m1) = self.memory();
        let (r0, r1) = self.poll_rates();
        println!(
            "memory: RSS {} KiB before the clients, highest {m0} KiB in the first third, {m1} KiB in the last third ({:+.1} %), {} KiB after",
            self.before.rss_kib,
            100.0 * (m1 as f64 - m0 as f64) / m0.max(1) as f64,
            self.after.rss_kib
        );
        let peak = self
            .points
            .iter()
            .map(|p| p.resources)
            .fold(Resources::default(), |a, r| Resources {
                rss_kib: a.rss_kib.max(r.rss_kib),
                fds: a.fds.max(r.fds),
                tasks: a.tasks.max(r.tasks),
            });
        println!(
            "file descriptors: {} before, {} at most, {} after; tasks: {} before, {} at most, {} after",
            self.before.fds,
            peak.fds,
            self.after.fds,
            self.before.tasks,
            peak.tasks,
            self.after.tasks
        );
        println!(
            "poll rate: {r0:.1}/s in the first third, {r1:.1}/s in the last ({:+.1} %)",
            100.0 * (r1 - r0) / r0.max(1e-9)
        );
    }
}

fn bus_name(bus: usize) -> String {
    format!("line{bus}")
}

fn drive_name(bus: usize, unit: u8) -> String {
    format!("l{bus}d{unit}")
}

/// Each drive holds its own angle, 0.01 degree: a status of the wrong
/// drive cannot pass for the right one.
fn signature(bus: usize, unit: u8) -> i16 {
    i16::try_from(-17_000 + (bus as i64 * i64::from(DRIVES) + i64::from(unit)) * 400).unwrap()
}

/// The Modbus TCP unit id of a drive.
fn tcp_unit(bus: usize, unit: u8) -> u8 {
    u8::try_from(bus * 10 + usize::from(unit)).unwrap()
}

fn config(plan: &Plan) -> String {
    let mut toml = String::from(
        "[http]\nlisten = \"127.0.0.1:0\"\nmax_connections = 256\n\
         [modbus_tcp]\nlisten = \"127.0.0.1:0\"\nmax_connections = 256\n",
    );
    for bus in 0..plan.buses {
        toml.push_str(&format!(
            "[[modbus_tcp.unit_map]]\nunits = \"{}-{}\"\nbus = \"{}\"\nbus_units = \"1-{DRIVES}\"\n",
            tcp_unit(bus, 1),
            tcp_unit(bus, DRIVES),
            bus_name(bus)
        ));
    }
    toml.push_str("[safety]\non_shutdown = \"none\"\n");
    for bus in 0..plan.buses {
        toml.push_str(&format!(
            "[[bus]]\nname = \"{}\"\nport = \"sim\"\nresponse_timeout_ms = 50\nretries = 1\nguard_ms = {GUARD_MS}\n\
             [bus.sim]\nturnaround_ms = 0.5\nseed = {}\n",
            bus_name(bus),
            bus + 1
        ));
        for unit in 1..=DRIVES {
            toml.push_str(&format!(
                "[[bus.drive]]\nunit = {unit}\nname = \"{}\"\ngear_ratio = 3.75\n",
                drive_name(bus, unit)
            ));
        }
    }
    toml
}

/// The daemon under soak.
struct Daemon {
    plant: Arc<Plant>,
    http: SocketAddr,
    tcp: SocketAddr,
    shutdown: CancellationToken,
    faces: drivegate::daemon::supervisor::Faces,
}

impl Daemon {
    async fn start(plan: &Plan) -> Self {
        let config = Config::parse(&config(plan), "soak").expect("soak config");
        let plant = Arc::new(Plant::start(&config).expect("plant starts"));
        let metrics = Metrics::new(plant.clone());
        let shutdown = CancellationToken::new();
        let faces =
            drivegate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
                .await
                .expect("faces start");
        Daemon {
            http: faces.http,
            tcp: faces.modbus_tcp.expect("Modbus TCP on"),
            plant,
            shutdown,
            faces,
        }
    }

    fn sim(&self, bus: usize) -> drivegate::plant::SimRef {
        drivegate::plant::SimRef::of(self.plant.buses()[bus].clone()).expect("simulated")
    }

    /// Activates every drive in position mode at its signature angle and
    /// waits until each holds it.
    async fn hold_signatures(&self) {
        for (bus, b) in self.plant.buses().iter().enumerate() {
            for unit in 1..=DRIVES {
                for request in [
                    DriveRequest::Config(ConfigCommand::Activate),
                    DriveRequest::Config(ConfigCommand::PositionMode),
                    DriveRequest::Position {
                        centideg: signature(bus, unit),
                    },
                ] {
                    // The set-up is not what the soak measures: a command
                    // whose attempts all timed out because the machine held
                    // the simulator past the 50 ms timeout is sent again.
                    let mut tries = 0;
                    loop {
                        tries += 1;
                        match b
                            .handle
                            .execute(unit, &request, JobOptions::default())
                            .await
                        {
                            Ok(_) => break,
                            Err(BusError::Timeout { .. }) if tries < 5 => continue,
                            Err(e) => {
                                panic!("set-up command not confirmed after {tries} tries: {e}")
                            }
                        }
                    }
                }
            }
        }
        let start = Instant::now();
        loop {
            let held = (0..self.plant.buses().len()).all(|bus| {
                self.sim(bus).drives().iter().all(|d| {
                    d.status.speed_rpm == 0
                        && (f64::from(d.status.angle_centideg)
                            - f64::from(signature(bus, d.address)))
                        .abs()
                            <= ANGLE_TOLERANCE / 2.0
                })
            });
            if held {
                return;
            }
            assert!(
                start.elapsed() < Duration::from_secs(20),
                "the drives did not reach their signature angles"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    fn totals(&self) -> (u64, u64, u64) {
        let mut t = (0, 0, 0);
        for b in self.plant.buses() {
            let s = b.handle.stats();
            t.0 += s.on_wire();
            t.1 += s.retries;
            t.2 += s.polls - s.poll_failures;
        }
        t
    }

    async fn stop(self) {
        self.shutdown.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), self.faces.wait()).await;
        drivegate::control::shutdown(
            &self.plant,
            drivegate::control::stop_action::StopAction::None,
        )
        .await;
    }
}

/// Where the clients find the truth.
struct World {
    plant: Arc<Plant>,
    http: SocketAddr,
    tcp: SocketAddr,
    buses: usize,
    clients: Arc<Clients>,
    stop: CancellationToken,
    plan: Plan,
    /// Values never written before, shared by every writer.
    next_value: AtomicU64,
}

impl World {
    fn unique(&self) -> u32 {
        u32::try_from(self.next_value.fetch_add(1, Ordering::Relaxed)).unwrap()
    }

    fn settings(&self, bus: usize, unit: u8) -> drivegate::sim::model::Settings {
        self.plant.buses()[bus]
            .sim
            .as_ref()
            .unwrap()
            .drive(unit)
            .expect("simulated drive")
            .settings
    }

    /// The drives client `i` of `n` owns (for its writes).
    fn owned(&self, i: usize, n: usize) -> Vec<(usize, u8)> {
        (0..self.buses)
            .flat_map(|b| (1..=DRIVES).map(move |u| (b, u)))
            .enumerate()
            .filter(|(k, _)| k % n == i)
            .map(|(_, d)| d)
            .collect()
    }

    /// Checks a status angle (degrees) against the drive's signature.
    fn angle_ok(bus: usize, unit: u8, angle_deg: f64) -> bool {
        (angle_deg * 100.0 - f64::from(signature(bus, unit))).abs() <= ANGLE_TOLERANCE
    }

    /// Finds a drive by name.
    fn drive(&self, name: &str) -> Option<(usize, u8)> {
        let (bus, unit) = name.strip_prefix('l')?.split_once('d')?;
        Some((bus.parse().ok()?, unit.parse().ok()?))
    }
}

/// Problem types the REST and WebSocket faces promise for a wire fault or
/// a bus that is momentarily full.
const FAULT_PROBLEMS: [&str; 5] = [
    "urn:drivegate:problem:drive-timeout",
    "urn:drivegate:problem:drive-bad-reply",
    "urn:drivegate:problem:drive-offline",
    "urn:drivegate:problem:bus-busy",
    "urn:drivegate:problem:queue-timeout",
];

fn is_fault_problem(problem: &Value) -> bool {
    problem["type"]
        .as_str()
        .is_some_and(|t| FAULT_PROBLEMS.contains(&t))
        && problem["detail"].is_string()
}

async fn http_client(world: Arc<World>, i: usize) {
    let c = &world.clients;
    let owned = world.owned(i, world.plan.http_clients);
    let mut client: Option<(reqwest::Client, Instant)> = None;
    let mut k = 0usize;
    while !world.stop.is_cancelled() {
        if client
            .as_ref()
            .is_none_or(|(_, since)| since.elapsed() >= world.plan.reconnect_every)
        {
            client = Some((
                reqwest::Client::builder()
                    .timeout(ANSWER_LIMIT)
                    .pool_max_idle_per_host(1)
                    .build()
                    .unwrap(),
                Instant::now(),
            ));
            c.http.connections.fetch_add(1, Ordering::Relaxed);
        }
        let http = &client.as_ref().unwrap().0;
        let (bus, unit) = owned[k % owned.len()];
        let name = drive_name(bus, unit);
        let base = format!("http://{}/api/v1/drives/{name}", world.http);
        match k % 3 {
            0 => {
                let alpha = 3_000_000 + world.unique();
                let sent = http
                    .put(format!("{base}/ramps/speed"))
                    .json(&json!({ "alpha": alpha }))
                    .send()
                    .await;
                match reply(sent).await {
                    Some((200, body)) if body["alpha"] == alpha => {
                        let truth = world.settings(bus, unit).speed_alpha;
                        if truth == alpha {
                            c.http.ok.fetch_add(1, Ordering::Relaxed);
                        } else {
                            c.wrong(
                                &c.http,
                                format!(
                                    "{name}: speed ramp {alpha} confirmed, drive holds {truth}"
                                ),
                            );
                        }
                    }
                    Some((s, body)) if s >= 429 && is_fault_problem(&body) => {
                        c.http.failed.fetch_add(1, Ordering::Relaxed);
                    }
                    other => c.wrong(&c.http, format!("{name}: speed ramp answered {other:?}")),
                }
            }
            n => {
                let url = if n == 1 {
                    format!("{base}/status")
                } else {
                    format!("{base}/status?fresh=true")
                };
                match reply(http.get(url).send().await).await {
                    Some((200, body))
                        if body["drive"] == name.as_str()
                            && body["unit"] == unit
                            && body["angle_deg"]
                                .as_f64()
                                .is_some_and(|a| World::angle_ok(bus, unit, a)) =>
                    {
                        c.http.ok.fetch_add(1, Ordering::Relaxed);
                    }
                    Some((s, body)) if s >= 429 && is_fault_problem(&body) => {
                        c.http.failed.fetch_add(1, Ordering::Relaxed);
                    }
                    other => c.wrong(&c.http, format!("{name}: status answered {other:?}")),
                }
            }
        }
        k += 1;
        pause(&world).await;
    }
}

async fn reply(sent: reqwest::Result<reqwest::Response>) -> Option<(u16, Value)> {
    let response = sent.ok()?;
    let status = response.status().as_u16();
    let body = response.json::<Value>().await.ok()?;
    Some((status, body))
}

async fn pause(world: &World) {
    tokio::select! {
        () = tokio::time::sleep(world.plan.pace) => {}
        () = world.stop.cancelled() => {}
    }
}

/// A WebSocket command waiting for its reply.
struct Pending {
    id: u64,
    sent: Instant,
    bus: usize,
    unit: u8,
    /// The inertia ratio written, or `None` for a fresh status read.
    inertia: Option<u16>,
}

async fn ws_client(world: Arc<World>, i: usize) {
    let c = &world.clients;
    let owned = world.owned(i, world.plan.ws_clients);
    let mut writes: BTreeMap<(usize, u8), u32> = BTreeMap::new();
    let mut k = 0usize;
    let mut id = 0u64;
    while !world.stop.is_cancelled() {
        let url = format!("ws://{}/api/v1/stream?drives=all", world.http);
        let mut ws =
            match tokio::time::timeout(ANSWER_LIMIT, tokio_tungstenite::connect_async(url)).await {
                Ok(Ok((ws, _))) => ws,
                other => {
                    c.wrong(&c.ws, format!("WebSocket connect: {other:?}"));
                    pause(&world).await;
                    continue;
                }
            };
        c.ws.connections.fetch_add(1, Ordering::Relaxed);
        let opened = Instant::now();
        let mut tick = tokio::time::interval(world.plan.pace);
        let mut pending: Option<Pending> = None;
        loop {
            let leaving =
                world.stop.is_cancelled() || opened.elapsed() >= world.plan.reconnect_every;
            if pending.is_none() && leaving {
                break;
            }
            if pending
                .as_ref()
                .is_some_and(|p| p.sent.elapsed() > ANSWER_LIMIT)
            {
                c.wrong(&c.ws, "a WebSocket command got no reply".into());
                pending = None;
            }
            tokio::select! {
                _ = tick.tick(), if pending.is_none() && !leaving => {
                    let (bus, unit) = owned[k % owned.len()];
                    id += 1;
                    let (op, body, inertia) = if k.is_multiple_of(2) {
                        let n = writes.entry((bus, unit)).or_default();
                        *n += 1;
                        let ratio = u16::try_from(2 + *n % 65_000).unwrap();
                        ("inertia", json!({ "ratio": ratio }), Some(ratio))
                    } else {
                        ("status", json!({ "fresh": true }), None)
                    };
                    k += 1;
                    let command = json!({
                        "type": "command", "id": id, "op": op,
                        "drive": drive_name(bus, unit), "body": body,
                    });
                    if ws.send(Message::Text(command.to_string().into())).await.is_err() {
                        c.wrong(&c.ws, "a WebSocket command could not be sent".into());
                        break;
                    }
                    pending = Some(Pending { id, sent: Instant::now(), bus, unit, inertia });
                }
                message = ws.next() => match message {
                    Some(Ok(Message::Text(text))) => {
                        let Ok(v) = serde_json::from_str::<Value>(text.as_str()) else {
                            c.wrong(&c.ws, format!("not JSON: {text}"));
                            continue;
                        };
                        ws_message(&world, &v, &mut pending);
                    }
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => {}
                    other => {
                        c.wrong(&c.ws, format!("the stream ended: {other:?}"));
                        break;
                    }
                },
                () = tokio::time::sleep(Duration::from_millis(100)) => {}
            }
        }
        let _ = tokio::time::timeout(Duration::from_secs(5), ws.close(None)).await;
    }
}

/// Checks one message of the stream.
fn ws_message(world: &World, v: &Value, pending: &mut Option<Pending>) {
    let c = &world.clients;
    match v["type"].as_str() {
        Some("status") => {
            let checked =
                v["drive"]
                    .as_str()
                    .and_then(|d| world.drive(d))
                    .filter(|&(bus, unit)| {
                        v["bus"] == bus_name(bus).as_str()
                            && v["unit"] == unit
                            && v["status"]["angle_deg"]
                                .as_f64()
                                .is_some_and(|a| World::angle_ok(bus, unit, a))
                    });
            match checked {
                Some(_) => {
                    c.ws_updates.fetch_add(1, Ordering::Relaxed);
                }
                None => c.wrong(&c.ws, format!("status update {v}")),
            }
        }
        Some("reply") => {
            let Some(p) = pending.take_if(|p| v["id"] == p.id) else {
                c.wrong(&c.ws, format!("a reply nobody waited for: {v}"));
                return;
            };
            let name = drive_name(p.bus, p.unit);
            if v["ok"] == false {
                if is_fault_problem(&v["problem"]) {
                    c.ws.failed.fetch_add(1, Ordering::Relaxed);
                } else {
                    c.wrong(&c.ws, format!("{name}: {v}"));
                }
                return;
            }
            let right = match p.inertia {
                Some(ratio) => world.settings(p.bus, p.unit).inertia_ratio == ratio,
                None => {
                    v["result"]["drive"] == name.as_str()
                        && v["result"]["angle_deg"]
                            .as_f64()
                            .is_some_and(|a| World::angle_ok(p.bus, p.unit, a))
                }
            };
            if right {
                c.ws.ok.fetch_add(1, Ordering::Relaxed);
            } else {
                c.wrong(
                    &c.ws,
                    format!(
                        "{name}: {v} (drive holds inertia {})",
                        world.settings(p.bus, p.unit).inertia_ratio
                    ),
                );
            }
        }
        Some("subscribed" | "online" | "offline" | "freshness" | "lagged") => {}
        // Every client's writes, as the audit log has them.
        Some("write") if v["who"].is_string() && v["what"].is_string() && v["ok"].is_boolean() => {}
        _ => c.wrong(&c.ws, format!("unexpected message {v}")),
    }
}

async fn tcp_client(world: Arc<World>, i: usize) {
    use tokio_modbus::{ExceptionCode, Slave};
    let c = &world.clients;
    let owned = world.owned(i, world.plan.tcp_clients);
    let mut ctx: Option<(tokio_modbus::client::Context, Instant)> = None;
    let mut k = 0usize;
    while !world.stop.is_cancelled() {
        if ctx
            .as_ref()
            .is_none_or(|(_, since)| since.elapsed() >= world.plan.reconnect_every)
        {
            if let Some((mut old, _)) = ctx.take() {
                let _ = old.disconnect().await;
            }
            match tokio::time::timeout(
                ANSWER_LIMIT,
                tokio_modbus::client::tcp::connect_slave(world.tcp, Slave(1)),
            )
            .await
            {
                Ok(Ok(new)) => {
                    ctx = Some((new, Instant::now()));
                    c.tcp.connections.fetch_add(1, Ordering::Relaxed);
                }
                Ok(Err(e)) => {
                    c.wrong(&c.tcp, format!("Modbus TCP connect: {e}"));
                    pause(&world).await;
                    continue;
                }
                Err(_) => {
                    c.wrong(&c.tcp, "Modbus TCP connect timed out".into());
                    pause(&world).await;
                    continue;
                }
            }
        }
        let modbus = &mut ctx.as_mut().unwrap().0;
        let (bus, unit) = owned[k % owned.len()];
        let name = drive_name(bus, unit);
        modbus.set_slave(Slave(tcp_unit(bus, unit)));
        // What the answer should be, checked once it is in.
        enum Want {
            Confirmed(u32),
            Alpha,
            Signature,
        }
        let (want, answer) = match k % 3 {
            0 => {
                let alpha = 4_000_000 + world.unique();
                let words = [(alpha >> 16) as u16, alpha as u16, 0];
                let answer = tokio::time::timeout(
                    ANSWER_LIMIT,
                    modbus.write_multiple_registers(0x001E, &words),
                )
                .await
                .map(|r| r.map(|r| r.map(|()| Vec::new())));
                (Want::Confirmed(alpha), answer)
            }
            1 => (
                Want::Alpha,
                tokio::time::timeout(ANSWER_LIMIT, modbus.read_holding_registers(0x001E, 2)).await,
            ),
            _ => (
                Want::Signature,
                tokio::time::timeout(ANSWER_LIMIT, modbus.read_holding_registers(0x00C0, 7)).await,
            ),
        };
        k += 1;
        match answer {
            Ok(Ok(Ok(words))) => {
                let truth = world.settings(bus, unit).position_alpha;
                let right = match want {
                    Want::Confirmed(alpha) => truth == alpha,
                    Want::Alpha => {
                        words.len() == 2
                            && (u32::from(words[0]) << 16 | u32::from(words[1])) == truth
                    }
                    Want::Signature => {
                        words.len() == 7
                            && World::angle_ok(bus, unit, f64::from(words[1] as i16) / 100.0)
                    }
                };
                if right {
                    c.tcp.ok.fetch_add(1, Ordering::Relaxed);
                } else {
                    c.wrong(
                        &c.tcp,
                        format!("{name}: Modbus TCP answer {words:?}, position ramp {truth}"),
                    );
                }
            }
            Ok(Ok(Err(ExceptionCode::GatewayTargetDevice | ExceptionCode::ServerDeviceBusy))) => {
                c.tcp.failed.fetch_add(1, Ordering::Relaxed);
            }
            Ok(other) => {
                c.wrong(&c.tcp, format!("{name}: Modbus TCP answer {other:?}"));
                ctx = None;
            }
            Err(_) => {
                c.wrong(
                    &c.tcp,
                    format!("{name}: no Modbus TCP answer in {ANSWER_LIMIT:?}"),
                );
                ctx = None;
            }
        }
        pause(&world).await;
    }
    if let Some((mut old, _)) = ctx.take() {
        let _ = old.disconnect().await;
    }
}

/// Scrapes `/metrics` every second, as Prometheus would.
async fn scraper(world: Arc<World>) {
    let c = &world.clients;
    let mut client: Option<(reqwest::Client, Instant)> = None;
    while !world.stop.is_cancelled() {
        if client
            .as_ref()
            .is_none_or(|(_, since)| since.elapsed() >= world.plan.reconnect_every)
        {
            client = Some((
                reqwest::Client::builder()
                    .timeout(ANSWER_LIMIT)
                    .build()
                    .unwrap(),
                Instant::now(),
            ));
            c.scrapes.connections.fetch_add(1, Ordering::Relaxed);
        }
        let http = &client.as_ref().unwrap().0;
        let text = match http
            .get(format!("http://{}/metrics", world.http))
            .send()
            .await
        {
            Ok(r) if r.status().as_u16() == 200 => r.text().await.ok(),
            _ => None,
        };
        match text {
            Some(t) if t.contains("drivegate_bus_polls_total{bus=\"line0\"}") => {
                c.scrapes.ok.fetch_add(1, Ordering::Relaxed);
            }
            other => c.wrong(&c.scrapes, format!("metrics scrape: {other:?}")),
        }
        tokio::select! {
            () = tokio::time::sleep(Duration::from_secs(1)) => {}
            () = world.stop.cancelled() => {}
        }
    }
}

/// Runs the soak described by `plan`.
pub async fn run(plan: Plan) -> Report {
    let daemon = Daemon::start(&plan).await;
    let online = Instant::now();
    while !daemon
        .plant
        .buses()
        .iter()
        .all(|b| b.handle.drives().iter().all(|d| d.status.is_some()))
    {
        assert!(
            online.elapsed() < Duration::from_secs(20),
            "drives offline at start"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    daemon.hold_signatures().await;
    let rates = FaultRates {
        drop_rate: plan.fault_rate,
        crc_error_rate: plan.fault_rate,
        late_rate: plan.fault_rate,
        late_ms: LATE_MS,
        noise_rate: plan.fault_rate,
        silent_units: Vec::new(),
    };
    let sims_before: Vec<_> = (0..plan.buses)
        .map(|b| {
            daemon.sim(b).set_fault_rates(rates.clone()).unwrap();
            daemon.sim(b).stats()
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let before = Resources::now();
    let (t0, r0, p0) = daemon.totals();

    let world = Arc::new(World {
        plant: daemon.plant.clone(),
        http: daemon.http,
        tcp: daemon.tcp,
        buses: plan.buses,
        clients: Arc::new(Clients::default()),
        stop: CancellationToken::new(),
        plan: plan.clone(),
        next_value: AtomicU64::new(0),
    });
    let mut tasks = Vec::new();
    for i in 0..plan.http_clients {
        tasks.push(tokio::spawn(http_client(world.clone(), i)));
    }
    for i in 0..plan.ws_clients {
        tasks.push(tokio::spawn(ws_client(world.clone(), i)));
    }
    for i in 0..plan.tcp_clients {
        tasks.push(tokio::spawn(tcp_client(world.clone(), i)));
    }
    tasks.push(tokio::spawn(scraper(world.clone())));

    let start = Instant::now();
    let mut points = Vec::new();
    let mut last_progress = start;
    loop {
        tokio::time::sleep(plan.sample_every).await;
        let (t, _, p) = daemon.totals();
        let point = Point {
            at: start.elapsed(),
            resources: Resources::now(),
            polls: p - p0,
            transactions: t - t0,
        };
        points.push(point);
        if let Some(every) = plan.progress_every
            && last_progress.elapsed() >= every
        {
            last_progress = Instant::now();
            println!(
                "  {:>6.0} s: {} transactions, RSS {} KiB, {} fds, {} tasks, {} wrong",
                point.at.as_secs_f64(),
                point.transactions,
                point.resources.rss_kib,
                point.resources.fds,
                point.resources.tasks,
                world.clients.wrong_total()
            );
        }
        if point.transactions >= plan.transactions || point.at >= plan.max_duration {
            break;
        }
    }
    world.stop.cancel();
    for task in tasks {
        tokio::time::timeout(Duration::from_secs(60), task)
            .await
            .expect("every client leaves within a minute")
            .expect("client task");
    }
    let elapsed = start.elapsed();
    let (t1, r1, p1) = daemon.totals();
    let mut injected = BTreeMap::new();
    let mut gap_violations = 0;
    for (b, s0) in sims_before.iter().enumerate() {
        let s = daemon.sim(b).stats();
        for (kind, n) in [
            ("dropped", s.dropped - s0.dropped),
            ("corrupted", s.corrupted - s0.corrupted),
            ("late", s.late - s0.late),
            ("noise", s.noise_bursts - s0.noise_bursts),
        ] {
            *injected.entry(kind).or_default() += n;
        }
        gap_violations += s.gap_violations - s0.gap_violations;
    }
    // The server side of each connection ends once it sees the close.
    let settle = Instant::now();
    let after = loop {
        let now = Resources::now();
        if (now.fds <= before.fds && now.tasks <= before.tasks)
            || settle.elapsed() > Duration::from_secs(10)
        {
            break now;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let clients = world.clients.clone();
    drop(world);
    daemon.stop().await;
    Report {
        plan,
        elapsed,
        before,
        after,
        points,
        clients,
        transactions: t1 - t0,
        retries: r1 - r0,
        polls: p1 - p0,
        injected,
        gap_violations,
    }
}
