//! The lease book: every motor-safety lease of the plant and the stops of
//! those that ended, as a pure state machine. Time is passed in; what has
//! to happen on the bus or on the network comes back as [`Effect`]s, which
//! the driver in [`super::leases`] carries out and reports back. Nothing
//! here sleeps, locks or sends, so every transition is unit-tested.
//!
//! The rules it keeps:
//! - one lease per drive: a leased setpoint takes the drive's lease over
//!   (the old one ends, replaced, without a stop);
//! - a lease is put in place before its setpoint is sent, with a deadline
//!   that allows for the bus queue, and gets its own deadline once the
//!   write is settled; a setpoint that surely did not land takes its lease
//!   back (unless it replaced another, which then still covers the motor);
//! - a session may have a communication-loss time (a Modbus TCP client's
//!   network): its setpoints and mode commands then take a lease of that
//!   length with the network's action, which any request of the session
//!   renews; silence for that long, or the session closing, ends it;
//! - a lease not renewed in time, or whose session (WebSocket, Modbus TCP
//!   connection) closed, ends with the stop action, retried with backoff (cut short when the bus or
//!   the drive comes back) until the drive confirms it, something newer
//!   takes over the drive, or the daemon stops;
//! - a stop due while a newer lease is on the drive waits for it: if that
//!   lease's setpoint lands, it takes over;
//! - a brake or a deactivation confirmed from any face ends the drive's
//!   lease without a stop, and ends a stop still being tried there: a zero
//!   speed after a brake would release it;
//! - while a brake or deactivation is on its way, stops of that drive wait
//!   for its result;
//! - a brake must hold: a write that can release it (a setpoint, a mode
//!   command, a zero-speed stop) sent before a brake but landing after it
//!   has the brake applied again, and so has a brake the drive did not
//!   confirm, until the drive confirms it;
//! - a leased setpoint that lands after its lease ended has the stop sent
//!   again.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::caller::SessionId;
use super::outcome::Applied;
use crate::drive::Mode;
use crate::safety::StopAction;

/// First wait before a failed stop is tried again; it doubles up to
/// [`RETRY_MAX`], and the bus or the drive coming back cuts it short.
pub const RETRY_FIRST: Duration = Duration::from_millis(250);
/// Longest wait between two tries of a failed stop.
pub const RETRY_MAX: Duration = Duration::from_secs(5);

/// How the end of a session reads when nothing more precise is known.
const SESSION_CLOSED: &str = "its session closed";

/// A lease's identity, unique for the daemon's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct LeaseId(pub u64);

/// A stop's identity, unique for the daemon's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct StopId(pub u64);

/// What holds a lease: a single request (it ends only by time or by a
/// write), or a session whose closing ends it too.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Holder {
    /// A request on its own (a REST call).
    Request,
    /// A session (a WebSocket, a Modbus TCP connection).
    Session(SessionId),
}

impl Holder {
    /// The session, if the lease has one.
    pub fn session(self) -> Option<SessionId> {
        match self {
            Holder::Request => None,
            Holder::Session(s) => Some(s),
        }
    }
}

/// A session's communication-loss function: a lease for each of its
/// setpoints and mode commands, renewed by any request of the session, and
/// ended by `after` of silence or by the session closing, with `action`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommLoss {
    /// Silence that ends its leases.
    pub after: Duration,
    /// What their end sends (`None`: nothing; the end is still shown).
    pub action: StopAction,
}

/// The lease a write takes: its length, its stop, and whether its
/// session's silence ends it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Terms {
    /// Its length.
    pub length: Duration,
    /// Its stop, if not the book's.
    pub action: Option<StopAction>,
    /// A communication-loss lease: renewed by any request of its session.
    pub comm_loss: bool,
}

/// What a lease is asked for with.
#[derive(Debug, Clone)]
pub struct LeaseAsk {
    /// Who takes it (token name, client address).
    pub owner: Arc<str>,
    /// What holds it.
    pub holder: Holder,
    /// The mode its setpoint drives the motor in: the stop's choice when
    /// the drive's mode cannot be read.
    pub mode: Mode,
    /// Its length: each renewal pushes the deadline this far.
    pub length: Duration,
    /// How long its setpoint may take to be settled (queue and retries).
    pub allowance: Duration,
    /// Its stop, if not the book's (a face's own setting, such as a
    /// communication-loss action).
    pub action: Option<StopAction>,
    /// A communication-loss lease: any request of its session renews it,
    /// and its end by time reads as communication lost.
    pub comm_loss: bool,
}

/// A lease as faces show it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LeaseView {
    /// Its id.
    pub id: LeaseId,
    /// Who holds it.
    pub owner: Arc<str>,
    /// What holds it.
    pub holder: Holder,
    /// Its length.
    pub length: Duration,
    /// Time left before the stop.
    pub expires_in: Duration,
    /// What its end sends.
    pub action: StopAction,
    /// A communication-loss lease (renewed by any request of its session).
    pub comm_loss: bool,
}

/// What [`LeaseBook::grant`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grant {
    /// The new lease.
    pub id: LeaseId,
    /// True when it replaced a lease on the drive.
    pub replaced: bool,
}

/// How a write bears on leases and on the brake.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteKind {
    /// A speed, position or torque setpoint, with the lease granted for it.
    Setpoint {
        /// Its lease, if it came with one.
        lease: Option<Grant>,
    },
    /// The emergency brake.
    Brake,
    /// A deactivation.
    Deactivate,
    /// Anything else that releases a brake (a mode command), with the
    /// lease granted for it (a communication-loss lease).
    ReleasesBrake {
        /// Its lease, if it came with one.
        lease: Option<Grant>,
    },
}

/// A write in progress, as the book tracks it: taken before the write is
/// sent, given back with its result.
#[derive(Debug, Clone)]
pub struct Ticket {
    drive: usize,
    kind: WriteKind,
    /// Brakes sent to the drive before this write (for a brake: its own
    /// number).
    seen: u64,
    /// Who sent it, in words ("the brake from scada (Modbus TCP)").
    by: Arc<str>,
}

impl Ticket {
    /// The write's kind.
    pub fn kind(&self) -> WriteKind {
        self.kind
    }
}

/// Why a lease ended with its stop.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StopReason {
    /// Nobody renewed it in time.
    NotRenewed,
    /// Its session sent nothing for this long (communication loss).
    CommLost(Duration),
    /// Its session closed (the text says how: "its WebSocket closed").
    SessionClosed(&'static str),
    /// A brake was sent but the drive did not confirm it: the brake is
    /// applied until it does.
    BrakeUnconfirmed(Arc<str>),
    /// A write that releases the brake landed after a brake.
    BrakeReleased(Arc<str>),
}

impl StopReason {
    /// In words, after "lease ended because".
    pub fn text(&self) -> String {
        match self {
            StopReason::NotRenewed => "it was not renewed in time".to_string(),
            StopReason::CommLost(after) => format!(
                "communication was lost: no request came on its connection for {} ms",
                after.as_millis()
            ),
            StopReason::SessionClosed(how) => (*how).to_string(),
            StopReason::BrakeUnconfirmed(by) => {
                format!("{by} was sent but not confirmed by the drive")
            }
            StopReason::BrakeReleased(by) => {
                format!("{by}, sent before a brake, reached the drive after it")
            }
        }
    }
}

/// A stop the driver must send.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StopOrder {
    /// Index of the drive in the plant.
    pub drive: usize,
    /// The stop.
    pub id: StopId,
    /// Who held the lease it ends (`None`: a brake applied again).
    pub owner: Option<Arc<str>>,
    /// What to send.
    pub action: StopAction,
    /// The mode to decide on when the drive's cannot be read.
    pub mode: Mode,
    /// 1 for the first try.
    pub attempt: u32,
}

/// What became of one try of a stop, as the driver reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StopReport {
    /// What was sent, in words, if anything may have reached the drive.
    pub sent: Option<String>,
    /// What the drive confirmed, or why the try failed.
    pub result: Result<String, String>,
    /// True when something that can release a brake may have reached the
    /// drive (a zero-speed setpoint).
    pub released_brake: bool,
}

/// News of a lease, for the stream and the event log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LeaseEvent {
    /// A lease ended without a stop: released, replaced, or ended by a
    /// write that stops the motor itself.
    Ended {
        /// Drive index.
        drive: usize,
        /// Who held it.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// Why, in words.
        reason: String,
    },
    /// A lease ended with its stop, and the stop's first try ended (or
    /// something took over before it was sent).
    Expired {
        /// Drive index.
        drive: usize,
        /// Who held it.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// Why it ended.
        reason: String,
        /// The stop action.
        action: StopAction,
        /// What was sent, if anything.
        sent: Option<String>,
        /// True when the stop was carried out (or nothing was needed).
        ok: bool,
        /// The drive's answer, or why it failed.
        result: String,
        /// True when drivegate keeps trying.
        retrying: bool,
    },
    /// A stop that failed at first ended: carried out, or taken over.
    StopSettled {
        /// Drive index.
        drive: usize,
        /// Who held the lease.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// The stop action.
        action: StopAction,
        /// What was sent at last, if anything.
        sent: Option<String>,
        /// True when the drive confirmed it.
        stopped: bool,
        /// Tries made.
        attempts: u32,
        /// The drive's answer, or what took over.
        result: String,
    },
}

impl LeaseEvent {
    /// The drive it concerns.
    pub fn drive(&self) -> usize {
        match self {
            LeaseEvent::Ended { drive, .. }
            | LeaseEvent::Expired { drive, .. }
            | LeaseEvent::StopSettled { drive, .. } => *drive,
        }
    }

    /// The holder of the lease it concerns.
    pub fn holder(&self) -> Holder {
        match self {
            LeaseEvent::Ended { holder, .. }
            | LeaseEvent::Expired { holder, .. }
            | LeaseEvent::StopSettled { holder, .. } => *holder,
        }
    }
}

/// What the book asks of its driver.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Effect {
    /// Send a stop and report with [`LeaseBook::stop_tried`].
    Stop(StopOrder),
    /// Publish this.
    Event(LeaseEvent),
    /// A communication-loss lease on `drive` ended: by silence (`closed`
    /// false) or by its session closing. Counted per bus.
    CommLoss {
        /// Drive index.
        drive: usize,
        /// True when its session closed.
        closed: bool,
    },
}

/// Why there is no lease to renew or release, in words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NoLease(pub String);

struct Lease {
    id: LeaseId,
    owner: Arc<str>,
    holder: Holder,
    mode: Mode,
    action: StopAction,
    comm_loss: bool,
    length: Duration,
    deadline: Instant,
    /// False until its setpoint was settled: the deadline then still
    /// allows for the bus queue.
    confirmed: bool,
}

/// How a drive's last lease ended.
struct Ended {
    id: LeaseId,
    owner: Arc<str>,
    holder: Holder,
    at: Instant,
    how: How,
}

enum How {
    /// Released (no stop) by this caller.
    Released(Arc<str>),
    /// Replaced by a newer lease.
    Replaced(Arc<str>),
    /// Ended by a confirmed write that stops the motor.
    EndedBy(Arc<str>),
    /// Ended with a stop; the stop is `Slot::stop` while it has this id.
    Stopping { reason: StopReason, stop: StopId },
    /// Ended with a stop, which ended so.
    Stopped {
        reason: StopReason,
        action: StopAction,
        end: StopEnd,
    },
}

/// How a stop ended.
#[derive(Clone)]
enum StopEnd {
    /// The drive confirmed it (or nothing was needed): the result.
    Done(String),
    /// Something newer took over the drive first.
    Superseded(String),
    /// Left to the daemon's safe stop at shutdown.
    Abandoned,
}

/// A stop being carried out.
struct Stop {
    id: StopId,
    /// The lease it ends, if it ends one (a brake re-applied has none).
    lease: Option<(LeaseId, Arc<str>, Holder)>,
    reason: StopReason,
    action: StopAction,
    mode: Mode,
    state: StopState,
    tries: u32,
    last_error: Option<String>,
    /// Send once more after the try under way: a leased setpoint landed.
    again: bool,
    /// The end of the lease was published (after the first try).
    announced: bool,
    /// Brakes sent before the try under way.
    seen: u64,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum StopState {
    /// To be sent at this instant.
    Due(Instant),
    /// Sent, result awaited.
    InFlight,
}

#[derive(Default)]
struct Slot {
    lease: Option<Lease>,
    last: Option<Ended>,
    stop: Option<Stop>,
    /// Brakes and deactivations on their way.
    stopping_writes: u32,
    /// Brakes sent to the drive so far: each brake's number.
    brakes_sent: u64,
    /// The highest number of a brake that reached the drive (or may have).
    brake_landed: u64,
    /// Brakes on their way, by number: true once a write sent before it
    /// that releases a brake has landed, and may have landed after it.
    brakes_in_flight: BTreeMap<u64, bool>,
    /// Stops taken over while on their way, with the brakes sent before
    /// them: what they send must still not release a later brake.
    orphans: Vec<(StopId, u64)>,
}

/// An open session.
struct Session {
    /// How its closing reads ("its WebSocket closed").
    closing: &'static str,
    /// Its communication-loss function, if it has one.
    comm_loss: Option<CommLoss>,
}

/// Every lease of the plant.
pub struct LeaseBook {
    action: StopAction,
    retry_first: Duration,
    retry_max: Duration,
    slots: BTreeMap<usize, Slot>,
    /// Open sessions.
    sessions: BTreeMap<SessionId, Session>,
    next_id: u64,
    shut_down: bool,
}

impl LeaseBook {
    /// A book whose leases end with `action`.
    pub fn new(action: StopAction) -> Self {
        LeaseBook {
            action,
            retry_first: RETRY_FIRST,
            retry_max: RETRY_MAX,
            slots: BTreeMap::new(),
            sessions: BTreeMap::new(),
            next_id: 1,
            shut_down: false,
        }
    }

    /// The stop action of expired leases.
    pub fn action(&self) -> StopAction {
        self.action
    }

    fn next(&mut self) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        id
    }

    fn slot(&mut self, drive: usize) -> &mut Slot {
        self.slots.entry(drive).or_default()
    }

    /// A session opened; `closing` is how its end reads in messages
    /// ("its WebSocket closed"), `comm_loss` its communication-loss
    /// function, if it has one.
    pub fn session_opened(
        &mut self,
        session: SessionId,
        closing: &'static str,
        comm_loss: Option<CommLoss>,
    ) {
        self.sessions
            .insert(session, Session { closing, comm_loss });
    }

    /// A session closed: its leases end now, with their stop.
    pub fn session_closed(&mut self, session: SessionId, now: Instant) -> Vec<Effect> {
        let closing = self
            .sessions
            .remove(&session)
            .map_or(SESSION_CLOSED, |s| s.closing);
        let drives: Vec<(usize, bool)> = self
            .slots
            .iter()
            .filter_map(|(d, s)| {
                let lease = s.lease.as_ref()?;
                (lease.holder == Holder::Session(session)).then_some((*d, lease.comm_loss))
            })
            .collect();
        let mut effects = Vec::new();
        for (drive, comm_loss) in drives {
            if comm_loss && !self.shut_down {
                effects.push(Effect::CommLoss {
                    drive,
                    closed: true,
                });
            }
            self.end_with_stop(drive, StopReason::SessionClosed(closing), now);
        }
        effects.extend(self.tick(now));
        effects
    }

    /// Any request came on `session`: its communication-loss leases run
    /// for their length from `now` (never brought closer while a setpoint
    /// waits for the bus). Other leases are renewed only when asked.
    pub fn session_active(&mut self, session: SessionId, now: Instant) {
        for slot in self.slots.values_mut() {
            if let Some(lease) = slot.lease.as_mut()
                && lease.comm_loss
                && lease.holder == Holder::Session(session)
            {
                lease.deadline = if lease.confirmed {
                    now + lease.length
                } else {
                    (now + lease.length).max(lease.deadline)
                };
            }
        }
    }

    /// The lease a setpoint or mode command of a caller in `session` takes:
    /// the one it asked for (`asked`, with `action`), else, in a session
    /// with a communication-loss time, a communication-loss lease; else
    /// none.
    pub fn terms(
        &self,
        session: Option<SessionId>,
        asked: Option<Duration>,
        action: Option<StopAction>,
    ) -> Option<Terms> {
        if let Some(length) = asked {
            return Some(Terms {
                length,
                action,
                comm_loss: false,
            });
        }
        let comm_loss = self.sessions.get(&session?)?.comm_loss?;
        Some(Terms {
            length: comm_loss.after,
            action: Some(comm_loss.action),
            comm_loss: true,
        })
    }

    /// Puts a lease on `drive` for `ask`, replacing any lease there. Until
    /// its setpoint is settled it runs for `length + allowance`.
    pub fn grant(&mut self, drive: usize, ask: LeaseAsk, now: Instant) -> (Grant, Vec<Effect>) {
        let id = LeaseId(self.next());
        let lease = Lease {
            id,
            owner: ask.owner.clone(),
            holder: ask.holder,
            mode: ask.mode,
            action: ask.action.unwrap_or(self.action),
            comm_loss: ask.comm_loss,
            length: ask.length,
            deadline: now + ask.length + ask.allowance,
            confirmed: false,
        };
        let slot = self.slot(drive);
        let old = slot.lease.replace(lease);
        let mut effects = Vec::new();
        let replaced = old.is_some();
        if let Some(old) = old {
            // A communication-loss lease taken again by its own session (a
            // PLC writing its setpoint each cycle) goes on: no news.
            let same = old.comm_loss && ask.comm_loss && old.holder == ask.holder;
            if !same {
                let reason = format!("replaced by a leased setpoint from {}", ask.owner);
                effects.push(Effect::Event(LeaseEvent::Ended {
                    drive,
                    owner: old.owner.clone(),
                    holder: old.holder,
                    reason,
                }));
            }
            // A stop still to be done for an older lease goes on: what it
            // stops was never confirmed to have changed.
            if !matches!(
                slot.last,
                Some(Ended {
                    how: How::Stopping { .. },
                    ..
                })
            ) {
                slot.last = Some(Ended {
                    id: old.id,
                    owner: old.owner,
                    holder: old.holder,
                    at: now,
                    how: How::Replaced(ask.owner),
                });
            }
        }
        (Grant { id, replaced }, effects)
    }

    /// Takes a ticket for a write of `kind` to `drive`, sent by `by`.
    pub fn begin_write(&mut self, drive: usize, kind: WriteKind, by: Arc<str>) -> Ticket {
        let slot = self.slot(drive);
        if matches!(kind, WriteKind::Brake | WriteKind::Deactivate) {
            slot.stopping_writes += 1;
        }
        if kind == WriteKind::Brake {
            slot.brakes_sent += 1;
            slot.brakes_in_flight.insert(slot.brakes_sent, false);
        }
        Ticket {
            drive,
            kind,
            seen: slot.brakes_sent,
            by,
        }
    }

    /// The write of `ticket` was settled: `applied` says whether it
    /// reached the drive.
    pub fn end_write(&mut self, ticket: &Ticket, applied: Applied, now: Instant) -> Vec<Effect> {
        let drive = ticket.drive;
        let by = ticket.by.clone();
        let mut effects = Vec::new();
        match ticket.kind {
            WriteKind::Setpoint { lease } => {
                self.settle_setpoint(drive, lease, applied, &by, true, now, &mut effects);
                if applied != Applied::No {
                    self.released(drive, ticket.seen, &by, now);
                }
            }
            WriteKind::ReleasesBrake { lease } => {
                if lease.is_some() {
                    // A mode command sets no speed: it never takes over a
                    // stop still being tried.
                    self.settle_setpoint(drive, lease, applied, &by, false, now, &mut effects);
                }
                if applied != Applied::No {
                    self.released(drive, ticket.seen, &by, now);
                }
            }
            WriteKind::Brake | WriteKind::Deactivate => {
                let slot = self.slot(drive);
                slot.stopping_writes = slot.stopping_writes.saturating_sub(1);
                let brake = ticket.kind == WriteKind::Brake;
                // Whether a write sent before this brake landed meanwhile.
                let overtaken =
                    brake && slot.brakes_in_flight.remove(&ticket.seen).unwrap_or(false);
                if brake && applied != Applied::No {
                    slot.brake_landed = slot.brake_landed.max(ticket.seen);
                }
                match applied {
                    Applied::Yes => {
                        self.end_by(drive, &by, now, &mut effects);
                        if overtaken && !self.shut_down {
                            self.rebrake(drive, StopReason::BrakeReleased(by.clone()), now);
                        }
                    }
                    Applied::Maybe if brake => {
                        // It may have landed, so what was sent before it
                        // must not release it; and it is applied until the
                        // drive confirms it.
                        self.end_with(
                            drive,
                            StopReason::BrakeUnconfirmed(by.clone()),
                            StopAction::Brake,
                            now,
                        );
                    }
                    Applied::Maybe | Applied::No => {}
                }
            }
        }
        effects.extend(self.tick(now));
        effects
    }

    /// Settles the lease of a setpoint (or mode command) and, when
    /// `takes_over`, ends a stop still being tried on the drive.
    #[allow(clippy::too_many_arguments)]
    fn settle_setpoint(
        &mut self,
        drive: usize,
        grant: Option<Grant>,
        applied: Applied,
        by: &Arc<str>,
        takes_over: bool,
        now: Instant,
        effects: &mut Vec<Effect>,
    ) {
        let Some(grant) = grant else {
            if applied == Applied::Yes {
                self.supersede(drive, by, effects);
            }
            return;
        };
        let live = self
            .slots
            .get(&drive)
            .and_then(|s| s.lease.as_ref())
            .is_some_and(|l| l.id == grant.id);
        if !live {
            if applied != Applied::No {
                // It ended while its setpoint waited: the setpoint may have
                // landed after the stop and set the motor going again.
                self.stop_again(drive, grant.id, now);
            }
            return;
        }
        if applied == Applied::No && !grant.replaced {
            // Surely never reached the drive, and covered nothing before.
            self.slot(drive).lease = None;
            return;
        }
        let lease = self.slots.get(&drive).and_then(|s| s.lease.as_ref());
        let closed = lease
            .and_then(|l| l.holder.session())
            .is_some_and(|s| !self.sessions.contains_key(&s));
        if closed {
            // Its session closed while the setpoint was on its way.
            if lease.is_some_and(|l| l.comm_loss) && !self.shut_down {
                effects.push(Effect::CommLoss {
                    drive,
                    closed: true,
                });
            }
            self.end_with_stop(drive, StopReason::SessionClosed(SESSION_CLOSED), now);
            return;
        }
        let Some(lease) = self.slot(drive).lease.as_mut() else {
            return;
        };
        lease.confirmed = true;
        lease.deadline = now + lease.length;
        let owner = lease.owner.clone();
        if applied == Applied::Yes && takes_over {
            let by: Arc<str> = format!("a leased setpoint from {owner}").into();
            self.supersede(drive, &by, effects);
        }
    }

    /// A write that releases a brake, sent after `seen` brakes, reached
    /// the drive (or may have). The results of writes come back in any
    /// order, so it may have landed after any brake sent later: one that
    /// landed already is applied again now; one still on its way is, once
    /// it lands.
    fn released(&mut self, drive: usize, seen: u64, by: &Arc<str>, now: Instant) {
        if self.shut_down {
            return;
        }
        let slot = self.slot(drive);
        for (_, overtaken) in slot.brakes_in_flight.range_mut(seen + 1..) {
            *overtaken = true;
        }
        if slot.brake_landed > seen {
            // A lease on the drive now is newer than the brake (the brake
            // ended the one before): the brake waits for it, and its
            // setpoint takes over.
            self.rebrake(drive, StopReason::BrakeReleased(by.clone()), now);
        }
    }

    /// A write that stops the motor itself was confirmed: the lease ends
    /// without a stop, and a stop still being tried is not needed.
    fn end_by(&mut self, drive: usize, by: &Arc<str>, now: Instant, effects: &mut Vec<Effect>) {
        let ended_by: Arc<str> = by.clone();
        self.supersede(drive, &ended_by, effects);
        let slot = self.slot(drive);
        if let Some(lease) = slot.lease.take() {
            effects.push(Effect::Event(LeaseEvent::Ended {
                drive,
                owner: lease.owner.clone(),
                holder: lease.holder,
                reason: format!("{by} was confirmed"),
            }));
            slot.last = Some(Ended {
                id: lease.id,
                owner: lease.owner,
                holder: lease.holder,
                at: now,
                how: How::EndedBy(by.clone()),
            });
        }
    }

    /// Something newer took over `drive`: a stop still to be done there is
    /// not tried again.
    fn supersede(&mut self, drive: usize, by: &Arc<str>, effects: &mut Vec<Effect>) {
        let slot = self.slot(drive);
        let Some(stop) = slot.stop.take() else {
            return;
        };
        if stop.state == StopState::InFlight {
            slot.orphans.push((stop.id, stop.seen));
        }
        let result = format!("not sent again: {by} took over the drive");
        if let Some((id, owner, holder)) = &stop.lease {
            if stop.announced {
                effects.push(Effect::Event(LeaseEvent::StopSettled {
                    drive,
                    owner: owner.clone(),
                    holder: *holder,
                    action: stop.action,
                    sent: None,
                    stopped: false,
                    attempts: stop.tries,
                    result,
                }));
            } else {
                effects.push(Effect::Event(LeaseEvent::Expired {
                    drive,
                    owner: owner.clone(),
                    holder: *holder,
                    reason: stop.reason.text(),
                    action: stop.action,
                    sent: None,
                    ok: false,
                    result,
                    retrying: false,
                }));
            }
            if let Some(Ended { id: ended, how, .. }) = slot.last.as_mut()
                && ended == id
            {
                *how = How::Stopped {
                    reason: stop.reason.clone(),
                    action: stop.action,
                    end: StopEnd::Superseded(by.to_string()),
                };
            }
        }
    }

    /// Ends `drive`'s lease now with the stop action.
    fn end_with_stop(&mut self, drive: usize, reason: StopReason, now: Instant) {
        let slot = self.slot(drive);
        let action = slot.lease.as_ref().map_or(StopAction::None, |l| l.action);
        self.end_with(drive, reason, action, now);
    }

    /// Ends `drive`'s lease (if any) with a stop by `action`; without a
    /// lease, the stop is begun all the same.
    fn end_with(&mut self, drive: usize, reason: StopReason, action: StopAction, now: Instant) {
        let lease = self.slot(drive).lease.take();
        let (ended, mode) = match lease {
            Some(lease) => {
                let ended = (lease.id, lease.owner.clone(), lease.holder);
                self.slot(drive).last = Some(Ended {
                    id: lease.id,
                    owner: lease.owner,
                    holder: lease.holder,
                    at: now,
                    how: How::Stopping {
                        reason: reason.clone(),
                        stop: StopId(0),
                    },
                });
                (Some(ended), lease.mode)
            }
            None => (None, Mode::Speed),
        };
        self.begin_stop(drive, ended, reason, action, mode, now);
    }

    /// Applies the brake to `drive` again, until the drive confirms it.
    fn rebrake(&mut self, drive: usize, reason: StopReason, now: Instant) {
        self.begin_stop(drive, None, reason, StopAction::Brake, Mode::Speed, now);
    }

    /// Begins a stop of `drive`. A stop still pending there is merged into
    /// it: the stronger action (the brake) wins.
    fn begin_stop(
        &mut self,
        drive: usize,
        lease: Option<(LeaseId, Arc<str>, Holder)>,
        reason: StopReason,
        action: StopAction,
        mode: Mode,
        now: Instant,
    ) {
        let id = StopId(self.next());
        let shut_down = self.shut_down;
        let slot = self.slot(drive);
        let mut action = action;
        let mut lease = lease;
        let mut reason = reason;
        if let Some(old) = slot.stop.take() {
            if old.state == StopState::InFlight {
                slot.orphans.push((old.id, old.seen));
            }
            if old.action == StopAction::Brake {
                action = StopAction::Brake;
            }
            if lease.is_none() {
                lease = old.lease;
                reason = old.reason;
            }
        }
        if let Some(Ended {
            how: How::Stopping { stop, .. },
            id: ended,
            ..
        }) = slot.last.as_mut()
            && lease.as_ref().is_some_and(|(l, _, _)| l == ended)
        {
            *stop = id;
        }
        if shut_down {
            Self::abandon_last(slot);
            return;
        }
        slot.stop = Some(Stop {
            id,
            lease,
            reason,
            action,
            mode,
            state: StopState::Due(now),
            tries: 0,
            last_error: None,
            again: false,
            announced: false,
            seen: slot.brakes_sent,
        });
    }

    fn abandon_last(slot: &mut Slot) {
        if let Some(Ended {
            how: how @ How::Stopping { .. },
            ..
        }) = slot.last.as_mut()
            && let How::Stopping { reason, .. } = how
        {
            *how = How::Stopped {
                reason: reason.clone(),
                action: StopAction::None,
                end: StopEnd::Abandoned,
            };
        }
    }

    /// Lease `id` on `drive` ended before its setpoint was settled, so the
    /// stop may have gone out first and the setpoint landed after it: the
    /// stop is sent again (after the try under way, if there is one).
    fn stop_again(&mut self, drive: usize, id: LeaseId, now: Instant) {
        if self.shut_down {
            return;
        }
        let slot = self.slot(drive);
        if let Some(stop) = slot.stop.as_mut()
            && stop.lease.as_ref().is_some_and(|(l, _, _)| *l == id)
        {
            if stop.state == StopState::InFlight {
                stop.again = true;
            }
            return;
        }
        let Some(Ended {
            id: ended,
            owner,
            holder,
            how:
                How::Stopped {
                    reason,
                    action,
                    end: StopEnd::Done(_),
                },
            ..
        }) = slot.last.as_ref()
        else {
            // Taken over by something newer, or left to the safe stop.
            return;
        };
        if *ended != id {
            return;
        }
        let lease = (id, owner.clone(), *holder);
        let (reason, action) = (reason.clone(), *action);
        slot.last = Some(Ended {
            id,
            owner: lease.1.clone(),
            holder: lease.2,
            at: now,
            how: How::Stopping {
                reason: reason.clone(),
                stop: StopId(0),
            },
        });
        self.begin_stop(drive, Some(lease), reason, action, Mode::Speed, now);
        if let Some(stop) = self.slot(drive).stop.as_mut() {
            // Its end was published with the first stop.
            stop.announced = true;
        }
    }

    /// Pushes the deadline of `drive`'s lease ahead by its length (or a new
    /// `length`). While its setpoint waits for the bus the deadline is never
    /// brought closer: the stop would go out before the setpoint it covers.
    pub fn renew(
        &mut self,
        drive: usize,
        length: Option<Duration>,
        now: Instant,
    ) -> Result<LeaseView, NoLease> {
        let Some(lease) = self.slot(drive).lease.as_mut() else {
            return Err(self.no_lease(drive, now));
        };
        if let Some(l) = length {
            lease.length = l;
        }
        let renewed = now + lease.length;
        lease.deadline = if lease.confirmed {
            renewed
        } else {
            renewed.max(lease.deadline)
        };
        Ok(view(lease, now))
    }

    /// Ends `drive`'s lease without a stop, for `by`.
    pub fn release(
        &mut self,
        drive: usize,
        by: &Arc<str>,
        now: Instant,
    ) -> Result<(LeaseView, Vec<Effect>), NoLease> {
        let Some(lease) = self.slot(drive).lease.take() else {
            return Err(self.no_lease(drive, now));
        };
        let shown = view(&lease, now);
        let slot = self.slot(drive);
        let effects = vec![Effect::Event(LeaseEvent::Ended {
            drive,
            owner: lease.owner.clone(),
            holder: lease.holder,
            reason: format!("released by {by} without a stop"),
        })];
        // A stop still to be done for an older lease goes on: what it
        // stops was never confirmed to have changed.
        if slot.stop.as_ref().is_none_or(|s| s.lease.is_none()) {
            slot.last = Some(Ended {
                id: lease.id,
                owner: lease.owner,
                holder: lease.holder,
                at: now,
                how: How::Released(by.clone()),
            });
        }
        Ok((shown, effects))
    }

    /// `drive`'s lease, if any.
    pub fn lease(&self, drive: usize, now: Instant) -> Option<LeaseView> {
        self.slots
            .get(&drive)
            .and_then(|s| s.lease.as_ref())
            .map(|l| view(l, now))
    }

    /// True when a stop is being carried out on `drive`.
    pub fn stopping(&self, drive: usize) -> bool {
        self.slots.get(&drive).is_some_and(|s| s.stop.is_some())
    }

    /// Ends leases that ran out and sends the stops that are due.
    pub fn tick(&mut self, now: Instant) -> Vec<Effect> {
        if self.shut_down {
            return Vec::new();
        }
        let expired: Vec<(usize, Option<Duration>)> = self
            .slots
            .iter()
            .filter_map(|(d, s)| {
                let lease = s.lease.as_ref().filter(|l| l.deadline <= now)?;
                Some((*d, lease.comm_loss.then_some(lease.length)))
            })
            .collect();
        let mut effects = Vec::new();
        for (drive, comm_loss) in expired {
            let reason = match comm_loss {
                Some(after) => {
                    effects.push(Effect::CommLoss {
                        drive,
                        closed: false,
                    });
                    StopReason::CommLost(after)
                }
                None => StopReason::NotRenewed,
            };
            self.end_with_stop(drive, reason, now);
        }
        for (&drive, slot) in &mut self.slots {
            let held = slot.stopping_writes > 0 || slot.lease.is_some();
            let Some(stop) = slot.stop.as_mut() else {
                continue;
            };
            if held {
                continue;
            }
            if let StopState::Due(at) = stop.state
                && at <= now
            {
                stop.state = StopState::InFlight;
                stop.tries += 1;
                stop.seen = slot.brakes_sent;
                effects.push(Effect::Stop(StopOrder {
                    drive,
                    id: stop.id,
                    owner: stop.lease.as_ref().map(|(_, owner, _)| owner.clone()),
                    action: stop.action,
                    mode: stop.mode,
                    attempt: stop.tries,
                }));
            }
        }
        effects
    }

    /// When [`tick`](Self::tick) has something to do next, if ever.
    pub fn next_wake(&self) -> Option<Instant> {
        if self.shut_down {
            return None;
        }
        let deadlines = self
            .slots
            .values()
            .filter_map(|s| s.lease.as_ref().map(|l| l.deadline));
        let stops = self.slots.values().filter_map(|s| {
            let held = s.stopping_writes > 0 || s.lease.is_some();
            match s.stop.as_ref()?.state {
                StopState::Due(at) if !held => Some(at),
                _ => None,
            }
        });
        deadlines.chain(stops).min()
    }

    /// Records a try of stop `id` on `drive`.
    pub fn stop_tried(
        &mut self,
        drive: usize,
        id: StopId,
        report: StopReport,
        now: Instant,
    ) -> Vec<Effect> {
        let mut effects = Vec::new();
        let (retry_first, retry_max) = (self.retry_first, self.retry_max);
        let shut_down = self.shut_down;
        let slot = self.slot(drive);
        let current = slot.stop.as_ref().is_some_and(|s| s.id == id);
        if !current {
            // Taken over while on its way: what it sent must still not
            // release a brake confirmed since.
            let orphan = slot.orphans.iter().position(|(o, _)| *o == id);
            if let Some(at) = orphan {
                let (_, seen) = slot.orphans.swap_remove(at);
                if report.released_brake {
                    self.released(drive, seen, &"a lease's stop".into(), now);
                }
            }
            effects.extend(self.tick(now));
            return effects;
        }
        let Some(mut stop) = slot.stop.take() else {
            return effects;
        };
        let released = report.released_brake.then_some(stop.seen);
        let first = !stop.announced;
        let lease = stop.lease.clone();
        match &report.result {
            Ok(_) if stop.again && !shut_down => {
                stop.again = false;
                stop.state = StopState::Due(now);
                stop.announced = true;
                if let Some((_, owner, holder)) = &lease
                    && first
                {
                    effects.push(Effect::Event(expired(
                        drive, owner, *holder, &stop, &report, false,
                    )));
                }
                slot.stop = Some(stop);
            }
            Ok(result) => {
                if let Some((lease_id, owner, holder)) = &lease {
                    effects.push(Effect::Event(if first {
                        expired(drive, owner, *holder, &stop, &report, false)
                    } else {
                        settled(drive, owner, *holder, &stop, &report)
                    }));
                    if let Some(Ended { id: ended, how, .. }) = slot.last.as_mut()
                        && ended == lease_id
                    {
                        *how = How::Stopped {
                            reason: stop.reason.clone(),
                            action: stop.action,
                            end: StopEnd::Done(result.clone()),
                        };
                    }
                }
            }
            Err(error) => {
                let wait = backoff(retry_first, retry_max, stop.tries);
                stop.last_error = Some(error.clone());
                stop.state = StopState::Due(now + wait);
                if let Some((_, owner, holder)) = &lease
                    && first
                {
                    effects.push(Effect::Event(expired(
                        drive, owner, *holder, &stop, &report, !shut_down,
                    )));
                }
                stop.announced = true;
                if shut_down {
                    Self::abandon_last(slot);
                } else {
                    slot.stop = Some(stop);
                }
            }
        }
        if let Some(seen) = released {
            self.released(drive, seen, &"a lease's stop".into(), now);
        }
        effects.extend(self.tick(now));
        effects
    }

    /// The bus or these drives answer again: stops waiting to be tried
    /// again go now.
    pub fn link_back(&mut self, drives: &[usize], now: Instant) -> Vec<Effect> {
        for drive in drives {
            if let Some(stop) = self.slots.get_mut(drive).and_then(|s| s.stop.as_mut())
                && stop.tries > 0
                && matches!(stop.state, StopState::Due(at) if at > now)
            {
                stop.state = StopState::Due(now);
            }
        }
        self.tick(now)
    }

    /// The daemon stops: its own safe stop covers every moving drive, so
    /// leases and stops end here, with nothing more sent.
    pub fn shutdown(&mut self) {
        self.shut_down = true;
        for slot in self.slots.values_mut() {
            slot.lease = None;
            if slot.stop.take().is_some() {
                Self::abandon_last(slot);
            }
        }
    }

    /// What became of `drive`'s last lease, for a client that finds none.
    pub fn no_lease(&self, drive: usize, now: Instant) -> NoLease {
        let slot = self.slots.get(&drive);
        let Some(ended) = slot.and_then(|s| s.last.as_ref()) else {
            return NoLease("has no lease: none was granted since drivegate started".to_string());
        };
        let ago = now.saturating_duration_since(ended.at).as_secs_f64();
        let head = format!(
            "has no lease: the last one, held by {}, ended {ago:.1} s ago",
            ended.owner
        );
        let action = self.action.name();
        NoLease(match &ended.how {
            How::Released(by) => {
                format!("{head}, released by {by} without a stop; the motor kept its setpoint")
            }
            How::Replaced(by) => format!("{head}, replaced by a leased setpoint from {by}"),
            How::EndedBy(what) => format!("{head} when {what} was confirmed"),
            How::Stopping { reason, .. } => {
                let stop = slot.and_then(|s| s.stop.as_ref());
                let action = stop.map_or(action, |s| s.action.name());
                let state = match stop {
                    Some(Stop {
                        tries,
                        state,
                        last_error: Some(error),
                        ..
                    }) => {
                        // The try under way has not failed (yet).
                        let failed = tries.saturating_sub(u32::from(*state == StopState::InFlight));
                        format!(
                            "its stop ({action}) is not confirmed yet: {failed} attempt(s) failed, the last with \"{error}\"; drivegate keeps trying it until the drive confirms it"
                        )
                    }
                    _ => format!("its stop ({action}) is being sent"),
                };
                format!("{head} because {}; {state}", reason.text())
            }
            How::Stopped {
                reason,
                action: stop_action,
                end,
            } => {
                // A stop left to the safe stop does not keep its action.
                let action = if matches!(end, StopEnd::Abandoned) {
                    action
                } else {
                    stop_action.name()
                };
                let state = match end {
                    StopEnd::Done(result) => {
                        format!("its stop ({action}) was carried out: {result}")
                    }
                    StopEnd::Superseded(by) => format!(
                        "its stop ({action}) was not confirmed before {by} took over the drive, and is not tried again"
                    ),
                    StopEnd::Abandoned => format!(
                        "its stop ({action}) was left to the safe stop of drivegate, which was stopping"
                    ),
                };
                format!("{head} because {}; {state}", reason.text())
            }
        })
    }
}

fn view(lease: &Lease, now: Instant) -> LeaseView {
    LeaseView {
        id: lease.id,
        owner: lease.owner.clone(),
        holder: lease.holder,
        length: lease.length,
        expires_in: lease.deadline.saturating_duration_since(now),
        action: lease.action,
        comm_loss: lease.comm_loss,
    }
}

fn backoff(first: Duration, max: Duration, tries: u32) -> Duration {
    let doublings = tries.saturating_sub(1).min(16);
    (first * 2u32.pow(doublings)).min(max)
}

/// What the stream shows as a stop's result: the drive's answer, or why.
fn shown(report: &StopReport) -> Result<String, String> {
    match &report.result {
        Ok(_) if report.sent.is_some() => Ok("confirmed by the drive".to_string()),
        other => other.clone(),
    }
}

fn expired(
    drive: usize,
    owner: &Arc<str>,
    holder: Holder,
    stop: &Stop,
    report: &StopReport,
    retrying: bool,
) -> LeaseEvent {
    let result = shown(report);
    LeaseEvent::Expired {
        drive,
        owner: owner.clone(),
        holder,
        reason: stop.reason.text(),
        action: stop.action,
        sent: report.sent.clone(),
        ok: result.is_ok(),
        result: result.unwrap_or_else(|e| e),
        retrying,
    }
}

fn settled(
    drive: usize,
    owner: &Arc<str>,
    holder: Holder,
    stop: &Stop,
    report: &StopReport,
) -> LeaseEvent {
    let result = shown(report);
    LeaseEvent::StopSettled {
        drive,
        owner: owner.clone(),
        holder,
        action: stop.action,
        sent: report.sent.clone(),
        stopped: result.is_ok(),
        attempts: stop.tries,
        result: result.unwrap_or_else(|e| e),
    }
}

#[cfg(test)]
mod tests;
