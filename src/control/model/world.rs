//! The core under test: the real `Control` over a plant whose bus the
//! bench serves, its clients (each face's caller, sessions opened and
//! closed as the steps say), its clock turned by hand, its journal in a
//! state directory of its own; `kill -9` and the start that follows.
//!
//! Everything runs on one current-thread runtime: a step acts, then the
//! world settles (every task of the core runs until it waits, the bench
//! serving the bus between), then the oracle reads what happened, in the
//! order it happened, and checks the invariants.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::bus::{BusHandle, SourceId};
use crate::config::Config;
use crate::control::lease_book::CommLoss;
use crate::control::live::Delivery;
use crate::control::outcome::{Applied, Failure, applied};
use crate::control::policy::Role;
use crate::control::time::Clock;
use crate::control::time::manual::Manual;
use crate::control::{Caller, Control, ControlRequest, Face, SessionGuard, Target, Write};
use crate::drive::{ConfigCommand, DriveRequest};

use super::bench::{self, Bench, Motion, Served, unit};
use super::oracle::{CoreDrive, Look, Oracle, Req};
use super::steps::{Cmd, DRIVES, Damage, Setup, Stale, Step, Who};

/// The bus's queue timeout, ms (a held bus is held for less).
const QUEUE_TIMEOUT_MS: u64 = 2000;

/// What the face tasks and the bench tell the oracle, in order.
#[derive(Debug)]
pub(super) enum Event {
    /// A request is on the queue (its lease in place): when (the core's
    /// clock), and the order it was sent in (the bus's clock).
    Queued(usize, Instant, Instant),
    /// The core refused a request before it was sent.
    Refused(usize),
    /// A request's result.
    Done(usize, Applied, Instant),
    /// A request the bus took nothing of (its lease taken and given back).
    NotSent(usize, Instant, Instant),
    /// The bench served a job.
    Served(Served),
}

type Log = Arc<Mutex<Vec<Event>>>;

fn push(log: &Log, event: Event) {
    log.lock().unwrap_or_else(|p| p.into_inner()).push(event);
}

/// A running drivegate.
struct Process {
    control: Control,
    handle: BusHandle,
    shutdown: CancellationToken,
    dir: PathBuf,
    /// Each client's open session, with its generation.
    sessions: Vec<Option<(SessionGuard, u64)>>,
    /// Requests waiting for their result, by client.
    tasks: Vec<(Who, JoinHandle<()>)>,
}

/// The plant, the core and its clients.
pub(super) struct World {
    setup: Setup,
    template: Config,
    clock: Arc<Manual>,
    bench: Bench,
    oracle: Oracle,
    log: Log,
    root: PathBuf,
    runs: u32,
    callers: Vec<Caller>,
    process: Option<Process>,
    /// Print what happens (`DRIVEGATE_MODEL_TRACE=1`).
    trace: bool,
}

/// The configuration every case runs with, but for `[safety]`'s actions.
fn template(setup: &Setup) -> Result<Config, String> {
    let text = format!(
        r#"
[[bus]]
name = "line"
port = "/dev/null"
response_timeout_ms = {timeout}
retries = {retries}
queue_timeout_ms = {QUEUE_TIMEOUT_MS}
offline_after = 1

[[bus.drive]]
unit = 1
name = "belt"

[[bus.drive]]
unit = 2
name = "lift"

[monitor]
ring_frames = 16

[safety]
on_lease_expiry = "{expiry}"
on_unknown_state = "{unknown}"
"#,
        timeout = bench::TIMEOUT_MS,
        retries = bench::ATTEMPTS - 1,
        expiry = setup.on_lease_expiry.name(),
        unknown = setup.on_unknown_state.name(),
    );
    Config::parse(&text, "model.toml").map_err(|e| e.to_string())
}

/// How long the core allows a write of this bus to be settled: the queue
/// wait and every attempt's timeout, with a second's margin.
fn allowance() -> Duration {
    let per_attempt = 2 * bench::TIMEOUT_MS;
    Duration::from_millis(QUEUE_TIMEOUT_MS + per_attempt * u64::from(bench::ATTEMPTS) + 1000)
}

fn caller(who: Who) -> Caller {
    let (face, name, role) = match who {
        Who::Panel => (Face::Http, "panel", Role::Operator),
        Who::Engineer => (Face::Http, "eng", Role::Admin),
        Who::Display => (Face::Http, "display", Role::Viewer),
        Who::Hmi => (Face::WebSocket, "hmi", Role::Operator),
        Who::Plc => (Face::ModbusTcp, "10.0.0.7:50412", Role::Operator),
        Who::Scada => (Face::Mqtt, "scada", Role::Operator),
        Who::Opcua => (Face::OpcUa, "alice (10.0.0.5:50412)", Role::Operator),
    };
    Caller::new(face, name, role, SourceId::new_unique())
}

fn request(cmd: Cmd) -> DriveRequest {
    match cmd {
        Cmd::Activate => DriveRequest::Config(ConfigCommand::Activate),
        Cmd::Deactivate => DriveRequest::Config(ConfigCommand::Deactivate),
        Cmd::Brake => DriveRequest::Config(ConfigCommand::EmergencyBrake),
        Cmd::SpeedMode => DriveRequest::Config(ConfigCommand::SpeedMode),
        Cmd::TorqueMode => DriveRequest::Config(ConfigCommand::TorqueMode),
        Cmd::Speed(rpm) => DriveRequest::Speed { rpm },
        Cmd::Torque(counts) => DriveRequest::Torque { counts },
    }
}

fn target(d: usize) -> Target {
    Target {
        bus: 0,
        unit: unit(d),
        drive: Some(d),
    }
}

/// A directory for a case's state: in memory where there is one (the
/// journal syncs each record).
pub(super) fn scratch() -> Result<tempfile::TempDir, String> {
    let shm = Path::new("/dev/shm");
    let mut builder = tempfile::Builder::new();
    builder.prefix("drivegate-model-");
    let dir = if shm.is_dir() {
        builder.tempdir_in(shm)
    } else {
        builder.tempdir()
    };
    dir.map_err(|e| format!("no scratch directory: {e}"))
}

impl World {
    /// The plant of `setup`, and drivegate's first start on it, in `root`.
    pub(super) fn new(setup: Setup, root: &Path) -> Result<World, String> {
        let clock = Arc::new(Manual::new(
            SystemTime::UNIX_EPOCH + Duration::from_secs(1_800_000_000),
        ));
        let log: Log = Arc::default();
        let mut world = World {
            setup,
            template: template(&setup)?,
            clock,
            bench: Bench::new(setup.active),
            oracle: Oracle::new(setup, allowance()),
            log,
            root: root.to_path_buf(),
            runs: 0,
            callers: Who::ALL.iter().map(|w| caller(*w)).collect(),
            process: None,
            trace: std::env::var("DRIVEGATE_MODEL_TRACE").is_ok_and(|v| v == "1"),
        };
        world.start(Vec::new())?;
        Ok(world)
    }

    /// Lets the first start settle, and checks.
    pub(super) async fn settle_start(&mut self) -> Result<(), String> {
        self.settle().await;
        self.look()
    }

    fn now(&self) -> Instant {
        self.clock.now()
    }

    /// Starts drivegate with a state directory holding `files`.
    fn start(&mut self, files: Vec<(String, Vec<u8>)>) -> Result<(), String> {
        self.runs += 1;
        let dir = self.root.join(format!("run{}", self.runs));
        std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
        for (name, bytes) in &files {
            std::fs::write(dir.join(name), bytes).map_err(|e| e.to_string())?;
        }
        let mut config = self.template.clone();
        config.safety.state_dir = Some(dir.clone());
        let settings = config.buses[0].settings("/dev/null");
        let handle = BusHandle {
            shared: crate::bus::scheduler::new_shared(&settings),
        };
        let plant = Arc::new(crate::plant::served(&config, vec![handle.clone()]));
        let shutdown = CancellationToken::new();
        let control = Control::start_with_clock(
            plant,
            &config.safety,
            shutdown.clone(),
            Clock::Manual(self.clock.clone()),
        );
        self.bench.attach(&handle);
        self.bench
            .follow_journal(dir.join(crate::control::journal::FILE));
        self.bench.poll(&handle, self.now());
        self.process = Some(Process {
            control,
            handle,
            shutdown,
            dir,
            sessions: (0..Who::ALL.len()).map(|_| None).collect(),
            tasks: Vec::new(),
        });
        Ok(())
    }

    /// Runs one step, then checks the invariants.
    pub(super) async fn step(&mut self, step: &Step) -> Result<(), String> {
        if self.trace {
            eprintln!("{:?} {step:?}", self.now());
        }
        self.oracle.expire(self.now());
        match *step {
            Step::Write {
                who,
                drive,
                cmd,
                lease_ms,
            } => self.write(who, drive, cmd, lease_ms, None),
            Step::Stale {
                drive,
                cmd,
                delivery,
            } => self.write(Who::Scada, drive, cmd, None, Some(delivery)),
            Step::Renew {
                who,
                drive,
                length_ms,
            } => self.renew(who, drive, length_ms),
            Step::Release { who, drive } => self.release(who, drive),
            Step::Activity { who } => self.activity(who),
            Step::Gone { who } => self.gone(who).await?,
            Step::Advance { ms } => return self.advance(Duration::from_millis(ms.into())).await,
            Step::Hold { ms } => {
                let until = self.now() + Duration::from_millis(ms.into());
                self.bench.hold(until);
            }
            Step::Fault { drive, trouble } => self.bench.inject(drive, trouble, self.now()),
            Step::BusDown { ms } => {
                let until = self.now() + Duration::from_millis(ms.into());
                if let Some(p) = &self.process {
                    self.bench.port_down(&p.handle, until, self.now());
                }
                self.flush_served();
            }
            Step::Restart {
                wire,
                damage,
                down_ms,
            } => {
                return self
                    .restart(wire, damage, Duration::from_millis(down_ms.into()))
                    .await;
            }
        }
        self.settle().await;
        self.look()
    }

    fn process(&self) -> Result<&Process, String> {
        self.process
            .as_ref()
            .ok_or_else(|| "drivegate is not running".to_string())
    }

    /// `who`'s caller, in its session (opened if it has none).
    fn session_caller(&mut self, who: Who) -> Option<Caller> {
        let base = self.callers[who.index()].clone();
        if !who.has_session() {
            return Some(base);
        }
        let p = self.process.as_mut()?;
        if p.sessions[who.index()].is_none() {
            let comm_loss = self.setup.comm_loss_of(who).map(|(ms, action)| CommLoss {
                after: Duration::from_millis(ms.into()),
                action,
                face: base.face,
            });
            let (guard, _news) = p.control.open_session("its session closed", comm_loss);
            let generation = self.oracle.open(who);
            p.sessions[who.index()] = Some((guard, generation));
        }
        let (guard, _) = p.sessions[who.index()].as_ref()?;
        Some(base.in_session(base.face, guard.id()))
    }

    /// `who` sends `cmd` to `drive`; `stale`: a command that did not come
    /// live, which the core must refuse before anything else.
    fn write(
        &mut self,
        who: Who,
        drive: usize,
        cmd: Cmd,
        lease_ms: Option<u32>,
        stale: Option<Stale>,
    ) {
        let Some(caller) = self.session_caller(who) else {
            return;
        };
        if who.comm_loss() && stale.is_none() {
            self.activity(who);
        }
        let drive_request = request(cmd);
        let Ok(pdu) = drive_request.pdu() else {
            return;
        };
        let lease = lease_ms.map(|ms| Duration::from_millis(ms.into()));
        let control_request = match who {
            // A PLC writes registers: the core decodes what they mean.
            Who::Plc => ControlRequest::new(Write::pdu(pdu.clone())),
            _ => ControlRequest::drive(drive_request).with_lease(lease),
        };
        let id = self.oracle.reqs.len();
        self.oracle.reqs.push(Req::new(
            who,
            caller.role,
            caller.source,
            drive,
            cmd,
            pdu,
            self.oracle.terms(who, cmd, lease_ms),
            self.oracle.session(who),
            caller.owner(),
        ));
        self.oracle.reqs[id].stale = stale.is_some();
        let Some(p) = self.process.as_mut() else {
            return;
        };
        let control = p.control.clone();
        let log = self.log.clone();
        let clock = self.clock.clone();
        let delivery = stale.map(|s| match s {
            Stale::Retained => Delivery::Retained,
            Stale::Queued => Delivery::Queued,
            Stale::Older => Delivery::Older {
                sent_ms: 1_799_999_000_000,
                connected_ms: 1_800_000_000_000,
            },
        });
        let task = tokio::spawn(async move {
            if let Some(delivery) = delivery
                && control
                    .check_live(&caller, "drive", "a command", delivery)
                    .is_err()
            {
                push(&log, Event::Refused(id));
                return;
            }
            match control
                .submit(&caller, target(drive), control_request)
                .await
            {
                Ok(mut pending) => {
                    push(&log, Event::Queued(id, clock.now(), Instant::now()));
                    pending.wait().await;
                    let result = pending.finish();
                    push(&log, Event::Done(id, applied(&result), clock.now()));
                }
                // Refused by the bus after its lease was taken: settled
                // as never sent.
                Err(Failure::NotSent(_)) => {
                    push(&log, Event::NotSent(id, clock.now(), Instant::now()));
                }
                Err(_) => push(&log, Event::Refused(id)),
            }
        });
        p.tasks.push((who, task));
    }

    fn renew(&mut self, who: Who, drive: usize, length_ms: Option<u32>) {
        let Some(caller) = self.session_caller(who) else {
            return;
        };
        let length = length_ms.map(|ms| Duration::from_millis(ms.into()));
        let now = self.now();
        if let Some(p) = &self.process {
            let _ = p.control.renew(&caller, drive, length);
        }
        self.oracle.renewed(who, caller.role, drive, length, now);
        self.oracle.note_ends();
    }

    fn release(&mut self, who: Who, drive: usize) {
        let Some(caller) = self.session_caller(who) else {
            return;
        };
        if let Some(p) = &self.process {
            let _ = p.control.release(&caller, drive);
        }
        self.oracle.released(caller.role, drive);
    }

    fn activity(&mut self, who: Who) {
        let now = self.now();
        let Some(p) = &self.process else {
            return;
        };
        if let Some((guard, _)) = &p.sessions[who.index()] {
            guard.active();
            self.oracle.active(who, now);
            self.oracle.note_ends();
        }
    }

    /// `who` goes away: its requests waiting for their result are dropped
    /// first (as a face cancels them), then its session closes.
    async fn gone(&mut self, who: Who) -> Result<(), String> {
        let now = self.now();
        let Some(p) = self.process.as_mut() else {
            return Ok(());
        };
        for (_, task) in p.tasks.iter().filter(|(w, _)| *w == who) {
            task.abort();
        }
        p.tasks.retain(|(w, _)| *w != who);
        self.yield_a_while().await;
        self.drain()?;
        self.oracle.gone(who, now);
        if let Some(p) = self.process.as_mut() {
            drop(p.sessions[who.index()].take());
        }
        Ok(())
    }

    /// Lets every task of the core run until it waits, the bench serving
    /// no job: a few turns of the runtime (each task that was woken runs,
    /// and what it wakes runs at the next).
    async fn yield_a_while(&self) {
        for _ in 0..4 {
            tokio::task::yield_now().await;
        }
    }

    /// Lets every task run until it waits, the bench serving the bus
    /// (when it carries anything) until nothing is left to serve; then the
    /// poller's round, and again if a drive or the bus came or went.
    async fn settle(&mut self) {
        loop {
            let mut quiet = 0;
            while quiet < 3 {
                self.yield_a_while().await;
                let served = match &self.process {
                    Some(p) => self.bench.serve_one(&p.handle, self.clock.now()),
                    None => false,
                };
                self.flush_served();
                quiet = if served { 0 } else { quiet + 1 };
            }
            let changed = match &self.process {
                Some(p) => self.bench.poll(&p.handle, self.clock.now()),
                None => false,
            };
            if !changed {
                break;
            }
        }
        if let Some(p) = self.process.as_mut() {
            p.tasks.retain(|(_, t)| !t.is_finished());
        }
    }

    /// Puts what the bench served on the log, after what the tasks said
    /// before it.
    fn flush_served(&mut self) {
        let served = self.bench.take_served();
        if served.is_empty() {
            return;
        }
        let mut log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        log.extend(served.into_iter().map(Event::Served));
    }

    /// Feeds the oracle what happened since it last looked.
    fn drain(&mut self) -> Result<(), String> {
        let events = std::mem::take(&mut *self.log.lock().unwrap_or_else(|p| p.into_inner()));
        for event in events {
            if self.trace {
                eprintln!("    {event:?}");
            }
            match event {
                Event::Queued(id, at, sent) => self.oracle.queued(id, at, sent),
                Event::Refused(id) => self.oracle.refused(id),
                Event::Done(id, applied, at) => self.oracle.settled(id, applied, at),
                Event::NotSent(id, at, sent) => self.oracle.not_sent(id, at, sent),
                Event::Served(s) => {
                    if let Some(broken) = self.oracle.served(&s) {
                        return Err(broken);
                    }
                }
            }
            self.oracle.note_ends();
        }
        Ok(())
    }

    /// What the core shows of each drive.
    fn core(&self) -> Vec<CoreDrive> {
        let Some(p) = &self.process else {
            return vec![
                CoreDrive {
                    lease: None,
                    stopping: false,
                };
                DRIVES
            ];
        };
        (0..DRIVES)
            .map(|d| CoreDrive {
                lease: p.control.lease(d),
                stopping: p.control.0.parts.leases().read(|book, _| book.stopping(d)),
            })
            .collect()
    }

    fn motions(&self) -> Vec<Motion> {
        (0..DRIVES).map(|d| self.bench.motion(d)).collect()
    }

    fn reachable(&self) -> Vec<bool> {
        (0..DRIVES).map(|d| !self.bench.unreachable(d)).collect()
    }

    fn troubled(&self) -> Vec<bool> {
        let now = self.now();
        (0..DRIVES)
            .map(|d| self.bench.troubled(d, now, Oracle::retry_window()))
            .collect()
    }

    /// Reads what happened and checks invariant 1.
    fn look(&mut self) -> Result<(), String> {
        self.drain()?;
        let now = self.now();
        self.oracle.expire(now);
        let (core, motion, troubled) = (self.core(), self.motions(), self.troubled());
        let reachable = self.reachable();
        self.oracle.check(&Look {
            now,
            core: &core,
            motion: &motion,
            troubled: &troubled,
            reachable: &reachable,
        })
    }

    /// Time passes: the clock moves from one wake of the core or change
    /// of the bench to the next, the world settling and the invariants
    /// checked at each.
    async fn advance(&mut self, by: Duration) -> Result<(), String> {
        let end = self.now() + by;
        loop {
            let now = self.now();
            let next = [self.clock.next_wake(), self.bench.next_change()]
                .into_iter()
                .flatten()
                .filter(|t| *t > now)
                .fold(end, Instant::min);
            self.clock.set(next);
            if let Some(p) = &self.process {
                self.bench.catch_up(&p.handle, next);
            }
            self.settle().await;
            self.look()?;
            if next >= end {
                return Ok(());
            }
        }
    }

    /// `kill -9`, the journal left with `damage`, and a start `down` later.
    async fn restart(&mut self, wire: bool, damage: Damage, down: Duration) -> Result<(), String> {
        let Some(p) = self.process.take() else {
            return Ok(());
        };
        let now = self.now();
        if wire {
            self.bench.kill_on_wire(&p.handle, now);
        }
        self.flush_served();
        self.process = Some(p);
        self.drain()?;
        let (core, motion) = (self.core(), self.motions());
        self.oracle.killed(now, damage, &core, &motion);
        self.oracle.forget_unknown();
        let Some(p) = self.process.take() else {
            return Ok(());
        };
        let mut files = snapshot(&p.dir);
        let floor = self.bench.journal_floor();
        // The process vanishes: nothing it still does reaches a drive.
        Bench::abandon(&p.handle);
        p.shutdown.cancel();
        for (_, task) in &p.tasks {
            task.abort();
        }
        let Process {
            control, sessions, ..
        } = p;
        drop(sessions);
        self.yield_a_while().await;
        drop(control);
        self.log.lock().unwrap_or_else(|e| e.into_inner()).clear();
        self.bench.take_served();

        self.clock.advance(down);
        self.bench.reopen();
        harm(&mut files, damage, floor);
        self.start(files)?;
        let found = self.motions();
        let control = self.process()?.control.clone();
        let replay = tokio::spawn(async move { control.replay().await });
        while !replay.is_finished() {
            self.settle().await;
        }
        self.settle().await;
        self.drain()?;
        let now = self.now();
        self.oracle.expire(now);
        let (core, motion, troubled) = (self.core(), self.motions(), self.troubled());
        let reachable = self.reachable();
        let look = Look {
            now,
            core: &core,
            motion: &motion,
            troubled: &troubled,
            reachable: &reachable,
        };
        self.oracle.check_restart(damage, &look)?;
        let unknown = damage == Damage::Garbled || damage.lost();
        if unknown {
            self.oracle.check_unknown(&found, &look)?;
        }
        self.oracle.restarted();
        self.oracle.check(&look)
    }

    /// The texts of the `unknown-state` alarms the running process raised.
    pub(super) fn unknown_state_alarms(&self) -> Vec<String> {
        self.process.as_ref().map_or_else(Vec::new, |p| {
            p.control
                .alarms()
                .list()
                .into_iter()
                .filter(|a| a.kind == crate::control::alarms::AlarmKind::UnknownState)
                .map(|a| a.text)
                .collect()
        })
    }

    /// Ends the case: drivegate stops. Its tasks see the shutdown before
    /// the runtime goes: a bus's followers (the alarm list's, holding the
    /// plant that holds the bus) leave its feed only then, and a case
    /// would otherwise keep its whole process, the alarm file's writer
    /// thread with it.
    pub(super) async fn finish(mut self) {
        if let Some(p) = self.process.take() {
            Bench::abandon(&p.handle);
            p.shutdown.cancel();
            self.yield_a_while().await;
        }
    }
}

/// The files of the state directory `dir`, as the disk holds them.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let bytes = std::fs::read(e.path()).ok()?;
            Some((name, bytes))
        })
        .collect()
}

/// Leaves the journal among `files` as `damage` says; `floor` is its
/// length when the bus last sent something.
fn harm(files: &mut Vec<(String, Vec<u8>)>, damage: Damage, floor: u64) {
    let journal = crate::control::journal::FILE;
    if damage == Damage::Deleted {
        files.retain(|(name, _)| name != journal);
        return;
    }
    let Some((_, bytes)) = files.iter_mut().find(|(name, _)| name == journal) else {
        return;
    };
    match damage {
        Damage::Intact | Damage::Deleted => {}
        Damage::Torn(thousandths) => {
            let len = bytes.len();
            let floor = usize::try_from(floor).unwrap_or(usize::MAX).min(len);
            let keep = floor + (len - floor) * usize::from(thousandths.min(1000)) / 1000;
            bytes.truncate(keep);
        }
        Damage::Garbled => {
            if let Some(b) = bytes.first_mut() {
                *b ^= 0xFF;
            }
        }
        Damage::Emptied => bytes.clear(),
        Damage::HeaderOnly => bytes.truncate(crate::control::journal::format::HEADER_LEN),
    }
}
