//! The brake guard: a brake or a deactivation confirmed from any face ends
//! the drive's lease without a stop, stops wait for a brake on its way,
//! and a brake holds: a write that can release it and lands after it has
//! the brake applied again, until the drive confirms it.

use std::sync::Arc;
use std::time::Instant;

use super::*;

impl LeaseBook {
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
        let seen = slot.brakes_sent;
        let order = self.next();
        match kind {
            // Journaled before it is sent: a restart applies a brake it
            // cannot know was confirmed again.
            WriteKind::Brake => self.note_brake(drive, BrakeState::Sent),
            WriteKind::Setpoint { .. } | WriteKind::ReleasesBrake { .. } => {
                self.note_brake(drive, BrakeState::Off);
            }
            WriteKind::Deactivate => {}
        }
        Ticket {
            drive,
            kind,
            seen,
            by,
            order,
        }
    }

    /// The write of `ticket` was settled: `applied` says whether it
    /// reached the drive.
    pub fn end_write(&mut self, ticket: &Ticket, applied: Applied, now: Instant) -> Vec<Effect> {
        let drive = ticket.drive;
        let by = ticket.by.clone();
        let mut effects = Vec::new();
        match ticket.kind {
            WriteKind::Setpoint { lease, mode } => {
                self.settle_setpoint(drive, lease, applied, &by, Some(mode), now, &mut effects);
                if applied != Applied::No {
                    self.released(drive, ticket.seen, &by, now);
                }
            }
            WriteKind::ReleasesBrake { lease } => {
                if lease.is_some() {
                    // A mode command sets no speed: it never takes over a
                    // stop still being tried.
                    self.settle_setpoint(drive, lease, applied, &by, None, now, &mut effects);
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
                // A lease taken after this brake or deactivation was sent
                // is not its to end: that lease's setpoint comes after it
                // (and releases the brake as asked).
                let newer = self
                    .slots
                    .get(&drive)
                    .and_then(|s| s.lease.as_ref())
                    .is_some_and(|l| l.id.0 > ticket.order);
                match applied {
                    Applied::Yes => {
                        if brake {
                            self.note_brake(drive, BrakeState::Confirmed);
                        }
                        if newer && brake {
                            self.supersede(drive, &by, &mut effects);
                            self.journal_lease_again(drive);
                        } else if newer {
                            // A deactivation: a stop under way is not
                            // needed (but for a brake's).
                            if !self.braking(drive) {
                                self.supersede(drive, &by, &mut effects);
                            }
                        } else {
                            self.end_by(drive, &by, !brake, now, &mut effects);
                        }
                        if overtaken && !self.shut_down {
                            self.rebrake(drive, StopReason::BrakeReleased(by.clone()), now);
                        }
                    }
                    Applied::Maybe if brake && newer => {
                        // Applied again once the newer lease ends (a stop
                        // waits for a lease on the drive).
                        self.rebrake(drive, StopReason::BrakeUnconfirmed(by.clone()), now);
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

    /// A write that releases a brake, sent after `seen` brakes, reached
    /// the drive (or may have). The results of writes come back in any
    /// order, so it may have landed after any brake sent later: one that
    /// landed already is applied again now; one still on its way is, once
    /// it lands.
    pub(super) fn released(&mut self, drive: usize, seen: u64, by: &Arc<str>, now: Instant) {
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

    /// A brake sent by a stop, numbered `number`, came back with
    /// `report`: if it may have reached the drive, what was sent before it
    /// must not release it. True when a write sent before it landed after
    /// it meanwhile (and it may have landed): the brake is owed again.
    pub(super) fn stop_brake_back(
        &mut self,
        drive: usize,
        number: u64,
        report: &StopReport,
    ) -> bool {
        let landed = match &report.result {
            StopResult::Failed(e) => !e.not_sent(),
            _ => true,
        };
        let slot = self.slot(drive);
        let overtaken = slot.brakes_in_flight.remove(&number).unwrap_or(false);
        if landed {
            slot.brake_landed = slot.brake_landed.max(number);
        }
        overtaken && landed
    }

    /// The lease on `drive` outlived a brake the journal says was
    /// confirmed (which a restart reads as the end of its lease): it is
    /// journaled again after it.
    fn journal_lease_again(&mut self, drive: usize) {
        let slot = self.slot(drive);
        if let Some(lease) = slot.lease.as_mut() {
            lease.journaled = None;
            // Its setpoint releases the brake: so the journal reads it.
            slot.brake_journal = None;
        }
        self.note_lease(drive);
    }

    /// A write that stops the motor itself was confirmed: the lease ends
    /// without a stop, and a stop still being tried is not needed; but a
    /// deactivation (`deactivation`) ends no brake being applied: it does
    /// not hold the motor as the brake does.
    pub(super) fn end_by(
        &mut self,
        drive: usize,
        by: &Arc<str>,
        deactivation: bool,
        now: Instant,
        effects: &mut Vec<Effect>,
    ) {
        let ended_by: Arc<str> = by.clone();
        if !(deactivation && self.braking(drive)) {
            self.supersede(drive, &ended_by, effects);
        }
        if self.slots.get(&drive).is_some_and(|s| s.lease.is_some()) {
            self.note(Note::LeaseEnded { drive });
        }
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
                mode: lease.mode,
                at: now,
                how: How::EndedBy(by.clone(), deactivation.then_some(lease.action)),
            });
        }
    }

    /// A setpoint of lease `id`, which a deactivation ended, was confirmed
    /// by the drive afterwards: the drive was activated again meanwhile,
    /// and turns with no lease. The lease's stop goes.
    pub(super) fn deactivated_then_landed(&mut self, drive: usize, id: LeaseId, now: Instant) {
        if self.shut_down {
            return;
        }
        let slot = self.slot(drive);
        if slot.lease.is_some() || slot.stop.is_some() {
            // A lease covers the motor; a stop is under way.
            return;
        }
        let Some(Ended {
            id: ended,
            owner,
            holder,
            mode,
            how: How::EndedBy(what, Some(action)),
            ..
        }) = slot.last.as_ref()
        else {
            return;
        };
        if *ended != id {
            return;
        }
        let lease = (id, owner.clone(), *holder);
        let (reason, action, mode) = (StopReason::LandedAfter(what.clone()), *action, *mode);
        self.stop_ended_lease(drive, lease, reason, action, mode, now);
    }

    /// True while a brake is being applied to `drive` (a stop's).
    fn braking(&self, drive: usize) -> bool {
        self.slots
            .get(&drive)
            .and_then(|s| s.stop.as_ref())
            .is_some_and(|s| s.action == StopAction::Brake)
    }

    /// Applies the brake to `drive` again, until the drive confirms it.
    pub(super) fn rebrake(&mut self, drive: usize, reason: StopReason, now: Instant) {
        self.begin_stop(drive, None, reason, StopAction::Brake, Mode::Speed, now);
    }
}
