//! What the book asks the safety journal to keep, and the restart that
//! reads it back: [`Note`]s are taken by the driver after each transition
//! and written (and synced) before anything it decided reaches the bus.
//!
//! The horizon rule for renewals: the journal holds a lease's deadline
//! never later than the one promised, and at most half a lease length
//! earlier. A renewal that keeps the deadline within that half length of
//! the journaled one writes nothing; one that pushes it further, or brings
//! it closer (a shorter length, a setpoint settled), writes the new one.
//! A client renewing a 1 s lease every 100 ms so costs two records a
//! second, not ten; after a crash its lease ends at most half a length
//! sooner than promised, never later. Leases held by a session are
//! journaled once: a restart ends them whatever their deadline.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::{Ended, Holder, How, Lease, LeaseBook, LeaseId, StopReason};
use crate::control::journal::format::BrakeState;
use crate::control::stop_action::StopAction;
use crate::drive::Mode;

/// A fact for the safety journal.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Note {
    /// A lease is on the drive until `deadline` at the latest.
    Lease {
        /// Drive index.
        drive: usize,
        /// Who holds it.
        owner: Arc<str>,
        /// What holds it.
        holder: Holder,
        /// A communication-loss lease.
        comm_loss: bool,
        /// Its deadline, as journaled.
        deadline: Instant,
        /// Its length.
        length: Duration,
        /// What its end sends.
        action: StopAction,
        /// Its setpoint's mode.
        mode: Mode,
    },
    /// The drive's lease ended without a stop.
    LeaseEnded {
        /// Drive index.
        drive: usize,
    },
    /// A stop of the drive is being carried out.
    Stop {
        /// Drive index.
        drive: usize,
        /// Who held the lease it ends, if any.
        owner: Option<Arc<str>>,
        /// What it sends.
        action: StopAction,
        /// The mode to decide on.
        mode: Mode,
        /// It ends the drive's lease.
        ends_lease: bool,
    },
    /// The drive's stop ended (confirmed, or taken over).
    StopEnded {
        /// Drive index.
        drive: usize,
    },
    /// A brake on its way, confirmed, or released.
    Brake {
        /// Drive index.
        drive: usize,
        /// Where it stands.
        state: BrakeState,
    },
}

impl LeaseBook {
    /// The notes of the transitions since the last call, oldest first.
    pub fn take_notes(&mut self) -> Vec<Note> {
        std::mem::take(&mut self.notes)
    }

    pub(super) fn note(&mut self, note: Note) {
        if !self.shut_down {
            self.notes.push(note);
        }
    }

    /// Journals `drive`'s lease if the horizon rule asks for it.
    pub(super) fn note_lease(&mut self, drive: usize) {
        self.note_lease_by(drive, None);
    }

    /// Journals `drive`'s lease if the horizon rule asks for it, with a
    /// deadline no later than `earliest`. A new lease is journaled with its
    /// length from the grant, not with the allowance for the bus queue: the
    /// deadline its confirmation sets (the length from then) is later by
    /// the queue's wait, within the horizon, so a new lease costs one
    /// synced record, not two.
    pub(super) fn note_lease_by(&mut self, drive: usize, earliest: Option<Instant>) {
        let Some(lease) = self.slots.get_mut(&drive).and_then(|s| s.lease.as_mut()) else {
            return;
        };
        let deadline = earliest.map_or(lease.deadline, |e| e.min(lease.deadline));
        let due = match lease.journaled {
            None => true,
            // A session's lease ends at a restart whatever its deadline.
            Some(_) if lease.holder != Holder::Request => false,
            Some(at) => deadline < at || deadline > at + lease.length / 2,
        };
        if !due {
            return;
        }
        lease.journaled = Some(deadline);
        let note = Note::Lease {
            drive,
            owner: lease.owner.clone(),
            holder: lease.holder,
            comm_loss: lease.comm_loss,
            deadline,
            length: lease.length,
            action: lease.action,
            mode: lease.mode,
        };
        self.note(note);
    }

    /// Journals the brake state of `drive`, if it changed.
    pub(super) fn note_brake(&mut self, drive: usize, state: BrakeState) {
        let slot = self.slot(drive);
        let was = slot.brake_journal;
        let now = (state != BrakeState::Off).then_some(state);
        if was == now {
            return;
        }
        slot.brake_journal = now;
        self.note(Note::Brake { drive, state });
    }

    /// At start-up: puts back an HTTP lease of the old process with the
    /// time it has `left`; its client may renew it.
    #[allow(clippy::too_many_arguments)]
    pub fn restore_lease(
        &mut self,
        drive: usize,
        owner: Arc<str>,
        length: Duration,
        left: Duration,
        action: StopAction,
        mode: Mode,
        now: Instant,
    ) {
        let id = LeaseId(self.next());
        let lease = Lease {
            id,
            owner,
            holder: Holder::Request,
            mode,
            action,
            comm_loss: false,
            face: None,
            length,
            deadline: now + left,
            confirmed: true,
            journaled: Some(now + left),
        };
        self.slot(drive).lease = Some(lease);
    }

    /// At start-up: a stop the old process owed `drive` (`owner`'s lease,
    /// if it ends one), tried until the drive confirms it.
    pub fn restart_stop(
        &mut self,
        drive: usize,
        owner: Option<Arc<str>>,
        action: StopAction,
        mode: Mode,
        why: Arc<str>,
        now: Instant,
    ) {
        let reason = StopReason::Restarted(why);
        let lease = owner.map(|owner| {
            let id = LeaseId(self.next());
            self.slot(drive).last = Some(Ended {
                id,
                owner: owner.clone(),
                holder: Holder::Request,
                mode,
                at: now,
                how: How::Stopping {
                    reason: reason.clone(),
                    stop: super::StopId(0),
                },
            });
            (id, owner, Holder::Request)
        });
        if action == StopAction::Brake {
            // Whatever it was, it is a brake now.
            self.slot(drive).brake_journal = Some(BrakeState::Sent);
        }
        self.begin_stop(drive, lease, reason, action, mode, now);
    }

    /// At start-up: the journal says `drive`'s last confirmed command was a
    /// brake, so a stop owed there is not sent; writes that release the
    /// brake are journaled as such.
    pub fn restore_brake(&mut self, drive: usize) {
        self.slot(drive).brake_journal = Some(BrakeState::Confirmed);
        // The stop it holds back is not owed any more, at any restart.
        self.note(Note::StopEnded { drive });
    }
}
