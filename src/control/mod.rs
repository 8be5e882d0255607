//! The control core: the one write path of the daemon, under every face.
//!
//! A face (HTTP, the WebSocket stream, Modbus TCP, and whatever comes next)
//! only authenticates its client into a [`Caller`], translates its request
//! into a [`ControlRequest`] for a [`Target`], calls [`Control::submit`] or
//! [`Control::write`], and renders the typed result. Everything a write
//! means for the motor is decided here, the same for every face:
//!
//! - [`policy`]: which role may do what, and what a write means (a
//!   setpoint, a brake, a save to flash, ...);
//! - the checks before sending (in [`write`]): the role; a setpoint only to
//!   an active drive (as the drive itself would answer); saves, factory
//!   reset, address setting and calibration only at standstill unless the
//!   face's override says so; an address broadcast only to a bus with one
//!   drive;
//! - [`lease_book`] (pure) and its driver [`leases`]: motor-safety leases,
//!   their stops, and the rule that a brake holds;
//! - [`outcome`]: what became of a write, typed from the bus up;
//! - [`audit`] and [`events`]: one wording in the log, one broadcast of
//!   lease news and writes for whoever listens;
//! - [`alarms`]: what needs an operator's attention, raised from the
//!   buses' and the core's events, kept across restarts, acknowledged
//!   through [`Control::acknowledge_alarm`];
//! - [`freshness`]: each change of a drive's data's freshness, told on
//!   the events for the faces that show it.
//!
//! [`Control`]'s whole surface stands in this file, beside the type: each
//! method is a few lines that hand the work to its concept's free
//! functions ([`write`](mod@write), [`settings`], [`reload`],
//! [`replacement`]), so a reader finds what the core offers in one place
//! and how each part works in the file named for it. Those functions take
//! the core's shared parts (`parts.rs`: plant, leases, events, lease
//! settings), not the handle, so no file of the folder imports this one.
//! What the events and the audit log carry is in [`news`], at the bottom.

pub mod alarms;
pub mod audit;
pub mod caller;
pub mod certificates;
pub mod config_edits;
pub mod drift;
pub mod events;
pub mod freshness;
pub mod identity;
pub mod journal;
pub mod lease_book;
pub mod leases;
pub mod live;
pub mod networks;
pub mod news;
pub mod outcome;
mod parts;
pub mod policy;
pub mod reload;
pub mod replacement;
pub mod request;
pub mod restart;
pub mod rules;
pub mod settings;
pub mod shutdown;
pub mod stop_action;
pub mod throttle;
pub mod time;
pub mod write;
pub mod written;

#[cfg(test)]
mod model;

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{broadcast, mpsc, watch};
use tokio_util::sync::CancellationToken;

pub use caller::{Caller, Face, SessionId};
pub use events::{ControlEvent, Published, WriteEnd, WriteEvent};
pub use lease_book::{CommLoss, LeaseEvent, LeaseView, NoLease};
pub use outcome::{Applied, Failure, Outcome, Refusal, Rule, WriteResult};
pub use policy::{Operation, Role};
pub use request::{ControlRequest, Target, Write};
pub use rules::LeaseBounds;
pub use shutdown::shutdown;
pub use write::Pending;

use crate::bus::BusError;
use crate::config::Config;
use crate::control::stop_action::{SafetyConfig, StopAction};
use crate::drive::Status;
use crate::drive::settings::DriveSettings;
use crate::drive::wanted::Document;
use crate::plant::{LookupError, Plant};
use events::Events;
use journal::Journal;
use journal::replay::Recovered;
use leases::Leases;
use parts::Parts;
use reload::{NewText, ReloadRequest, ReloadResult, ReloadStatus};
use replacement::ReplacementEvent;
use settings::{ApplyOptions, SettingsError, SettingsReport};

/// Why an alarm could not be acknowledged.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AlarmError {
    /// The caller may not.
    Refused(Refusal),
    /// There is no such alarm.
    Unknown(alarms::AckError),
}

/// Why a lease could not be renewed or released.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LeaseError {
    /// The caller may not.
    Refused(Refusal),
    /// There is none; the text says what became of the last one.
    NoLease(NoLease),
}

/// The handle every face holds; cheap to clone.
#[derive(Clone)]
pub struct Control(Arc<Inner>);

struct Inner {
    /// The plant, the lease driver, the events and the lease settings.
    parts: Arc<Parts>,
    alarms: Arc<alarms::Alarms>,
    /// Reloads of the configuration.
    reloads: reload::Reloads,
    /// The last changes written into the configuration file.
    edits: config_edits::EditLog,
    /// The certificates' store, once the daemon attached it.
    certificates: certificates::Certificates,
    /// What the journal held at start-up, until it is replayed.
    recovered: std::sync::Mutex<Option<Recovered>>,
    on_unknown_state: StopAction,
    /// What start-up found in the journal, in words (for `/readyz`).
    journal_news: Vec<String>,
    /// Replayed decisions by kind.
    replayed: std::sync::Mutex<restart::Counts>,
    /// The replay's decisions in words, for the stream's clients.
    restart_notes: std::sync::Mutex<Vec<restart::RestartNote>>,
    /// Drives compared with their declared settings.
    drift: Arc<drift::DriftBook>,
}

impl Control {
    /// The core over `plant`, with `safety`'s lease-expiry action; its
    /// lease driver stops when `shutdown` fires.
    pub fn start(plant: Arc<Plant>, safety: &SafetyConfig, shutdown: CancellationToken) -> Self {
        Self::start_with_clock(plant, safety, shutdown, time::Clock::System)
    }

    /// [`start`](Self::start), its leases' time read from `clock`.
    pub(crate) fn start_with_clock(
        plant: Arc<Plant>,
        safety: &SafetyConfig,
        shutdown: CancellationToken,
        clock: time::Clock,
    ) -> Self {
        let events = Arc::new(Events::default());
        let state_dir = safety.state_dir();
        // The journal first: what the state directory held before this
        // start (the alarm file among it) tells a lost journal from a
        // first start.
        let opened = Journal::open(state_dir.as_deref(), plant.now().drive_count());
        let alarms = alarms::Alarms::open(state_dir.as_deref(), safety.alarms_kept, events.clone());
        alarms.reconcile(&plant);
        alarms.watch(&plant, events.subscribe(), &shutdown);
        freshness::watch(&plant, events.clone(), &shutdown);
        for news in &opened.news {
            match opened.journal.health() {
                journal::Health::Off(_) => tracing::info!("{news}"),
                _ => tracing::warn!("{news}"),
            }
        }
        let leases = Leases::start(
            plant.clone(),
            safety.on_lease_expiry,
            events.clone(),
            opened.journal,
            shutdown.clone(),
            clock,
        );
        let parts = Arc::new(Parts::new(plant, leases, events, safety));
        let control = Control(Arc::new(Inner {
            parts: parts.clone(),
            alarms,
            reloads: reload::Reloads::default(),
            edits: config_edits::EditLog::default(),
            certificates: certificates::Certificates::default(),
            recovered: std::sync::Mutex::new(Some(opened.recovered)),
            on_unknown_state: safety.on_unknown_state,
            journal_news: opened.news,
            replayed: std::sync::Mutex::new(restart::Counts::new()),
            restart_notes: std::sync::Mutex::new(Vec::new()),
            drift: Arc::new(drift::DriftBook::default()),
        }));
        drift::start(&control.0.drift, &parts, &shutdown);
        control
    }

    /// Checks `request` for `caller`, puts it on the bus queue, and
    /// returns the way to its result. A refusal, a failed check or a bus
    /// that takes nothing is settled (audited) and returned at once.
    pub async fn submit(
        &self,
        caller: &Caller,
        target: Target,
        request: ControlRequest,
    ) -> Result<Pending, Failure> {
        write::submit(&self.0.parts, caller, target, request).await
    }

    /// [`submit`](Self::submit), then waits for the result.
    pub async fn write(
        &self,
        caller: &Caller,
        target: Target,
        request: ControlRequest,
    ) -> WriteResult {
        write::write(&self.0.parts, caller, target, request).await
    }

    /// Audits a write its face could not make into a request (`what` the
    /// caller asked for, `why` it cannot be made: a value out of the
    /// drive's range naming the range, a mode the drive does not have), as
    /// every refusal is: nothing is sent, and the stream hears of it.
    pub fn refused(&self, caller: &Caller, target: Target, what: String, why: String) {
        write::refused_unmade(&self.0.parts, caller, target, what, why);
    }

    /// Reads the drive's status now (not from the poll cache), with the
    /// caller's turn on the bus.
    pub async fn read_status(&self, caller: &Caller, target: Target) -> Result<Status, BusError> {
        write::read_status(&self.0.parts, caller, target).await
    }

    /// Reads what the drive at `target` holds: its setpoints and settings
    /// (six reads at command priority, with the caller's turn on the bus).
    /// A read changes nothing, so it is not audited.
    pub async fn read_settings(
        &self,
        caller: &Caller,
        target: Target,
    ) -> Result<DriveSettings, BusError> {
        settings::read_settings(&self.0.parts, caller, target).await
    }

    /// Puts `document` on the drive at `target` for `caller`: checked whole
    /// (ranges, then every write's rules), then written message by message,
    /// then read back. With `dry_run`, only compared and checked.
    pub async fn apply_settings(
        &self,
        caller: &Caller,
        target: Target,
        document: &Document,
        options: ApplyOptions,
    ) -> Result<SettingsReport, SettingsError> {
        let done =
            settings::apply_settings(&self.0.parts, caller, target, document, options).await?;
        // Then, for a drive with a declaration, what it holds now.
        if let (Some(index), Some(held)) = (target.drive, &done.held) {
            self.0.drift.after_apply(&self.0.parts, index, held);
        }
        Ok(done.report)
    }

    /// [`apply_settings`](Self::apply_settings) of settings whose values
    /// were checked already (what the drive holds, saved to its flash by
    /// OPC UA's `Settings.Save()`).
    pub(crate) async fn apply_wanted(
        &self,
        caller: &Caller,
        target: Target,
        wanted: &crate::drive::wanted::Wanted,
        options: ApplyOptions,
    ) -> Result<SettingsReport, SettingsError> {
        let done = settings::apply_wanted(&self.0.parts, caller, target, wanted, options).await?;
        if let (Some(index), Some(held)) = (target.drive, &done.held) {
            self.0.drift.after_apply(&self.0.parts, index, held);
        }
        Ok(done.report)
    }

    /// The daemon's reloader of `file` takes reloads from here on.
    pub fn attach_reloader(&self, reloader: mpsc::Sender<ReloadRequest>, file: &std::path::Path) {
        self.0.reloads.attach(reloader, file);
    }

    /// Reloads the configuration for `caller` (an admin), optionally
    /// writing `write` into the file first; audited either way, with the
    /// change's lines when it writes.
    pub async fn reload(&self, caller: &Caller, write: Option<NewText>) -> ReloadResult {
        let edit = write
            .as_ref()
            .map(|w| config_edits::ConfigEdit::of(caller, w));
        let result = reload::reload(&self.0.reloads, caller, write).await;
        if let (Ok(_), Some(edit)) = (&result, edit) {
            self.0.edits.record(edit);
        }
        result
    }

    /// The last changes written into the configuration file through the
    /// core, oldest first (who made the file as it is).
    pub fn config_edits(&self) -> Vec<config_edits::ConfigEdit> {
        self.0.edits.all()
    }

    /// Asks the reloader, for a caller the daemon vouches for (SIGHUP).
    pub(crate) async fn reload_as(&self, by: String, write: Option<NewText>) -> ReloadResult {
        self.0.reloads.ask(by, write).await
    }

    /// The configuration file a reload reads, if drivegate was started
    /// with one.
    pub fn config_file(&self) -> Option<std::path::PathBuf> {
        self.0.reloads.file()
    }

    /// What became of reloads since start-up.
    pub fn reload_status(&self) -> ReloadStatus {
        self.0.reloads.status()
    }

    /// Records what became of a reload (by the reloader).
    pub fn record_reload(&self, result: &ReloadResult) {
        self.0.reloads.record(result);
    }

    /// The running configuration, as last loaded; a face follows it for
    /// its own section (`changed().await`, then `borrow_and_update()`).
    pub fn follow_config(&self) -> watch::Receiver<Option<Arc<Config>>> {
        self.0.reloads.follow()
    }

    /// Publishes the running configuration: at start-up, and after each
    /// reload once the plant follows it. Applies `[safety]`'s lease bounds,
    /// jog lease and lease-expiry action to leases granted from now on.
    pub fn set_config(&self, config: Arc<Config>) {
        self.0.parts.set_safety(&config.safety);
        self.0.reloads.publish(config);
    }

    /// Stops the drives (slot indices) a reload removes, while their bus
    /// still runs: a drive with a lease gets its lease's stop, the others
    /// `on_shutdown` if they move; each stop audited. Returns what was
    /// done, in words, once every stop ended (or after a few seconds).
    pub async fn retire(&self, drives: &[usize], on_shutdown: StopAction) -> Vec<String> {
        reload::retire(&self.0.parts, drives, on_shutdown).await
    }

    /// Drive `old` of bus `bus` is named `new` now: a reload renamed it,
    /// the same motor at the same unit, which keeps its slot (its lease,
    /// its subscriptions). What the core keeps by name follows it: what
    /// the safety journal owes it, its alarms and its settings' latest
    /// comparison.
    pub fn renamed(&self, bus: &str, old: &str, new: &str) {
        self.0.parts.leases().renamed(old, new);
        self.alarms().rename(bus, old, new);
        self.0.drift.rename(old, new);
        tracing::info!(bus, drive = new, "drive {old} is named {new} now");
    }

    /// Notes in the audit log that `caller` started, finished or abandoned
    /// the replacement of drive `drive` (an index in the plant), with
    /// `detail` in the caller's words (where its settings came from, the
    /// time it took). Commissioning work: the admin role.
    pub fn note_replacement(
        &self,
        caller: &Caller,
        drive: usize,
        event: ReplacementEvent,
        detail: &str,
    ) -> Result<(), Refusal> {
        replacement::note_replacement(&self.0.parts, caller, drive, event, detail)
    }

    /// The daemon's certificates are in `store` from now on; their expiry
    /// is looked at now and every hour until `stop` (an alarm for each
    /// that expires within 30 days).
    pub fn attach_certificates(
        &self,
        store: Arc<dyn certificates::CertificateStore>,
        stop: CancellationToken,
    ) {
        self.0
            .certificates
            .attach(store, self.0.alarms.clone(), stop);
    }

    /// Every certificate the daemon serves, trusts or refused, for
    /// `caller` (an admin).
    pub async fn certificates(
        &self,
        caller: &Caller,
    ) -> Result<certificates::Listing, certificates::CertError> {
        self.0.certificates.list(caller).await
    }

    /// Trusts a refused OPC UA client, removes a trusted one or renews the
    /// server's own certificate, for `caller` (an admin); audited either
    /// way. Applies without a restart of the daemon.
    pub async fn certificate_action(
        &self,
        caller: &Caller,
        action: certificates::Action,
    ) -> Result<certificates::Done, certificates::CertError> {
        self.0
            .certificates
            .act(caller, action, &self.0.alarms)
            .await
    }

    /// Drives compared with their declared settings.
    pub fn drift(&self) -> &Arc<drift::DriftBook> {
        &self.0.drift
    }

    /// Replays the safety journal (once): what the last process owed the
    /// motors is owed again. Call before any face takes a client.
    pub async fn replay(&self) {
        let recovered = self
            .0
            .recovered
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        let Some(recovered) = recovered else {
            return;
        };
        let (alarms, plant) = (self.0.alarms.clone(), self.0.parts.plant().clone());
        let alarm: restart::Alarm = Arc::new(move |drive: &str, text: String| {
            alarms.unknown_state(&plant, drive, text);
        });
        let decisions = restart::run(
            self.0.parts.plant(),
            self.0.parts.leases(),
            &recovered,
            self.0.on_unknown_state,
            alarm,
        )
        .await;
        let mut counts = self.0.replayed.lock().unwrap_or_else(|p| p.into_inner());
        for d in &decisions {
            *counts.entry(restart::kind(&d.what)).or_default() += 1;
            if let Some(text) = restart::unknown_state_alarm(d) {
                self.0
                    .alarms
                    .unknown_state(self.0.parts.plant(), &d.drive, text);
            }
        }
        let at = std::time::SystemTime::now();
        *self
            .0
            .restart_notes
            .lock()
            .unwrap_or_else(|p| p.into_inner()) =
            decisions.iter().map(|d| restart::note(d, at)).collect();
    }

    /// What the start-up replay did, drive by drive, in words (empty when
    /// the last process owed nothing).
    pub fn restart_notes(&self) -> Vec<restart::RestartNote> {
        self.0
            .restart_notes
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Decisions of the start-up replay, by kind.
    pub fn replayed(&self) -> restart::Counts {
        self.0
            .replayed
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The safety journal's health and counts.
    pub fn journal(&self) -> (journal::Health, journal::Counts) {
        self.0
            .parts
            .leases()
            .journal(|j| (j.health().clone(), j.counts()))
    }

    /// What is wrong with the safety journal, in words (empty: nothing).
    pub fn journal_warnings(&self) -> Vec<String> {
        let mut out = self.0.journal_news.clone();
        match self.0.parts.leases().journal(|j| j.health().clone()) {
            journal::Health::Ok => {}
            journal::Health::Off(why) => {
                if !out.contains(&why) {
                    out.push(why);
                }
            }
            journal::Health::Failing(why) => out.push(format!(
                "{why}; leases work in memory only and are not kept across a restart"
            )),
        }
        out
    }

    /// The lease a console jog asks for (`[safety] jog_lease_ms`).
    pub fn jog_lease(&self) -> Duration {
        self.0.parts.jog_lease()
    }

    /// The shortest and longest lease a setpoint may ask for (`[safety]
    /// lease_min_ms`, `lease_max_ms`), from any face.
    pub fn lease_bounds(&self) -> LeaseBounds {
        self.0.parts.lease_bounds()
    }

    /// Buses and drives.
    pub fn plant(&self) -> &Arc<Plant> {
        self.0.parts.plant()
    }

    /// Every future event of the core.
    pub fn subscribe(&self) -> broadcast::Receiver<Published> {
        self.0.parts.events().subscribe()
    }

    /// The alarm list.
    pub fn alarms(&self) -> &Arc<alarms::Alarms> {
        &self.0.alarms
    }

    /// Acknowledges alarm `id` for `caller` (an operator's work), audited;
    /// answered once the acknowledgement is on the disk.
    pub async fn acknowledge_alarm(
        &self,
        caller: &Caller,
        id: u64,
    ) -> Result<alarms::Alarm, AlarmError> {
        rules::role(caller, Operation::AcknowledgeAlarm.needs()).map_err(AlarmError::Refused)?;
        let before = self.0.alarms.get(id).and_then(|a| a.ack);
        let alarm = self
            .0
            .alarms
            .acknowledge(id, &caller.who)
            .await
            .map_err(AlarmError::Unknown)?;
        if before.is_none() {
            audit::alarm_acknowledged(
                caller.face.name(),
                &caller.who,
                id,
                alarm.kind.name(),
                alarm.drive.as_deref().unwrap_or(""),
                &alarm.text,
            );
        }
        Ok(alarm)
    }

    /// The configured drive named `key` (or, on a single bus, with that
    /// unit number).
    pub fn target(&self, key: &str) -> Result<Target, LookupError> {
        let (index, drive, _) = self.0.parts.plant().find(key)?;
        Ok(Target {
            bus: drive.bus,
            unit: drive.unit,
            drive: Some(index),
        })
    }

    /// `unit` on bus `bus` (0: a broadcast), configured or not.
    pub fn unit_target(&self, bus: usize, unit: u8) -> Target {
        self.0.parts.unit_target(bus, unit)
    }

    /// Refuses a command of `caller` unless it came live from its sender
    /// (`delivery`, as its face received it; [`live::judge`]): a refused
    /// one is audited ("a retained command was ignored"), with `what` it
    /// asked of `subject` (a drive, or the node), and nothing of it may be
    /// carried out. Every command a face cannot vouch for as live passes
    /// here before anything else.
    pub fn check_live(
        &self,
        caller: &Caller,
        subject: &str,
        what: &str,
        delivery: live::Delivery,
    ) -> Result<(), Refusal> {
        live::judge(delivery).inspect_err(|refusal| {
            let why = refusal
                .detail
                .strip_prefix(delivery.ignored())
                .map_or(refusal.detail.as_str(), |rest| {
                    rest.trim_start_matches(": ")
                });
            audit::not_live(
                caller.face.name(),
                &caller.who,
                subject,
                what,
                delivery.ignored(),
                why,
            );
        })
    }

    /// Refuses `caller` unless its role allows `operation` (what is not
    /// a write: a write's role comes from its meaning, in
    /// [`submit`](Self::submit)).
    pub fn authorize(&self, caller: &Caller, operation: Operation) -> Result<(), Refusal> {
        rules::role(caller, operation.needs())
    }

    /// The lease on drive `drive`, if any.
    pub fn lease(&self, drive: usize) -> Option<LeaseView> {
        self.0
            .parts
            .leases()
            .read(|book, now| book.lease(drive, now))
    }

    /// Pushes the deadline of drive `drive`'s lease ahead by its length (or
    /// by a new `length`).
    pub fn renew(
        &self,
        caller: &Caller,
        drive: usize,
        length: Option<Duration>,
    ) -> Result<LeaseView, LeaseError> {
        rules::role(caller, Operation::Lease.needs()).map_err(LeaseError::Refused)?;
        if let Some(length) = length {
            self.lease_bounds()
                .check(length)
                .map_err(LeaseError::Refused)?;
        }
        let name = self.0.parts.drive_name(drive);
        self.0.parts.leases().with(|book, now| {
            let result = book
                .renew(drive, length, now)
                .map_err(|e| LeaseError::NoLease(named(&name, e)));
            (result, Vec::new())
        })
    }

    /// Ends drive `drive`'s lease without a stop: the motor keeps its
    /// setpoint, unguarded.
    pub fn release(&self, caller: &Caller, drive: usize) -> Result<LeaseView, LeaseError> {
        rules::role(caller, Operation::Lease.needs()).map_err(LeaseError::Refused)?;
        let name = self.0.parts.drive_name(drive);
        let released = self.0.parts.leases().with(|book, now| {
            match book.release(drive, &caller.who, now) {
                Ok((view, effects)) => (Ok(view), effects),
                Err(e) => (Err(LeaseError::NoLease(named(&name, e))), Vec::new()),
            }
        })?;
        audit::released(caller.face.name(), &caller.who, &name);
        Ok(released)
    }

    /// Opens a session whose leases end when it closes (`closing` is how
    /// that reads: "its WebSocket closed"). With `comm_loss`, its setpoints
    /// and mode commands each take a lease that any request of the session
    /// renews ([`SessionGuard::active`]) and silence ends: the
    /// communication-loss function of a Modbus TCP client's network. News
    /// of the end of its leases comes out of the receiver, never skipped.
    pub fn open_session(
        &self,
        closing: &'static str,
        comm_loss: Option<CommLoss>,
    ) -> (SessionGuard, mpsc::UnboundedReceiver<Arc<ControlEvent>>) {
        let (id, rx) = self.0.parts.leases().open_session(closing, comm_loss);
        (
            SessionGuard {
                id,
                watched: comm_loss.is_some(),
                leases: self.0.parts.leases().clone(),
            },
            rx,
        )
    }

    /// Communication-loss leases of bus `bus` held by sessions of `face`
    /// that ended since start-up: by silence (no request within the time,
    /// or for MQTT no broker), and by their session closing. Each was
    /// followed by its action.
    pub fn comm_loss_ends(&self, bus: usize, face: Face) -> (u64, u64) {
        self.0.parts.leases().comm_loss_ends(bus, face)
    }

    /// Waits for the lease driver and its stops to finish (after shutdown).
    pub async fn wait(&self) {
        self.0.parts.leases().wait().await;
        // The alarm file gets what the stop raised, and is closed.
        let alarms = self.0.alarms.clone();
        let _ = tokio::task::spawn_blocking(move || alarms.close()).await;
    }
}

impl reload::RunningConfig for Control {
    fn running_config(&self) -> watch::Receiver<Option<Arc<Config>>> {
        self.0.reloads.follow()
    }
}

fn named(drive: &str, e: NoLease) -> NoLease {
    NoLease(format!("drive \"{drive}\" {}", e.0))
}

/// An open session: dropping it ends its leases, with their stop.
pub struct SessionGuard {
    id: SessionId,
    /// It has a communication-loss function.
    watched: bool,
    leases: Arc<Leases>,
}

impl SessionGuard {
    /// The session's id, for [`Caller::in_session`].
    pub fn id(&self) -> SessionId {
        self.id
    }

    /// A request came on the session: its communication-loss leases run
    /// for their time from now. Costs nothing without communication loss.
    pub fn active(&self) {
        if self.watched {
            self.leases.session_active(self.id);
        }
    }
}

impl Drop for SessionGuard {
    fn drop(&mut self) {
        self.leases.close_session(self.id);
    }
}
