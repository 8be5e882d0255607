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

mod brake_guard;
mod notes;
mod sessions;
mod stop_retry;
mod types;

pub use notes::Note;
pub use stop_retry::{RETRY_FIRST, RETRY_MAX};
pub use types::*;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::caller::{Face, SessionId};
use super::outcome::Applied;
use crate::control::journal::format::BrakeState;
use crate::control::stop_action::StopAction;
use crate::drive::Mode;

use types::SESSION_CLOSED;

struct Lease {
    id: LeaseId,
    owner: Arc<str>,
    holder: Holder,
    mode: Mode,
    action: StopAction,
    comm_loss: bool,
    /// The face of its session's communication-loss function, if its
    /// session has one (whether this lease is a communication-loss one or
    /// asked for explicitly in that session).
    face: Option<Face>,
    length: Duration,
    deadline: Instant,
    /// False until its setpoint was settled: the deadline then still
    /// allows for the bus queue.
    confirmed: bool,
    /// The deadline the safety journal holds, once journaled.
    journaled: Option<Instant>,
}

/// How a drive's last lease ended.
struct Ended {
    id: LeaseId,
    owner: Arc<str>,
    holder: Holder,
    /// The mode of its setpoint: the motion its stop ends.
    mode: Mode,
    at: Instant,
    how: How,
}

enum How {
    /// Released (no stop) by this caller.
    Released(Arc<str>),
    /// Replaced by a newer lease.
    Replaced(Arc<str>),
    /// Ended by a confirmed write that stops the motor; for a
    /// deactivation, with the lease's stop: a setpoint of it that the drive
    /// confirms afterwards (activated again meanwhile) turns the motor with
    /// no lease, and has this stop.
    EndedBy(Arc<str>, Option<StopAction>),
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
    /// The number of the brake the try under way sends, if it sends one.
    brake: Option<u64>,
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
    /// them (and the brake they send, numbered): what they send must
    /// still not release a later brake.
    orphans: Vec<(StopId, u64, Option<u64>)>,
    /// The drive's brake as the safety journal holds it.
    brake_journal: Option<BrakeState>,
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
    /// Facts for the safety journal, taken by the driver.
    notes: Vec<Note>,
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
            notes: Vec::new(),
        }
    }

    /// The stop action of expired leases.
    pub fn action(&self) -> StopAction {
        self.action
    }

    /// Leases granted from now on end with `action` (a reload of
    /// `[safety] on_lease_expiry`); a lease keeps the action it was
    /// granted with.
    pub fn set_action(&mut self, action: StopAction) {
        self.action = action;
    }

    fn next(&mut self) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        id
    }

    fn slot(&mut self, drive: usize) -> &mut Slot {
        self.slots.entry(drive).or_default()
    }

    /// Puts a lease on `drive` for `ask`, replacing any lease there. Until
    /// its setpoint is settled it runs for `length + allowance`.
    pub fn grant(&mut self, drive: usize, ask: LeaseAsk, now: Instant) -> (Grant, Vec<Effect>) {
        let id = LeaseId(self.next());
        let face = ask
            .holder
            .session()
            .and_then(|s| self.sessions.get(&s))
            .and_then(|s| s.comm_loss)
            .map(|c| c.face);
        let lease = Lease {
            id,
            owner: ask.owner.clone(),
            holder: ask.holder,
            mode: ask.mode,
            action: ask.action.unwrap_or(self.action),
            comm_loss: ask.comm_loss,
            face,
            length: ask.length,
            deadline: now + ask.length + ask.allowance,
            confirmed: false,
            journaled: None,
        };
        let slot = self.slot(drive);
        let old = slot.lease.replace(lease);
        let mut effects = Vec::new();
        let replaced = old.is_some();
        if let Some(old) = old {
            // A communication-loss lease taken again by its own session (a
            // PLC writing its setpoint each cycle) goes on: no news.
            let same = old.comm_loss && ask.comm_loss && old.holder == ask.holder;
            if let Some(new) = slot.lease.as_mut()
                && same
                && (old.owner.clone(), old.action, old.mode)
                    == (new.owner.clone(), new.action, new.mode)
            {
                // Journaled already, and its deadline does not matter.
                new.journaled = old.journaled;
            }
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
                    mode: old.mode,
                    at: now,
                    how: How::Replaced(ask.owner),
                });
            }
        }
        self.note_lease_by(drive, Some(now + ask.length));
        (Grant { id, replaced }, effects)
    }

    /// Settles the lease of a setpoint of mode `sets` (or of a mode
    /// command, `None`) and, when it took over, ends a stop still being
    /// tried on the drive. A mode command sets no motion: it takes over
    /// nothing. A confirmed leased setpoint does: its lease covers the
    /// motor. One without a lease does only when it sets the motion the
    /// stop ends, the setpoint of that stop's mode: another mode's leaves
    /// the motor at what the ended lease set, with nobody owning it.
    #[allow(clippy::too_many_arguments)]
    fn settle_setpoint(
        &mut self,
        drive: usize,
        grant: Option<Grant>,
        applied: Applied,
        by: &Arc<str>,
        sets: Option<Mode>,
        now: Instant,
        effects: &mut Vec<Effect>,
    ) {
        let Some(grant) = grant else {
            if applied == Applied::Yes && sets.is_some_and(|m| self.stop_of_mode(drive, m)) {
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
            if applied == Applied::Yes {
                self.deactivated_then_landed(drive, grant.id, now);
            }
            return;
        }
        if applied == Applied::No && !grant.replaced {
            // Surely never reached the drive, and covered nothing before.
            self.slot(drive).lease = None;
            self.note(Note::LeaseEnded { drive });
            return;
        }
        let lease = self.slots.get(&drive).and_then(|s| s.lease.as_ref());
        let closed = lease
            .and_then(|l| l.holder.session())
            .is_some_and(|s| !self.sessions.contains_key(&s));
        if closed {
            // Its session closed while the setpoint was on its way.
            if let Some(l) = lease.filter(|l| l.comm_loss)
                && !self.shut_down
            {
                effects.push(Effect::CommLoss {
                    drive,
                    closed: true,
                    face: l.face.unwrap_or(Face::ModbusTcp),
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
        self.note_lease(drive);
        if applied == Applied::Yes && sets.is_some() {
            let by: Arc<str> = format!("a leased setpoint from {owner}").into();
            self.supersede(drive, &by, effects);
        }
    }

    /// True when a setpoint of `mode` sets the motion of the stop being
    /// tried on `drive`: the motion of the mode of the lease it ends (not
    /// the last poll's, which a drive silent since the lease's mode command
    /// never showed). A brake applied again for no lease ends any motion;
    /// without a stop, there is nothing to take over.
    fn stop_of_mode(&self, drive: usize, mode: Mode) -> bool {
        self.slots
            .get(&drive)
            .and_then(|s| s.stop.as_ref())
            .is_none_or(|s| s.lease.is_none() || s.mode == mode)
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
        let shown = view(lease, now);
        self.note_lease(drive);
        Ok(shown)
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
        self.note(Note::LeaseEnded { drive });
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
                mode: lease.mode,
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
        let expired: Vec<(usize, Option<(Duration, Face)>)> = self
            .slots
            .iter()
            .filter_map(|(d, s)| {
                let lease = s.lease.as_ref().filter(|l| l.deadline <= now)?;
                let face = lease.face.unwrap_or(Face::ModbusTcp);
                Some((*d, lease.comm_loss.then_some((lease.length, face))))
            })
            .collect();
        let mut effects = Vec::new();
        for (drive, comm_loss) in expired {
            let reason = match comm_loss {
                Some((after, face)) => {
                    effects.push(Effect::CommLoss {
                        drive,
                        closed: false,
                        face,
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
                // A brake is a brake, whoever sends it: numbered, so that
                // a write sent before it that lands after it is seen.
                stop.brake = (stop.action == StopAction::Brake).then(|| {
                    slot.brakes_sent += 1;
                    slot.brakes_in_flight.insert(slot.brakes_sent, false);
                    slot.brakes_sent
                });
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
            How::EndedBy(what, _) => format!("{head} when {what} was confirmed"),
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
        comm_loss_face: lease.face,
    }
}

#[cfg(test)]
mod tests;
