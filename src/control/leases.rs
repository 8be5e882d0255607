//! The lease book's driver: owns the [`LeaseBook`] behind a lock, wakes it
//! when a deadline passes, carries out its effects (sends stops through
//! [`crate::control::stop_action`], publishes its news), reports the stops' results
//! back, and tells it when a bus or a drive answers again.
//!
//! One task sleeps until the book's next deadline; every change to the
//! book wakes it to look again, so a renewal costs no task. Each stop runs
//! in a task of its own, at emergency priority.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};

use tokio::sync::{Notify, broadcast, mpsc};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::audit;
use super::caller::{Face, SessionId};
use super::events::{ControlEvent, Events, WriteEnd, WriteEvent};
use super::journal::Journal;
use super::journal::format::{self as record, Action, HolderKind, ModeName, Record};
use super::lease_book::{
    CommLoss, Effect, Holder, LeaseBook, LeaseEvent, Note, StopOrder, StopReport, StopResult,
};
use super::time::Clock;
use super::written::describe;
use crate::bus::{BusError, BusEvent, Origin};
use crate::control::stop_action::{self, StopAction, StopOutcome};
use crate::drive::{DriveRequest, Mode};
use crate::plant::Plant;

/// Communication-loss leases of one bus that ended.
#[derive(Default)]
struct CommLossCount {
    timed_out: AtomicU64,
    closed: AtomicU64,
}

/// The lease book with its driver.
pub struct Leases {
    plant: Arc<Plant>,
    book: Mutex<LeaseBook>,
    wake: Notify,
    events: Arc<Events>,
    /// Open sessions, with the way to tell them of their leases' ends.
    sessions: Mutex<HashMap<SessionId, mpsc::UnboundedSender<Arc<ControlEvent>>>>,
    /// Communication-loss lease ends per bus and face: by silence, by a
    /// close.
    comm_loss: Mutex<HashMap<(usize, Face), Arc<CommLossCount>>>,
    shutdown: CancellationToken,
    tasks: TaskTracker,
    /// The safety journal: what a restart must know.
    journal: Mutex<Journal>,
    /// Where the time comes from.
    clock: Clock,
}

impl Leases {
    /// Starts the driver for the drives of `plant`; leases end with
    /// `action`, deadlines are kept by `clock`. It stops when `shutdown`
    /// fires (the daemon's own safe stop then covers every moving drive).
    pub fn start(
        plant: Arc<Plant>,
        action: StopAction,
        events: Arc<Events>,
        journal: Journal,
        shutdown: CancellationToken,
        clock: Clock,
    ) -> Arc<Leases> {
        let leases = Arc::new(Leases {
            plant: plant.clone(),
            book: Mutex::new(LeaseBook::new(action)),
            wake: Notify::new(),
            events,
            sessions: Mutex::new(HashMap::new()),
            comm_loss: Mutex::new(HashMap::new()),
            shutdown,
            tasks: TaskTracker::new(),
            journal: Mutex::new(journal),
            clock,
        });
        let driver = leases.clone();
        leases.tasks.spawn(async move { driver.run().await });
        let follower = leases.clone();
        leases
            .tasks
            .spawn(async move { follower.follow_buses().await });
        leases
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LeaseBook> {
        self.book.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs `f` on the book at the current instant and carries out the
    /// effects it returns.
    pub fn with<R>(
        self: &Arc<Self>,
        f: impl FnOnce(&mut LeaseBook, Instant) -> (R, Vec<Effect>),
    ) -> R {
        let (result, effects) = self.journaled(f);
        self.carry_out(effects);
        self.wake.notify_one();
        result
    }

    /// Runs `f` on the book and writes what it asks the journal to keep,
    /// synced, before returning: before anything `f` decided is sent. The
    /// journal is locked before the book is let go, so records reach the
    /// disk in the order of the book's transitions.
    fn journaled<R>(&self, f: impl FnOnce(&mut LeaseBook, Instant) -> R) -> R {
        let mut book = self.lock();
        let result = f(&mut book, self.clock.now());
        let notes = book.take_notes();
        if notes.is_empty() {
            return result;
        }
        let mut journal = self.journal.lock().unwrap_or_else(|p| p.into_inner());
        drop(book);
        let records: Vec<Record> = notes.iter().filter_map(|n| self.record(n)).collect();
        if let Err(why) = journal.append(&records) {
            // Never a reason to refuse a write, least of all a brake.
            for r in &records {
                tracing::warn!(record = ?r, "not kept across a restart: {why}");
            }
        }
        result
    }

    /// A note of the book as a journal record.
    fn record(&self, note: &Note) -> Option<Record> {
        let now = self.plant.now();
        let name = |drive: usize| now.drive_at(drive).map(|d| d.name.clone());
        Some(match note {
            Note::Lease {
                drive,
                owner,
                holder,
                comm_loss,
                deadline,
                length,
                action,
                mode,
            } => Record::Lease {
                drive: name(*drive)?,
                owner: owner.to_string(),
                holder: match (holder, comm_loss) {
                    (Holder::Request, _) => HolderKind::Http,
                    (Holder::Session(_), false) => HolderKind::Session,
                    (Holder::Session(_), true) => HolderKind::CommLoss,
                },
                deadline_ms: record::unix_ms(self.clock.wall(*deadline)),
                length_ms: u64::try_from(length.as_millis()).unwrap_or(u64::MAX),
                action: action_of(*action),
                mode: mode_of(*mode),
            },
            Note::LeaseEnded { drive } => Record::LeaseEnded {
                drive: name(*drive)?,
            },
            Note::Stop {
                drive,
                owner,
                action,
                mode,
                ends_lease,
            } => Record::Stop {
                drive: name(*drive)?,
                owner: owner.as_ref().map(|o| o.to_string()),
                action: action_of(*action),
                mode: mode_of(*mode),
                ends_lease: *ends_lease,
            },
            Note::StopEnded { drive } => Record::StopEnded {
                drive: name(*drive)?,
            },
            Note::Brake { drive, state } => Record::Brake {
                drive: name(*drive)?,
                state: *state,
            },
        })
    }

    /// Drive `old` is named `new` now (renamed by a reload, the same slot):
    /// what the journal owes it is owed under the new name, so a restart
    /// finds it.
    pub fn renamed(&self, old: &str, new: &str) {
        let mut journal = self.journal.lock().unwrap_or_else(|p| p.into_inner());
        if let Err(why) = journal.rename(old, new) {
            tracing::warn!(
                drive = new,
                "the renamed drive's lease is not kept across a restart: {why}"
            );
        }
    }

    /// The safety journal.
    pub fn journal<R>(&self, f: impl FnOnce(&Journal) -> R) -> R {
        f(&self.journal.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// Reads the book at the current instant.
    pub fn read<R>(&self, f: impl FnOnce(&LeaseBook, Instant) -> R) -> R {
        let book = self.lock();
        f(&book, self.clock.now())
    }

    /// Where the time comes from.
    pub fn clock(&self) -> &Clock {
        &self.clock
    }

    fn carry_out(self: &Arc<Self>, effects: Vec<Effect>) {
        for effect in effects {
            match effect {
                Effect::Stop(order) => {
                    if tokio::runtime::Handle::try_current().is_err() {
                        // Only outside the daemon (a session dropped after
                        // its runtime): nothing can be sent any more.
                        tracing::warn!(
                            drive = order.drive,
                            "a stop could not be started: no runtime"
                        );
                        continue;
                    }
                    let leases = self.clone();
                    self.tasks.spawn(async move { leases.stop(order).await });
                }
                Effect::Event(event) => self.announce(event),
                Effect::CommLoss {
                    drive,
                    closed,
                    face,
                } => {
                    self.events
                        .publish(Arc::new(ControlEvent::CommLoss { drive, closed }), None);
                    let bus = self.plant.now().drive_at(drive).map(|d| d.bus);
                    if let Some(bus) = bus {
                        let count = self
                            .comm_loss
                            .lock()
                            .unwrap_or_else(|p| p.into_inner())
                            .entry((bus, face))
                            .or_default()
                            .clone();
                        let counter = if closed {
                            &count.closed
                        } else {
                            &count.timed_out
                        };
                        counter.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    }

    /// Publishes lease news, and sends it directly to the session that
    /// held the lease, if it is still open (which then skips the copy).
    fn announce(&self, event: LeaseEvent) {
        if let Some(drive) = self.plant.now().drive_at(event.drive()) {
            audit::lease(&drive.name, &event);
        }
        let session = event.holder().session();
        let event = Arc::new(ControlEvent::Lease(event));
        let delivered_to = session.filter(|s| {
            self.sessions
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .get(s)
                .is_some_and(|tx| tx.send(event.clone()).is_ok())
        });
        self.events.publish(event, delivered_to);
    }

    /// Opens a session: leases may be tied to it, and news of their end
    /// comes out of the receiver. `closing` is how its end reads ("its
    /// WebSocket closed"); `comm_loss`, its communication-loss function.
    pub fn open_session(
        self: &Arc<Self>,
        closing: &'static str,
        comm_loss: Option<CommLoss>,
    ) -> (SessionId, mpsc::UnboundedReceiver<Arc<ControlEvent>>) {
        let id = SessionId::new_unique();
        let (tx, rx) = mpsc::unbounded_channel();
        self.sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id, tx);
        self.with(|book, _| {
            book.session_opened(id, closing, comm_loss);
            ((), Vec::new())
        });
        (id, rx)
    }

    /// A request came on session `id`: its communication-loss leases run
    /// on. Deadlines only move later, so the driver need not wake.
    pub fn session_active(&self, id: SessionId) {
        self.journaled(|book, now| book.session_active(id, now));
    }

    /// Communication-loss leases of bus `bus` held by sessions of `face`
    /// that ended since start-up: by silence, and by their session
    /// closing.
    pub fn comm_loss_ends(&self, bus: usize, face: Face) -> (u64, u64) {
        let counts = self.comm_loss.lock().unwrap_or_else(|p| p.into_inner());
        counts.get(&(bus, face)).map_or((0, 0), |c| {
            (
                c.timed_out.load(Ordering::Relaxed),
                c.closed.load(Ordering::Relaxed),
            )
        })
    }

    /// A session closed: its leases end now, with their stop.
    pub fn close_session(self: &Arc<Self>, id: SessionId) {
        self.sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&id);
        self.with(|book, now| ((), book.session_closed(id, now)));
    }

    /// Waits for the driver and the stops to finish (after shutdown).
    pub async fn wait(&self) {
        self.tasks.close();
        self.tasks.wait().await;
    }

    async fn run(self: Arc<Self>) {
        loop {
            let next = self.lock().next_wake();
            let sleep = async {
                match next {
                    Some(at) => self.clock.sleep_until(at).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                () = self.shutdown.cancelled() => {
                    self.lock().shutdown();
                    // The daemon's safe stop covers every drive from here:
                    // nothing before is owed to the next process.
                    let mut journal = self.journal.lock().unwrap_or_else(|p| p.into_inner());
                    if let Err(why) = journal.append(&[Record::Shutdown]) {
                        tracing::warn!("the clean stop is not journaled: {why}");
                    }
                    return;
                }
                () = self.wake.notified() => {}
                () = sleep => {}
            }
            let effects = self.journaled(|book, now| book.tick(now));
            self.carry_out(effects);
        }
    }

    /// Tells the book when the bus opens or one of its drives answers
    /// again: stops waiting to be tried again go at once.
    async fn watch_links(self: Arc<Self>, bus: usize, mut rx: broadcast::Receiver<BusEvent>) {
        let drives_of = |unit: Option<u8>| -> Vec<usize> {
            self.plant
                .now()
                .indexed_drives()
                .filter(|(_, d)| d.bus == bus && unit.is_none_or(|u| u == d.unit))
                .map(|(i, _)| i)
                .collect()
        };
        loop {
            let event = tokio::select! {
                () = self.shutdown.cancelled() => return,
                event = rx.recv() => event,
            };
            let drives = match event {
                Ok(BusEvent::BusUp { .. }) => drives_of(None),
                Ok(BusEvent::Online { unit, .. }) => drives_of(Some(unit)),
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => continue,
                Err(broadcast::error::RecvError::Closed) => return,
            };
            self.with(|book, now| ((), book.link_back(&drives, now)));
        }
    }

    /// At start-up, a drive that did not answer while what the last
    /// process promised about it is unknown (its journal unreadable, or
    /// read only in part): once it answers, if it moves, it gets `action`
    /// (`[safety] on_unknown_state`; none sends nothing), as the drives
    /// found moving at the start did, and `decided` is told its speed (for
    /// the alarm), unless a face's write to it was settled first (someone
    /// owns it again). A drive silent at the start (a cable, the port
    /// down) still turns at whatever it was told before.
    pub fn stop_at_first_answer(
        self: &Arc<Self>,
        drive: usize,
        action: StopAction,
        why: Arc<str>,
        decided: Box<dyn FnOnce(i16) + Send>,
    ) {
        let now = self.plant.now();
        let Some((handle, unit)) = now
            .drive_at(drive)
            .and_then(|d| Some((now.handle_of(d)?.clone(), d.unit)))
        else {
            return;
        };
        let mut bus = handle.subscribe();
        let mut writes = self.events.subscribe();
        let leases = self.clone();
        self.tasks.spawn(async move {
            let status = loop {
                tokio::select! {
                    () = leases.shutdown.cancelled() => return,
                    event = bus.recv() => match event {
                        Ok(BusEvent::Status { unit: u, status, .. }) if u == unit => break status,
                        Err(broadcast::error::RecvError::Closed) => return,
                        Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                    },
                    published = writes.recv() => match published {
                        Ok(p) => if let ControlEvent::Write(w) = p.event.as_ref()
                            && w.drive == Some(drive)
                            && w.face != Face::Internal
                            && matches!(w.result, WriteEnd::Confirmed | WriteEnd::CallerGone(_))
                        {
                            return;
                        },
                        Err(broadcast::error::RecvError::Closed) => return,
                        Err(broadcast::error::RecvError::Lagged(_)) => {}
                    },
                }
            };
            if !stop_action::is_moving(&status) {
                return;
            }
            if action != StopAction::None {
                leases.with(|book, now| {
                    book.restart_stop(drive, None, action, Mode::Speed, why, now);
                    ((), book.tick(now))
                });
            }
            decided(status.speed_rpm);
        });
    }

    /// Watches the events of every bus, and of each bus a reload adds or
    /// reopens, until shutdown.
    async fn follow_buses(self: Arc<Self>) {
        let mut plant = self.plant.follow();
        // The buses watched, by slot: a bus reopened is another running
        // bus (one changed in place is the same).
        let mut watched: Vec<(usize, crate::bus::BusHandle)> = Vec::new();
        loop {
            let now = plant.borrow_and_update().clone();
            watched.retain(|(i, b)| now.bus_at(*i).is_some_and(|n| n.handle.is(b)));
            for (index, bus) in now.indexed_buses() {
                if watched.iter().any(|(i, _)| *i == index) {
                    continue;
                }
                watched.push((index, bus.handle.clone()));
                let watcher = self.clone();
                let rx = bus.handle.subscribe_links();
                self.tasks
                    .spawn(async move { watcher.watch_links(index, rx).await });
            }
            tokio::select! {
                () = self.shutdown.cancelled() => return,
                changed = plant.changed() => if changed.is_err() { return },
            }
        }
    }

    /// Sends one stop and reports how it went.
    async fn stop(self: Arc<Self>, order: StopOrder) {
        let now = self.plant.now();
        let Some(drive) = now.drive_at(order.drive) else {
            return;
        };
        let Some(bus) = now.handle_of(drive) else {
            return;
        };
        // A brake applied again has no lease behind it: drivegate's own.
        let origin = order
            .owner
            .clone()
            .map_or(Origin::Internal, |owner| Origin::LeaseExpiry { owner });
        let outcome = stop_action::stop_drive(bus, drive.unit, order.action, false, origin).await;
        let who = match &order.owner {
            Some(owner) => format!("lease-expiry ({owner})"),
            None => "brake-guard".to_string(),
        };
        let who: Arc<str> = who.into();
        let bus_name: Arc<str> = bus.name().into();
        let report = report(&order, outcome, |what, result| {
            audit::write(
                Face::Internal.name(),
                &who,
                &bus_name,
                drive.unit,
                what,
                result,
            );
            let event = ControlEvent::Write(WriteEvent {
                at: SystemTime::now(),
                face: Face::Internal,
                who: who.clone(),
                bus: bus_name.clone(),
                unit: drive.unit,
                drive: Some(order.drive),
                what: what.to_string(),
                result: result.clone(),
            });
            self.events.publish(event.into(), None);
        });
        self.with(|book, now| ((), book.stop_tried(order.drive, order.id, report, now)));
    }
}

/// A stop's outcome: what was sent, and what the drive confirmed (or why
/// it failed); `audit` gets each write that may have reached the drive, and
/// the first failure.
fn report(
    order: &StopOrder,
    outcome: Result<StopOutcome, BusError>,
    audit: impl Fn(&str, &WriteEnd),
) -> StopReport {
    let releases =
        |r: &DriveRequest| matches!(r, DriveRequest::Speed { .. } | DriveRequest::Torque { .. });
    match outcome {
        Ok(stop) if stop.sent.is_some() => {
            let sent: Vec<String> = stop.requests().map(describe).collect();
            for what in &sent {
                audit(what, &WriteEnd::Confirmed);
            }
            StopReport {
                released_brake: stop.requests().any(releases),
                result: StopResult::Confirmed,
                sent: Some(sent.join(", ")),
            }
        }
        Ok(StopOutcome { mode, .. }) if order.action != StopAction::None => StopReport {
            sent: None,
            result: StopResult::NothingToSend {
                action: order.action,
                mode,
            },
            released_brake: false,
        },
        Ok(_) => StopReport {
            sent: None,
            result: StopResult::ActionNone,
            released_brake: false,
        },
        Err(e) => {
            if order.attempt == 1 || !e.not_sent() {
                audit(order.action.name(), &WriteEnd::bus_error(e.clone()));
            }
            StopReport {
                sent: Some(order.action.name().to_string()),
                released_brake: order.action == StopAction::ZeroSpeed && !e.not_sent(),
                result: StopResult::Failed(e),
            }
        }
    }
}

fn action_of(action: StopAction) -> Action {
    match action {
        StopAction::ZeroSpeed => Action::ZeroSpeed,
        StopAction::Brake => Action::Brake,
        StopAction::None => Action::None,
    }
}

/// The stop action a journal record names.
pub(crate) fn stop_action(action: Action) -> StopAction {
    match action {
        Action::ZeroSpeed => StopAction::ZeroSpeed,
        Action::Brake => StopAction::Brake,
        Action::None => StopAction::None,
    }
}

fn mode_of(mode: Mode) -> ModeName {
    match mode {
        Mode::OpenLoop => ModeName::OpenLoop,
        Mode::Speed => ModeName::Speed,
        Mode::Position => ModeName::Position,
        Mode::Torque => ModeName::Torque,
    }
}

/// The mode a journal record names.
pub(crate) fn mode(name: ModeName) -> Mode {
    match name {
        ModeName::OpenLoop => Mode::OpenLoop,
        ModeName::Speed => Mode::Speed,
        ModeName::Position => Mode::Position,
        ModeName::Torque => Mode::Torque,
    }
}
