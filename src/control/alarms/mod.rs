//! Alarms: what needs an operator's attention, kept until acknowledged
//! and across restarts. The core raises and clears them from what it sees
//! (every bus's events: faults, stalls, drives offline or never heard since
//! their bus opened, ports down; its own
//! events: communication-loss stops, stops not confirmed, writes refused
//! by a safety rule), keeps them in [`book`] (pure, time passed in) and in
//! a file in `[safety] state_dir` ([`file`]), and publishes each change
//! on its events ([`ControlEvent::Alarm`]) for the stream, the console and
//! the metrics. An acknowledgement is the core's to authorise and audit,
//! like a write ([`crate::control::Control::acknowledge_alarm`]).
//!
//! The file is written by a thread of its own, so a slow disk never holds
//! up the bus events; an acknowledgement is answered only once it is on
//! the disk.

pub mod book;
pub mod file;
mod follower;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex, mpsc};
use std::time::SystemTime;

use tokio::sync::{broadcast, oneshot};
use tokio_util::sync::CancellationToken;

pub use book::{Ack, AckError, Alarm, AlarmBook, AlarmKey, AlarmKind, Change, Raise};
use file::{AlarmFile, AlarmRecord, FileState};
use follower::Follower;

use super::events::{ControlEvent, Events, Published, WriteEnd, WriteEvent};
use super::journal::format::unix_ms;
use super::lease_book::LeaseEvent;
pub use super::news::AlarmNews;
use super::outcome::{Failure, Rule};
use crate::bus::BusEvent;
use crate::bus::cache::Link;
use crate::bus::freshness::Freshness;
use crate::bus::handle::PortState;
use crate::drive::help;
use crate::plant::Plant;

/// Alarms kept when `[safety] alarms_kept` does not say.
pub const DEFAULT_KEPT: usize = 500;

/// What is wrong in the alarm list, for the metrics.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Summary {
    /// Active alarms by kind (every kind present, 0 when none).
    pub active: BTreeMap<AlarmKind, u64>,
    /// Alarms not acknowledged yet, active or not.
    pub unacknowledged: u64,
    /// Alarms held.
    pub held: u64,
}

struct Batch {
    records: Vec<AlarmRecord>,
    done: Option<oneshot::Sender<()>>,
}

/// The alarm list of the daemon.
pub struct Alarms {
    book: Mutex<AlarmBook>,
    writer: Mutex<Option<mpsc::Sender<Batch>>>,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
    file: Arc<Mutex<FileState>>,
    events: Arc<Events>,
}

fn now_ms() -> u64 {
    unix_ms(SystemTime::now())
}

impl Alarms {
    /// Opens the alarm list kept in `dir` (`None`: in memory only), at
    /// most `keep` alarms, publishing its news on `events`.
    pub fn open(dir: Option<&Path>, keep: usize, events: Arc<Events>) -> Arc<Alarms> {
        let opened = AlarmFile::open(dir, keep);
        for news in &opened.news {
            if dir.is_some() {
                tracing::warn!("{news}");
            } else {
                tracing::info!("{news}");
            }
        }
        let (mut book, dropped) = AlarmBook::restore(keep, opened.alarms);
        book.number_after(opened.last_id);
        let file_state = Arc::new(Mutex::new(opened.file.state().clone()));
        let (tx, rx) = mpsc::channel::<Batch>();
        let thread = {
            let mut file = opened.file;
            let state = file_state.clone();
            std::thread::Builder::new()
                .name("drivegate-alarms".into())
                .spawn(move || {
                    while let Ok(batch) = rx.recv() {
                        let mut records = batch.records;
                        let mut done: Vec<_> = batch.done.into_iter().collect();
                        // What queued meanwhile goes with it, in one sync.
                        while let Ok(more) = rx.try_recv() {
                            records.extend(more.records);
                            done.extend(more.done);
                        }
                        file.append(&records);
                        *state.lock().unwrap_or_else(|p| p.into_inner()) = file.state().clone();
                        for d in done {
                            let _ = d.send(());
                        }
                    }
                })
        };
        let thread = match thread {
            Ok(t) => Some(t),
            Err(e) => {
                tracing::warn!(
                    "the alarm file's writer did not start ({e}): alarms are kept in memory only"
                );
                None
            }
        };
        let alarms = Arc::new(Alarms {
            book: Mutex::new(book),
            writer: Mutex::new(thread.as_ref().map(|_| tx)),
            thread: Mutex::new(thread),
            file: file_state,
            events,
        });
        alarms.persist(&dropped, None);
        alarms
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, AlarmBook> {
        self.book.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands `changes` to the file's writer, in the order they were made
    /// (called with the book locked).
    fn persist(&self, changes: &[Change], done: Option<oneshot::Sender<()>>) {
        let records: Vec<AlarmRecord> = changes
            .iter()
            .map(|c| match c {
                Change::Raised(a) | Change::Cleared(a) | Change::Acknowledged(a) => {
                    AlarmRecord::Alarm(a.clone())
                }
                Change::Dropped(id) => AlarmRecord::Dropped { id: *id },
            })
            .collect();
        if records.is_empty() && done.is_none() {
            return;
        }
        let writer = self.writer.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(tx) = writer.as_ref() {
            let _ = tx.send(Batch { records, done });
        }
    }

    fn publish(&self, changes: Vec<Change>) {
        for change in changes {
            let news = match change {
                Change::Raised(a) => {
                    tracing::warn!(target: "drivegate::alarms", id = a.id, kind = a.kind.name(), drive = a.drive.as_deref().unwrap_or(""), count = a.count, "alarm: {}", a.text);
                    AlarmNews::Raised(a)
                }
                Change::Cleared(a) => {
                    tracing::info!(target: "drivegate::alarms", id = a.id, kind = a.kind.name(), drive = a.drive.as_deref().unwrap_or(""), "alarm cleared: {}", a.text);
                    AlarmNews::Cleared(a)
                }
                Change::Acknowledged(a) => AlarmNews::Acknowledged(a),
                Change::Dropped(_) => continue,
            };
            self.events
                .publish(Arc::new(ControlEvent::Alarm(news)), None);
        }
    }

    /// Runs `f` on the book at the current time, keeps and publishes what
    /// it changed.
    fn apply(&self, f: impl FnOnce(&mut AlarmBook, u64) -> Vec<Change>) {
        let changes = {
            let mut book = self.lock();
            let changes = f(&mut book, now_ms());
            self.persist(&changes, None);
            changes
        };
        self.publish(changes);
    }

    /// Acknowledges alarm `id` for `by`; answers once the file has it.
    pub(crate) async fn acknowledge(&self, id: u64, by: &str) -> Result<Alarm, AckError> {
        let (done_tx, done_rx) = oneshot::channel();
        let (alarm, change) = {
            let mut book = self.lock();
            let (alarm, change) = book.acknowledge(id, by, now_ms())?;
            let changes: Vec<Change> = change.into_iter().collect();
            self.persist(&changes, Some(done_tx));
            (alarm, changes)
        };
        // A writer that is gone (the daemon stops) answers at once.
        let _ = tokio::time::timeout(std::time::Duration::from_secs(5), done_rx).await;
        self.publish(change);
        Ok(alarm)
    }

    /// Drive `old` of `bus` is named `new` now (the same motor, renamed by
    /// a reload): its alarms follow it, in the book and in the file.
    pub(crate) fn rename(&self, bus: &str, old: &str, new: &str) {
        let mut book = self.lock();
        let records: Vec<AlarmRecord> = book
            .rename(bus, old, new)
            .into_iter()
            .map(AlarmRecord::Alarm)
            .collect();
        if records.is_empty() {
            return;
        }
        let writer = self.writer.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(tx) = writer.as_ref() {
            let _ = tx.send(Batch {
                records,
                done: None,
            });
        }
    }

    /// Every alarm, oldest first.
    pub fn list(&self) -> Vec<Alarm> {
        self.lock().alarms().cloned().collect()
    }

    /// The most it keeps (`[safety] alarms_kept`).
    pub fn kept_at_most(&self) -> usize {
        self.lock().keep()
    }

    /// Alarm `id`.
    pub fn get(&self, id: u64) -> Option<Alarm> {
        self.lock().get(id).cloned()
    }

    /// Active alarms by kind and the unacknowledged count.
    pub fn summary(&self) -> Summary {
        let book = self.lock();
        let mut s = Summary {
            active: AlarmKind::ALL.iter().map(|k| (*k, 0)).collect(),
            ..Summary::default()
        };
        for a in book.alarms() {
            s.held += 1;
            if a.active() {
                *s.active.entry(a.kind).or_default() += 1;
            }
            if a.ack.is_none() {
                s.unacknowledged += 1;
            }
        }
        s
    }

    /// The file's size and health.
    pub fn file_state(&self) -> FileState {
        self.file.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Stops the file's writer once it wrote what it was given, and waits
    /// for it (the daemon stops).
    pub(crate) fn close(&self) {
        drop(self.writer.lock().unwrap_or_else(|p| p.into_inner()).take());
        let thread = self.thread.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(t) = thread {
            let _ = t.join();
        }
    }

    /// Clears, at start-up, the active conditions of the last process that
    /// no event will clear: those of drives and buses no longer
    /// configured, and stops not confirmed (the restart's replay of the
    /// safety journal owns those stops now, and says what it did).
    pub(crate) fn reconcile(&self, plant: &Plant) {
        let directory = plant.now();
        self.apply(|book, now| {
            book.clear_where(
                |a| {
                    let bus = plant.bus(&a.bus);
                    let drive_gone = a
                        .drive
                        .as_ref()
                        .is_some_and(|name| !directory.drives().any(|d| &d.name == name));
                    // A certificate's alarm is the certificate check's to
                    // clear (it names no bus).
                    let gone = bus.is_none() && a.kind != AlarmKind::CertificateExpiring;
                    gone || drive_gone || a.kind == AlarmKind::StopFailed
                },
                now,
            )
        });
    }

    /// Raises an alarm for each certificate in `expiring` (once while it
    /// lasts) and clears those of certificates that no longer expire soon
    /// (renewed, replaced, removed).
    pub(crate) fn certificates_expiring(&self, expiring: Vec<Raise>) {
        let keep: std::collections::HashSet<AlarmKey> =
            expiring.iter().map(|r| r.key.clone()).collect();
        self.apply(|book, now| {
            let mut changes = book.clear_where(
                |a| a.kind == AlarmKind::CertificateExpiring && !keep.contains(&a.key()),
                now,
            );
            for raise in expiring {
                changes.extend(book.raise(raise, now));
            }
            changes
        });
    }

    /// Follows every bus of `plant` and the core's `events` until
    /// `shutdown` fires.
    pub(crate) fn watch(
        self: &Arc<Self>,
        plant: &Arc<Plant>,
        events: broadcast::Receiver<Published>,
        shutdown: &CancellationToken,
    ) {
        if tokio::runtime::Handle::try_current().is_err() {
            return;
        }
        let following = (self.clone(), plant.clone());
        plant.for_each_bus(shutdown, move |index, bus, shutdown| {
            let (alarms, plant) = (following.0.clone(), following.1.clone());
            // What happened before this subscription (a port that failed
            // to open at start) is read from the bus's state, after it.
            let (raise, on) = (alarms.clone(), plant.clone());
            let follower = Follower(move |e: &BusEvent| raise.bus_event(&on, index, e));
            bus.handle.follow(Arc::new(follower), shutdown);
            alarms.seed(&plant, index);
        });
        let (alarms, plant, shutdown) = (self.clone(), plant.clone(), shutdown.clone());
        let mut rx = events;
        tokio::spawn(async move {
            loop {
                let event = tokio::select! {
                    () = shutdown.cancelled() => return,
                    e = rx.recv() => e,
                };
                match event {
                    Ok(p) => alarms.control_event(&plant, &p.event),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!("the alarm list fell {n} control events behind");
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        });
    }

    /// Raises or clears what bus `index`'s state says now: its port, and
    /// its drives' links (the same as the events that led there would).
    fn seed(&self, plant: &Plant, index: usize) {
        let Some(bus) = plant.now().bus_at(index).cloned() else {
            return;
        };
        let name: Arc<str> = bus.handle.name_arc();
        let port = match bus.handle.port_state() {
            PortState::Up { .. } => Some(BusEvent::BusUp { bus: name.clone() }),
            PortState::Down { reason, .. } => Some(BusEvent::BusDown {
                bus: name.clone(),
                reason,
            }),
            PortState::Opening => None,
        };
        if let Some(event) = port {
            self.bus_event(plant, index, &event);
        }
        for d in bus.handle.drives() {
            let event = match d.link {
                Link::Online => BusEvent::Online {
                    bus: name.clone(),
                    unit: d.unit,
                },
                Link::Offline => BusEvent::Offline {
                    bus: name.clone(),
                    unit: d.unit,
                    reason: "it did not answer its polls".into(),
                },
                Link::Unknown => continue,
            };
            self.bus_event(plant, index, &event);
        }
    }

    /// Raises or clears what a bus event says.
    pub(crate) fn bus_event(&self, plant: &Plant, bus_index: usize, event: &BusEvent) {
        let now = plant.now();
        let Some(bus) = now.bus_at(bus_index) else {
            return;
        };
        let bus_name = bus.handle.name().to_string();
        let drive_of = |unit: u8| {
            now.drives()
                .find(|d| d.bus == bus_index && d.unit == unit)
                .map(|d| d.name.clone())
        };
        let bus_key = AlarmKey {
            kind: AlarmKind::BusDown,
            bus: bus_name.clone(),
            drive: None,
            code: 0,
        };
        match event {
            BusEvent::Status { unit, status, .. } => {
                // A scan reads units that are not configured: not alarms.
                let Some(drive) = drive_of(*unit) else { return };
                self.status(&bus_name, (&drive, *unit), status);
            }
            BusEvent::Online { unit, .. } => {
                let Some(drive) = drive_of(*unit) else { return };
                self.apply(|book, now| answered(book, &bus_name, &drive, now));
            }
            BusEvent::Offline { unit, reason, .. } => {
                let Some(drive) = drive_of(*unit) else { return };
                self.silent(bus, (&drive, *unit), reason);
            }
            BusEvent::BusUp { .. } => {
                self.apply(|book, now| book.clear(&bus_key, now));
            }
            BusEvent::BusDown { reason, .. } => {
                self.apply(|book, now| {
                    book.raise(
                        Raise {
                            key: bus_key,
                            text: format!(
                                "bus {bus_name}: its port failed ({reason}); none of its drives is read or written until it reopens"
                            ),
                            help: BUS_DOWN_HELP.to_string(),
                        },
                        now,
                    )
                });
            }
        }
    }

    /// A status of `drive` (`unit`) on `bus`: it answers (its `offline` or
    /// `never-answered` alarm clears), and its fault and stall.
    fn status(&self, bus: &str, (drive, unit): (&str, u8), status: &crate::drive::Status) {
        let fault = status.fault();
        // The common case, a healthy drive with nothing open: no
        // change to make, nothing to allocate.
        if fault.code() == 0 && !status.stalled() && !self.lock().has_open_for(bus, drive) {
            return;
        }
        let key = |kind, code| drive_key(kind, bus, drive, code);
        self.apply(|book, now| {
            let mut changes = answered(book, bus, drive, now);
            let code = fault.code();
            changes.extend(book.clear_other_codes(
                AlarmKind::Fault,
                bus,
                Some(drive),
                (code != 0).then_some(code),
                now,
            ));
            if code != 0 {
                changes.extend(book.raise(
                    Raise {
                        key: key(AlarmKind::Fault, code),
                        text: format!(
                            "drive {drive} (bus {bus}, unit {unit}) reports a fault: {} (code {code})",
                            fault_words(fault)
                        ),
                        help: help::fault(fault).to_string(),
                    },
                    now,
                ));
            }
            let stall = key(AlarmKind::Stall, 0);
            if status.stalled() {
                changes.extend(book.raise(
                    Raise {
                        key: stall,
                        text: format!(
                            "the motor of drive {drive} (bus {bus}, unit {unit}) stalled and is stopped until a fault reset"
                        ),
                        help: help::STALL.to_string(),
                    },
                    now,
                ));
            } else {
                changes.extend(book.clear(&stall, now));
            }
            changes
        });
    }

    /// `drive` (`unit`) of `bus` went silent (`reason`, its last poll): an
    /// `offline` alarm if it had answered since its bus opened, a
    /// `never-answered` one (naming the baud rate and the unit address)
    /// if it never did. A drive never heard on a bus whose port is down
    /// gets neither: the bus's own `bus-down` alarm says why.
    fn silent(&self, bus: &crate::plant::Bus, (drive, unit): (&str, u8), reason: &str) {
        let bus_name = bus.handle.name();
        let verdict = bus.handle.freshness(unit);
        let never_heard = bus
            .handle
            .drive(unit)
            .is_some_and(|d| d.seen_instant.is_none());
        let raise = match verdict.as_ref().map(|v| v.freshness) {
            Some(Freshness::Never) => {
                let why = verdict
                    .as_ref()
                    .and_then(|v| v.words(bus_name, unit, bus.config.baud))
                    .unwrap_or_else(|| reason.to_string());
                Raise {
                    key: drive_key(AlarmKind::NeverAnswered, bus_name, drive, 0),
                    text: format!(
                        "drive {drive} (bus {bus_name}, unit {unit}) has never answered: {why}"
                    ),
                    help: help::NEVER_ANSWERED.to_string(),
                }
            }
            Some(Freshness::BusDown) if never_heard => return,
            _ => Raise {
                key: drive_key(AlarmKind::Offline, bus_name, drive, 0),
                text: format!(
                    "drive {drive} (bus {bus_name}, unit {unit}) stopped answering: {reason}"
                ),
                help: help::OFFLINE.to_string(),
            },
        };
        self.apply(|book, now| book.raise(raise, now));
    }

    /// Raises or clears what an event of the core says.
    pub(crate) fn control_event(&self, plant: &Plant, event: &ControlEvent) {
        let now = plant.now();
        let drive = |i: usize| {
            let d = now.drive_at(i)?;
            let bus = now.bus_at(d.bus)?.handle.name().to_string();
            Some((d.name.clone(), bus, d.unit))
        };
        match event {
            ControlEvent::Lease(LeaseEvent::Expired {
                drive: i,
                owner,
                action,
                ok: false,
                result,
                ..
            }) => {
                let Some((name, bus, unit)) = drive(*i) else {
                    return;
                };
                self.apply(|book, now| {
                    book.raise(
                        Raise {
                            key: AlarmKey {
                                kind: AlarmKind::StopFailed,
                                bus: bus.clone(),
                                drive: Some(name.clone()),
                                code: 0,
                            },
                            text: format!(
                                "the {} stop of drive {name} (bus {bus}, unit {unit}) at the end of {owner}'s lease was not confirmed: {result}; drivegate keeps trying",
                                action.name()
                            ),
                            help: STOP_FAILED_HELP.to_string(),
                        },
                        now,
                    )
                });
            }
            ControlEvent::Lease(LeaseEvent::StopSettled { drive: i, .. }) => {
                let Some((name, bus, _)) = drive(*i) else {
                    return;
                };
                let k = AlarmKey {
                    kind: AlarmKind::StopFailed,
                    bus,
                    drive: Some(name),
                    code: 0,
                };
                self.apply(|book, now| book.clear(&k, now));
            }
            ControlEvent::Lease(_)
            | ControlEvent::Alarm(_)
            | ControlEvent::Settings(_)
            | ControlEvent::Freshness(_)
            | ControlEvent::Drift(_) => {}
            ControlEvent::CommLoss { drive: i, closed } => {
                let Some((name, bus, unit)) = drive(*i) else {
                    return;
                };
                let why = if *closed {
                    "its connection closed"
                } else {
                    "no request came within its communication-loss time"
                };
                self.apply(|book, now| {
                    book.raise(
                        Raise {
                            key: AlarmKey {
                                kind: AlarmKind::CommLoss,
                                bus: bus.clone(),
                                drive: Some(name.clone()),
                                code: 0,
                            },
                            text: format!(
                                "drive {name} (bus {bus}, unit {unit}) was stopped by its Modbus TCP client's communication-loss function: {why}"
                            ),
                            help: COMM_LOSS_HELP.to_string(),
                        },
                        now,
                    )
                });
            }
            ControlEvent::Write(w) => {
                self.refused_write(plant, w);
            }
        }
    }

    /// Raises the alarm of a drive found moving at start while the safety
    /// journal could not say who owned it: `text` names the journal's state
    /// and what was done.
    pub(crate) fn unknown_state(&self, plant: &Plant, drive: &str, text: String) {
        let now = plant.now();
        let Some(bus) = now
            .drives()
            .find(|d| d.name == drive)
            .and_then(|d| now.handle_of(d))
            .map(|h| h.name().to_string())
        else {
            return;
        };
        self.apply(|book, now| {
            book.raise(
                Raise {
                    key: drive_key(AlarmKind::UnknownState, &bus, drive, 0),
                    text,
                    help: UNKNOWN_STATE_HELP.to_string(),
                },
                now,
            )
        });
    }

    /// Raises an alarm for a write refused by a safety rule (a motor that
    /// turns, a shared bus address).
    fn refused_write(&self, plant: &Plant, w: &WriteEvent) {
        let now = plant.now();
        let WriteEnd::Failed(Failure::Refused(refusal)) = &w.result else {
            return;
        };
        let help = match refusal.rule {
            Rule::Moving { .. } => MOVING_HELP,
            Rule::SharedBusAddress => SHARED_BUS_HELP,
            _ => return,
        };
        let name = w
            .drive
            .and_then(|i| now.drive_at(i))
            .map(|d| d.name.clone());
        let target = match &name {
            Some(n) => format!("drive {n} (bus {}, unit {})", w.bus, w.unit),
            None => format!("bus {} unit {}", w.bus, w.unit),
        };
        let text = format!(
            "{target}: {} from {} {} was refused: {}",
            w.what,
            w.who,
            w.face.words(),
            refusal.detail
        );
        let key = AlarmKey {
            kind: AlarmKind::RefusedWrite,
            bus: w.bus.to_string(),
            drive: name,
            code: 0,
        };
        self.apply(|book, now| {
            book.raise(
                Raise {
                    key,
                    text,
                    help: help.to_string(),
                },
                now,
            )
        });
    }
}

/// The key of `drive`'s alarm of `kind` on `bus`.
fn drive_key(kind: AlarmKind, bus: &str, drive: &str, code: u16) -> AlarmKey {
    AlarmKey {
        kind,
        bus: bus.to_string(),
        drive: Some(drive.to_string()),
        code,
    }
}

/// `drive` answered: its `offline` and `never-answered` conditions end.
fn answered(book: &mut AlarmBook, bus: &str, drive: &str, now: u64) -> Vec<Change> {
    let mut changes = book.clear(&drive_key(AlarmKind::Offline, bus, drive, 0), now);
    changes.extend(book.clear(&drive_key(AlarmKind::NeverAnswered, bus, drive, 0), now));
    changes
}

/// A fault in words, for an alarm's text.
fn fault_words(fault: crate::drive::Fault) -> &'static str {
    use crate::drive::Fault;
    match fault {
        Fault::None => "no fault",
        Fault::CurrentSense => "current feedback signal fault",
        Fault::Encoder => "encoder feedback signal fault",
        Fault::PowerStage => "power stage fault",
        Fault::OverTemperature => "drive over-temperature",
        Fault::UnderVoltage => "supply under-voltage",
        Fault::OverVoltage => "supply over-voltage",
        Fault::Reserved => "reserved fault code",
    }
}

const BUS_DOWN_HELP: &str = "The bus's serial adapter (or serial device server) failed or \
     closed: no drive on it is read or written, and no stop can reach them. Check the USB cable \
     and the adapter (the kernel log shows an adapter unplugged), that no other program holds \
     the port, its permissions (the dialout group), or, for a tcp:// port, the device server's \
     power and network. drivegate reopens the port with backoff and clears this alarm when it \
     opens.";

const COMM_LOSS_HELP: &str = "A Modbus TCP client whose network has a communication-loss time \
     ([[modbus_tcp.clients]] comm_loss_ms) held this drive and went silent or closed its \
     connection, so drivegate stopped the drive with the network's comm_loss_action. Check the \
     PLC or SCADA client: it stopped, lost its network, or sends requests less often than \
     comm_loss_ms. The drive stays stopped until a client sends a setpoint again.";

const STOP_FAILED_HELP: &str = "drivegate tried to stop the drive at the end of a lease \
     ([safety] on_lease_expiry, or a network's comm_loss_action) and the drive did not confirm \
     the stop: the motor may still be turning. Check the machine and use its own emergency stop \
     if it moves: the brake sent over the bus is not a safety-rated stop. drivegate keeps \
     sending the stop until the drive confirms it (this alarm then clears); see the drive's \
     offline alarm for why it does not answer.";

const MOVING_HELP: &str = "A write that the manual allows only with the motor standing still \
     was refused because the motor turned: a save to flash (save flag of manual 1.8 to 1.11: \
     'make sure the motor is at standstill when saving'), a factory reset (CONFIG 0x6, 1.3), a \
     new address (1.2) or a calibration (CONFIG 0x2 and 0x3, 1.3). Stop the motor, check that it \
     reads 0 rpm, and send it again; a client that sends it while the line runs needs its \
     sequence fixed.";

const UNKNOWN_STATE_HELP: &str = "At start, drivegate found this drive moving and its safety \
     journal ([safety] state_dir/safety.journal) could not say who had set it moving: the file \
     could not be read, was empty, held only its header, or was missing although an earlier run \
     kept one. A lease it held may have been lost, so drivegate applied [safety] \
     on_unknown_state to the drive (or left it moving, with none). Check the machine, then the \
     state directory's disk: a power cut on a disk that does not keep what it is told to keep \
     (a write cache without power-loss protection), a full or failing disk, or someone emptying \
     or deleting the file. The owner of the motor sends its command again.";

const SHARED_BUS_HELP: &str = "An address broadcast (manual 1.2: sent to address 0, every drive \
     that hears it takes the new address, and only one drive may be on the bus) was refused \
     because the caller did not confirm that only one drive is connected. Disconnect the other \
     drives from the bus, then send it again with that confirmation.";

#[cfg(test)]
mod tests;
