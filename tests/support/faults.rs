//! What the fault tests share: a bus of eight simulated drives, the truth
//! kept by the simulator across power cycles and replugs, a checked
//! workload (unique writes, each read back), per-drive poll counts, and the
//! `/metrics` text parsed into the counters the accounting compares.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use drivegate::bus::handle::JobOptions;
use drivegate::bus::{BusError, BusEvent, BusHandle, SourceId};
use drivegate::drive::{DriveReply, DriveRequest};
use drivegate::plant::{Plant, SimRef};
use drivegate::sim::model::Settings;
use drivegate::sim::{SimConfig, SimDriveView, SimHandle, SimStats, Simulator};
use tokio::sync::Mutex;
use tokio_util::sync::CancellationToken;

use crate::support::config::ConfigBuilder;

/// Longest a single job may take in these tests (queue wait, retries,
/// guard times and a replug included): a job that takes longer was lost.
pub const JOB_LIMIT: Duration = Duration::from_secs(10);

/// The units of the eight drives.
pub const UNITS: std::ops::RangeInclusive<u8> = 1..=8;

/// A daemon config: one bus of eight drives (units 1-8, named `d1`..`d8`)
/// on `port` (`"sim"` for the built-in simulator), one retry, extra
/// `[[bus]]` keys in `bus` (timeouts, guard), extra `[bus.sim]` keys in
/// `sim`. Modbus TCP is off: these tests drive the bus through its handle,
/// as every face does. No safe-stop action at shutdown: stopping the
/// daemon adds no traffic to what the accounting compares.
pub fn eight_drives(port: &str, bus: &str, sim: &str) -> String {
    ConfigBuilder::new()
        .modbus_tcp_off()
        .section("safety", "on_shutdown = \"none\"")
        .bus("line", |b| {
            b.port(port)
                .keys(bus)
                .sim("seed = 11")
                .sim(sim)
                .drives(UNITS)
        })
        .toml()
}

// ---------------------------------------------------------------------------
// The truth

/// Where the simulated drives live now.
enum Live {
    /// The daemon's built-in simulator, owned by the plant.
    Plant(Arc<Plant>),
    /// A simulator behind a pty link, owned here so it can be unplugged.
    Linked(Box<Linked>),
}

impl Live {
    fn sim(&self) -> LiveSim<'_> {
        match self {
            Live::Plant(plant) => {
                LiveSim::Plant(SimRef::of(plant.buses()[0].clone()).expect("a simulated bus"))
            }
            Live::Linked(linked) => {
                LiveSim::Linked(linked.sim.as_ref().expect("the adapter is plugged in"))
            }
        }
    }
}

/// The simulator of a [`Live`] bus.
enum LiveSim<'a> {
    Plant(SimRef),
    Linked(&'a SimHandle),
}

impl std::ops::Deref for LiveSim<'_> {
    type Target = SimHandle;

    fn deref(&self) -> &SimHandle {
        match self {
            LiveSim::Plant(sim) => sim,
            LiveSim::Linked(sim) => sim,
        }
    }
}

/// A simulator behind a link, and what it takes to plug in another.
struct Linked {
    sim: Option<SimHandle>,
    link: PathBuf,
    config: SimConfig,
}

struct Epochs {
    live: Live,
    /// `ended[e]`: every drive's state at the end of epoch `e`.
    ended: Vec<Vec<SimDriveView>>,
}

/// The simulator's truth about the drives' settings. A power cycle or a
/// replug ends an *epoch*: the drives' state at that moment is kept, so a
/// reply can be checked against every state its drive had between the
/// request's submission and the check.
///
/// Each epoch ends with the drives concerned made silent *before* their
/// state is copied: nothing can change them between the copy and the cut,
/// and what a drive confirmed before the cut is in the copy.
pub struct Truth {
    epoch: AtomicU64,
    state: Mutex<Epochs>,
}

impl Truth {
    /// The truth of the daemon's built-in simulator (bus 0).
    pub fn of_plant(plant: Arc<Plant>) -> Self {
        Self::new(Live::Plant(plant))
    }

    /// Starts a simulator with `config` and links its pty at `link`: an
    /// adapter the test can unplug.
    pub fn linked(config: SimConfig, link: &Path) -> Self {
        let mut sim = Simulator::start(config.clone()).expect("simulator starts");
        sim.link_at(link).expect("link the pty");
        Self::new(Live::Linked(Box::new(Linked {
            sim: Some(sim),
            link: link.to_path_buf(),
            config,
        })))
    }

    fn new(live: Live) -> Self {
        Self {
            epoch: AtomicU64::new(0),
            state: Mutex::new(Epochs {
                live,
                ended: Vec::new(),
            }),
        }
    }

    /// The current epoch; take it before submitting a request.
    pub fn epoch(&self) -> u64 {
        self.epoch.load(Ordering::SeqCst)
    }

    /// Runs `f` on the live simulator.
    pub async fn with_sim<T>(&self, f: impl FnOnce(&SimHandle) -> T) -> T {
        f(&self.state.lock().await.live.sim())
    }

    /// Every settings state `unit` had from epoch `since` to now.
    pub async fn settings_since(&self, since: u64, unit: u8) -> Vec<Settings> {
        let state = self.state.lock().await;
        let find =
            |views: &[SimDriveView]| views.iter().find(|v| v.address == unit).map(|v| v.settings);
        let since = usize::try_from(since).unwrap();
        let mut out: Vec<Settings> = state.ended[since.min(state.ended.len())..]
            .iter()
            .filter_map(|views| find(views))
            .collect();
        out.extend(find(&state.live.sim().drives()));
        out
    }

    /// Cuts the power of `unit`: silenced, its state kept, power-cycled,
    /// then answering again once it has rebooted.
    pub async fn power_cycle(&self, unit: u8) {
        let mut state = self.state.lock().await;
        let sim = state.live.sim();
        sim.set_silent(unit, true);
        let views = sim.drives();
        sim.power_cycle(unit).expect("the drive exists");
        sim.set_silent(unit, false);
        state.ended.push(views);
        self.epoch.fetch_add(1, Ordering::SeqCst);
    }

    /// Unplugs the adapter (the pty and its link disappear), waits `away`,
    /// and plugs a new one in at the same path. The drives behind the new
    /// adapter start from their power-on state.
    pub async fn unplug_for(&self, away: Duration) {
        let mut state = self.state.lock().await;
        let Live::Linked(linked) = &mut state.live else {
            panic!("only a linked simulator can be unplugged");
        };
        let old = linked.sim.take().expect("plugged in");
        for unit in UNITS {
            old.set_silent(unit, true);
        }
        let views = old.drives();
        self.epoch.fetch_add(1, Ordering::SeqCst);
        // Dropping the handle stops the simulator: its pty closes, the link goes.
        tokio::task::block_in_place(move || drop(old));
        tokio::time::sleep(away).await;
        let mut new = Simulator::start(linked.config.clone()).expect("simulator starts");
        new.link_at(&linked.link).expect("link the pty");
        linked.sim = Some(new);
        state.ended.push(views);
    }
}

// ---------------------------------------------------------------------------
// The checked workload

/// The drive settings the workload writes with unique values and reads
/// back, each through a different register block and reply length.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Setting {
    /// 0x0018, 2 registers (reply 9 bytes).
    SpeedRamp,
    /// 0x001E, 2 registers (reply 9 bytes).
    PositionRamp,
    /// 0x0024, 1 register (reply 7 bytes).
    Inertia,
    /// 0x000C, 2 registers: current limit and stall time (reply 9 bytes).
    OverCurrent,
}

impl Setting {
    /// In the order the workload cycles through them.
    pub const ALL: [Setting; 4] = [
        Setting::SpeedRamp,
        Setting::Inertia,
        Setting::PositionRamp,
        Setting::OverCurrent,
    ];

    /// The `i`-th write of this setting to a drive: a value never written
    /// before (nor the factory value), for `i` below 40 000.
    pub fn write(self, i: u32) -> (DriveRequest, u64) {
        match self {
            Setting::SpeedRamp => {
                let alpha = 1_000_000 + i;
                (
                    DriveRequest::SpeedRamp { alpha, save: false },
                    u64::from(alpha),
                )
            }
            Setting::PositionRamp => {
                let alpha = 2_000_000 + i;
                (
                    DriveRequest::PositionRamp { alpha, save: false },
                    u64::from(alpha),
                )
            }
            Setting::Inertia => {
                let ratio = u16::try_from(10 + i).unwrap();
                (
                    DriveRequest::LoadInertia { ratio, save: false },
                    u64::from(ratio),
                )
            }
            Setting::OverCurrent => {
                let limit_counts = u16::try_from(i % 2048).unwrap();
                let stall_ms = u16::try_from(10_000 + i).unwrap();
                (
                    DriveRequest::OverCurrent {
                        limit_counts,
                        stall_ms,
                        save: false,
                    },
                    (u64::from(limit_counts) << 16) | u64::from(stall_ms),
                )
            }
        }
    }

    /// The read-back request PDU.
    pub fn read_pdu(self) -> Vec<u8> {
        let (start, count): (u16, u16) = match self {
            Setting::SpeedRamp => (0x0018, 2),
            Setting::PositionRamp => (0x001E, 2),
            Setting::Inertia => (0x0024, 1),
            Setting::OverCurrent => (0x000C, 2),
        };
        let mut pdu = vec![0x03];
        pdu.extend_from_slice(&start.to_be_bytes());
        pdu.extend_from_slice(&count.to_be_bytes());
        pdu
    }

    /// The value in a read-back reply PDU; `None` if the reply is not the
    /// shape this read asks for.
    pub fn decode(self, reply: &[u8]) -> Option<u64> {
        let words = match self {
            Setting::Inertia => 1,
            _ => 2,
        };
        if reply.len() != 2 + 2 * words || reply[0] != 0x03 || usize::from(reply[1]) != 2 * words {
            return None;
        }
        Some(reply[2..].chunks(2).fold(0u64, |v, w| {
            (v << 16) | u64::from(u16::from_be_bytes([w[0], w[1]]))
        }))
    }

    /// The same value, from the simulator's settings.
    pub fn of(self, s: &Settings) -> u64 {
        match self {
            Setting::SpeedRamp => u64::from(s.speed_alpha),
            Setting::PositionRamp => u64::from(s.position_alpha),
            Setting::Inertia => u64::from(s.inertia_ratio),
            Setting::OverCurrent => {
                (u64::from(s.stall_current) << 16) | u64::from(s.stall_duration_ms)
            }
        }
    }
}

/// What one or several workload tasks saw.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Tally {
    /// Writes the bus accepted into its queue.
    pub writes_accepted: u64,
    /// Writes refused at submission (bus down, busy): nothing was sent.
    pub writes_refused: u64,
    /// Accepted writes the drive confirmed (each checked in the simulator).
    pub writes_confirmed: u64,
    /// Accepted writes reported failed.
    pub writes_failed: u64,
    /// Reads accepted.
    pub reads_accepted: u64,
    /// Reads refused at submission.
    pub reads_refused: u64,
    /// Reads answered (each checked against the simulator's truth).
    pub reads_answered: u64,
    /// Reads reported failed.
    pub reads_failed: u64,
    /// Accepted jobs that failed because the port went down (before their
    /// request went out, or after): each is a `port_error` transaction in
    /// the metrics.
    pub failed_bus_down: u64,
    /// Failures and refusals by kind (error variant).
    pub failures: BTreeMap<&'static str, u64>,
}

impl Tally {
    /// Adds another task's tally.
    pub fn add(&mut self, other: &Tally) {
        self.writes_accepted += other.writes_accepted;
        self.writes_refused += other.writes_refused;
        self.writes_confirmed += other.writes_confirmed;
        self.writes_failed += other.writes_failed;
        self.reads_accepted += other.reads_accepted;
        self.reads_refused += other.reads_refused;
        self.reads_answered += other.reads_answered;
        self.reads_failed += other.reads_failed;
        self.failed_bus_down += other.failed_bus_down;
        for (k, v) in &other.failures {
            *self.failures.entry(k).or_default() += v;
        }
    }

    /// Every accepted job ended confirmed/answered or reported failed.
    pub fn assert_nothing_lost(&self) {
        assert_eq!(
            self.writes_confirmed + self.writes_failed,
            self.writes_accepted,
            "every accepted write is confirmed or reported failed: {self:?}"
        );
        assert_eq!(
            self.reads_answered + self.reads_failed,
            self.reads_accepted,
            "every accepted read is answered or reported failed: {self:?}"
        );
    }
}

/// The name of an error's kind, for the tally.
pub fn kind(e: &BusError) -> &'static str {
    match e {
        BusError::Busy { .. } => "busy",
        BusError::BusDown { .. } => "bus_down",
        BusError::BusDownAfterSend { .. } => "bus_down_after_send",
        BusError::Timeout { .. } => "timeout",
        BusError::BadReply { .. } => "bad_reply",
        BusError::Exception { .. } => "exception",
        BusError::Unconfirmed { .. } => "unconfirmed",
        BusError::Expired { .. } => "expired",
        BusError::ShuttingDown => "shutting_down",
        BusError::Invalid(_) => "invalid",
    }
}

/// How a job ended, as a client sees it.
enum Ended {
    Refused(BusError),
    Failed(BusError),
    Replied(Vec<u8>),
}

async fn run_job(bus: &BusHandle, unit: u8, pdu: Vec<u8>, source: SourceId) -> Ended {
    let rx = match bus.submit(unit, pdu, JobOptions::from_source(source)) {
        Ok(rx) => rx,
        Err(e) => return Ended::Refused(e),
    };
    let result = tokio::time::timeout(JOB_LIMIT, rx)
        .await
        .unwrap_or_else(|_| panic!("an accepted job to unit {unit} got no result in {JOB_LIMIT:?}"))
        .expect("the bus always answers an accepted job");
    match result {
        Ok(exchange) => Ended::Replied(exchange.reply),
        Err(e) => Ended::Failed(e),
    }
}

/// Which failures a scenario may report; anything else fails the test.
pub type Allowed = &'static [&'static str];

/// One drive's share of the workload: `rounds` times, write a unique value
/// of the next setting and read it back. Every confirmed write must be
/// true in the simulator, and every answered read must carry the value the
/// simulator held for that drive while the read was under way: a reply
/// delivered to the wrong request would carry another register's value, an
/// older value or a status block, and fail the check.
pub async fn checked_traffic(
    bus: BusHandle,
    truth: Arc<Truth>,
    unit: u8,
    rounds: u32,
    allowed: Allowed,
    stop: CancellationToken,
) -> Tally {
    let source = SourceId::new_unique();
    let mut tally = Tally::default();
    // `accepted`: the job was in the queue when it failed.
    let fail = |tally: &mut Tally, e: &BusError, accepted: bool| {
        let k = kind(e);
        assert!(
            allowed.contains(&k),
            "unit {unit}: unexpected failure {k}: {e}"
        );
        if accepted {
            assert!(!matches!(e, BusError::Busy { .. }), "{e}");
        } else {
            assert!(e.not_sent(), "refused at submission yet maybe sent: {e}");
        }
        *tally.failures.entry(k).or_default() += 1;
        if accepted && matches!(k, "bus_down" | "bus_down_after_send") {
            tally.failed_bus_down += 1;
        }
    };
    for i in 0..rounds {
        if stop.is_cancelled() {
            break;
        }
        let setting = Setting::ALL[i as usize % Setting::ALL.len()];
        let (request, value) = setting.write(i);

        let epoch = truth.epoch();
        match run_job(&bus, unit, request.pdu().unwrap(), source).await {
            Ended::Refused(e) => {
                tally.writes_refused += 1;
                fail(&mut tally, &e, false);
                tokio::time::sleep(Duration::from_millis(20)).await;
                continue;
            }
            Ended::Failed(e) => {
                tally.writes_accepted += 1;
                tally.writes_failed += 1;
                fail(&mut tally, &e, true);
            }
            Ended::Replied(reply) => {
                tally.writes_accepted += 1;
                match request.parse_reply(&reply) {
                    Ok(DriveReply::Confirmed) => {}
                    other => panic!("unit {unit}: write {request:?} answered {other:?}"),
                }
                let states = truth.settings_since(epoch, unit).await;
                assert!(
                    states.iter().any(|s| setting.of(s) == value),
                    "unit {unit}: write of {value} to {setting:?} confirmed, but the drive holds {:?}",
                    states.iter().map(|s| setting.of(s)).collect::<Vec<_>>()
                );
                tally.writes_confirmed += 1;
            }
        }

        let epoch = truth.epoch();
        match run_job(&bus, unit, setting.read_pdu(), source).await {
            Ended::Refused(e) => {
                tally.reads_refused += 1;
                fail(&mut tally, &e, false);
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Ended::Failed(e) => {
                tally.reads_accepted += 1;
                tally.reads_failed += 1;
                fail(&mut tally, &e, true);
            }
            Ended::Replied(reply) => {
                tally.reads_accepted += 1;
                let got = setting.decode(&reply).unwrap_or_else(|| {
                    panic!("unit {unit}: read of {setting:?} answered {reply:02x?}")
                });
                let states = truth.settings_since(epoch, unit).await;
                assert!(
                    states.iter().any(|s| setting.of(s) == got),
                    "unit {unit}: read of {setting:?} returned {got}, the drive held {:?}",
                    states.iter().map(|s| setting.of(s)).collect::<Vec<_>>()
                );
                tally.reads_answered += 1;
            }
        }
    }
    tally
}

/// Runs [`checked_traffic`] on every unit of `units` at once; returns the
/// total and each unit's tally.
pub async fn traffic_on(
    bus: &BusHandle,
    truth: &Arc<Truth>,
    units: impl IntoIterator<Item = u8>,
    rounds: u32,
    allowed: Allowed,
    stop: &CancellationToken,
) -> (Tally, BTreeMap<u8, Tally>) {
    let tasks: Vec<_> = units
        .into_iter()
        .map(|unit| {
            let task = tokio::spawn(checked_traffic(
                bus.clone(),
                truth.clone(),
                unit,
                rounds,
                allowed,
                stop.clone(),
            ));
            (unit, task)
        })
        .collect();
    let mut total = Tally::default();
    let mut each = BTreeMap::new();
    for (unit, task) in tasks {
        let tally = task.await.expect("workload task");
        total.add(&tally);
        each.insert(unit, tally);
    }
    (total, each)
}

// ---------------------------------------------------------------------------
// Poll counts

/// Counts the status polls each drive answered, from the bus's events.
pub struct PollCounter {
    stop: CancellationToken,
    task: tokio::task::JoinHandle<(BTreeMap<u8, u64>, u64)>,
}

impl PollCounter {
    /// Starts counting now.
    pub fn start(bus: &BusHandle) -> Self {
        let mut events = bus.subscribe();
        let stop = CancellationToken::new();
        let task = tokio::spawn({
            let stop = stop.clone();
            async move {
                let mut counts: BTreeMap<u8, u64> = BTreeMap::new();
                let mut missed = 0;
                loop {
                    tokio::select! {
                        () = stop.cancelled() => break,
                        event = events.recv() => match event {
                            Ok(BusEvent::Status { unit, .. }) => *counts.entry(unit).or_default() += 1,
                            Ok(_) => {}
                            Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => missed += n,
                            Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                        }
                    }
                }
                (counts, missed)
            }
        });
        Self { stop, task }
    }

    /// Stops counting; the status reads per unit.
    pub async fn finish(self) -> BTreeMap<u8, u64> {
        self.stop.cancel();
        let (counts, missed) = self.task.await.expect("counter task");
        assert_eq!(missed, 0, "the poll counter fell behind the bus");
        counts
    }
}

/// Every unit of `healthy` kept being polled: at least `min` status reads
/// each, and shared fairly (round robin: the least polled got at least
/// half of the most polled's count).
pub fn assert_polled(counts: &BTreeMap<u8, u64>, healthy: impl IntoIterator<Item = u8>, min: u64) {
    let got: Vec<(u8, u64)> = healthy
        .into_iter()
        .map(|u| (u, counts.get(&u).copied().unwrap_or(0)))
        .collect();
    let least = got.iter().map(|g| g.1).min().unwrap_or(0);
    let most = got.iter().map(|g| g.1).max().unwrap_or(0);
    assert!(
        least >= min && least * 2 >= most,
        "healthy drives' status reads {got:?}: want at least {min} each, shared fairly"
    );
}

// ---------------------------------------------------------------------------
// /metrics

/// One sample line of the text exposition.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Series name.
    pub name: String,
    /// Its labels.
    pub labels: BTreeMap<String, String>,
    /// Its value.
    pub value: f64,
}

/// A parsed scrape of `/metrics`.
#[derive(Debug, Clone)]
pub struct Scrape(pub Vec<Sample>);

impl Scrape {
    /// Parses the text format (label values here never hold quotes or commas).
    pub fn parse(text: &str) -> Self {
        let mut out = Vec::new();
        for line in text
            .lines()
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
        {
            let (series, value) = line.rsplit_once(' ').expect("sample line has a value");
            let value: f64 = match value {
                "+Inf" => f64::INFINITY,
                v => v
                    .parse()
                    .unwrap_or_else(|_| panic!("bad value in {line:?}")),
            };
            let (name, labels) = match series.split_once('{') {
                None => (series.to_string(), BTreeMap::new()),
                Some((name, rest)) => {
                    let labels = rest
                        .trim_end_matches('}')
                        .split("\",")
                        .filter(|p| !p.is_empty())
                        .map(|p| {
                            let (k, v) = p.split_once("=\"").expect("label");
                            (k.to_string(), v.trim_end_matches('"').to_string())
                        })
                        .collect();
                    (name.to_string(), labels)
                }
            };
            out.push(Sample {
                name,
                labels,
                value,
            });
        }
        Scrape(out)
    }

    fn matching<'a>(
        &'a self,
        name: &'a str,
        labels: &'a [(&'a str, &'a str)],
    ) -> impl Iterator<Item = &'a Sample> + 'a {
        self.0.iter().filter(move |s| {
            s.name == name
                && labels
                    .iter()
                    .all(|(k, v)| s.labels.get(*k).map(String::as_str) == Some(*v))
        })
    }

    /// The one series of `name` with `labels`.
    pub fn get(&self, name: &str, labels: &[(&str, &str)]) -> f64 {
        let found: Vec<_> = self.matching(name, labels).collect();
        assert_eq!(found.len(), 1, "one series {name} {labels:?}: {found:?}");
        found[0].value
    }

    /// The sum over every series of `name` with `labels`.
    pub fn sum(&self, name: &str, labels: &[(&str, &str)]) -> f64 {
        self.matching(name, labels).map(|s| s.value).sum()
    }
}

/// The bus counters of one scrape that the fault accounting compares, as
/// integers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Wire {
    /// Transactions by outcome, all functions.
    pub ok: u64,
    pub exception: u64,
    pub timeout: u64,
    pub crc_error: u64,
    pub bad_reply: u64,
    pub dropped: u64,
    pub port_error: u64,
    /// Attempts beyond the first.
    pub retries: u64,
    /// Bytes that belonged to no reply.
    pub stray_bytes: u64,
    /// Status polls, and those that failed.
    pub polls: u64,
    pub poll_failures: u64,
    /// Port failures and reopens.
    pub port_errors: u64,
    pub reopens: u64,
    /// 1 while the port is open.
    pub port_open: u64,
}

fn int(v: f64) -> u64 {
    assert!(v >= 0.0 && v.fract() == 0.0, "a counter: {v}");
    v as u64
}

impl Wire {
    /// The counters of bus `bus` in `s`.
    pub fn of(s: &Scrape, bus: &str) -> Self {
        let outcome = |o: &str| {
            int(s.sum(
                "drivegate_bus_transactions_total",
                &[("bus", bus), ("outcome", o)],
            ))
        };
        let one = |name: &str| int(s.get(name, &[("bus", bus)]));
        Wire {
            ok: outcome("ok"),
            exception: outcome("exception"),
            timeout: outcome("timeout"),
            crc_error: outcome("crc_error"),
            bad_reply: outcome("bad_reply"),
            dropped: outcome("dropped"),
            port_error: outcome("port_error"),
            retries: one("drivegate_bus_retries_total"),
            stray_bytes: one("drivegate_bus_stray_bytes_total"),
            polls: one("drivegate_bus_polls_total"),
            poll_failures: one("drivegate_bus_poll_failures_total"),
            port_errors: one("drivegate_bus_port_errors_total"),
            reopens: one("drivegate_bus_reopens_total"),
            port_open: one("drivegate_bus_port_open"),
        }
    }

    /// Transactions that reached the wire.
    pub fn on_wire(&self) -> u64 {
        self.ok + self.exception + self.timeout + self.crc_error + self.bad_reply
    }

    /// Frames sent: each transaction on the wire once, plus its retries.
    pub fn attempts(&self) -> u64 {
        self.on_wire() + self.retries
    }

    /// Attempts that failed: the retries and the transactions that failed
    /// on their last attempt.
    pub fn failed_attempts(&self) -> u64 {
        self.retries + self.timeout + self.crc_error + self.bad_reply
    }
}

/// The shortest and longest reply frames of the checked workload: a
/// one-register read (7 bytes) and the status block (19 bytes).
pub const SHORTEST_REPLY: u64 = 7;
pub const LONGEST_REPLY: u64 = 19;

/// Failed attempts that no injected fault explains: replies that came
/// after the response timeout although the simulator did not delay them.
/// The simulator is a thread of this process, on the same CPUs as the
/// other tests and whatever else the machine runs; kept from running for
/// longer than the timeout, it answers late like a slow drive would. That
/// is the machine's doing, not the master's, so it is allowed, but it must
/// be rare (a master that gave up early would make most replies late) and
/// each must be a reply the master did not take
/// ([`assert_late_replies_discarded`]): its attempt timed out, or, when
/// the machine held it past the guard time too, the attempt it met refused
/// it as a bad reply (what RTU allows: never taken as an answer). Every
/// injected fault still fails its attempt: fewer failed attempts than
/// faults fails here.
pub fn late_by_the_machine(wire: &Wire, sim: &SimStats) -> u64 {
    let injected = sim.dropped + sim.unanswered + sim.late + sim.corrupted;
    let failed = wire.failed_attempts();
    assert!(
        failed >= injected,
        "{failed} failed attempts for {injected} injected faults: {wire:?} {sim}"
    );
    let late = failed - injected;
    assert!(
        late * 50 <= sim.requests,
        "{late} of {} replies came after the response timeout without being made late: {wire:?} {sim}",
        sim.requests
    );
    late
}

/// In a run without noise, the replies no attempt took are exactly the
/// late ones (the simulator's and `machine_late`); corrupted replies were
/// taken, and failed their CRC. Each of the simulator's late replies came
/// whole in the guard time and was discarded as stray bytes; one the
/// machine made later than the guard was flushed before the next request,
/// uncounted, so those only bound the count from above.
pub fn assert_late_replies_discarded(wire: &Wire, sim: &SimStats, machine_late: u64) {
    // A reply the machine held until the master had spoken again was given
    // up by the simulator (`stalled`): its attempt failed, but it never
    // came.
    let late = sim.late + machine_late.saturating_sub(sim.stalled);
    assert_eq!(
        sim.replies - (wire.ok + wire.exception + sim.corrupted),
        late,
        "replies not taken: {wire:?} {sim}"
    );
    assert!(
        (SHORTEST_REPLY * sim.late..=LONGEST_REPLY * late).contains(&wire.stray_bytes),
        "{} stray bytes for {} late replies and {machine_late} made late by the machine",
        wire.stray_bytes,
        sim.late
    );
}

/// The simulator's fault counters as `/metrics` exports them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Injected {
    pub requests: u64,
    pub dropped: u64,
    pub corrupted: u64,
    pub late: u64,
    pub noise: u64,
    pub gap_violations: u64,
}

impl Injected {
    /// The simulator's counters of bus `bus` in `s`.
    pub fn of(s: &Scrape, bus: &str) -> Self {
        let kind = |k: &str| {
            int(s.get(
                "drivegate_sim_injected_faults_total",
                &[("bus", bus), ("kind", k)],
            ))
        };
        Injected {
            requests: int(s.get("drivegate_sim_requests_total", &[("bus", bus)])),
            dropped: kind("dropped"),
            corrupted: kind("corrupted"),
            late: kind("late"),
            noise: kind("noise"),
            gap_violations: int(s.get("drivegate_sim_gap_violations_total", &[("bus", bus)])),
        }
    }
}

/// `drivegate_drive_up` of `unit` on bus `bus`.
pub fn drive_up(s: &Scrape, bus: &str, unit: u8) -> f64 {
    s.get(
        "drivegate_drive_up",
        &[("bus", bus), ("unit", &unit.to_string())],
    )
}

/// Stops the daemon (each bus finishes the frame on the wire, then its
/// thread ends) and scrapes `/metrics` once nothing moves any more, so the
/// bus's counters and the simulator's describe the same transactions. The
/// plant is returned to read the simulator's own counters.
pub async fn stop_and_scrape(d: crate::support::TestDaemon) -> (Scrape, Arc<Plant>) {
    let metrics = d.metrics.clone();
    let plant = d.plant.clone();
    d.stop().await;
    (Scrape::parse(&metrics.render()), plant)
}
