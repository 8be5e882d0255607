//! The stop retry: a lease that ends with its stop has it sent until the
//! drive confirms it, with backoff (cut short when the bus or the drive
//! comes back), unless something newer takes the drive over first.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::*;

/// First wait before a failed stop is tried again; it doubles up to
/// [`RETRY_MAX`], and the bus or the drive coming back cuts it short.
pub const RETRY_FIRST: Duration = Duration::from_millis(250);
/// Longest wait between two tries of a failed stop.
pub const RETRY_MAX: Duration = Duration::from_secs(5);

impl LeaseBook {
    /// Something newer took over `drive`: a stop still to be done there is
    /// not tried again.
    pub(super) fn supersede(&mut self, drive: usize, by: &Arc<str>, effects: &mut Vec<Effect>) {
        if self.slots.get(&drive).is_some_and(|s| s.stop.is_some()) {
            self.note(Note::StopEnded { drive });
        }
        let slot = self.slot(drive);
        let Some(stop) = slot.stop.take() else {
            return;
        };
        if stop.state == StopState::InFlight {
            slot.orphans.push((stop.id, stop.seen, stop.brake));
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
    /// A reload removes `drive`: its lease (if any) ends now with its
    /// stop. True when there was one (the stop is among the effects).
    pub fn retire(&mut self, drive: usize, now: Instant) -> (bool, Vec<Effect>) {
        let leased = self.slots.get(&drive).is_some_and(|s| s.lease.is_some());
        if !leased {
            return (false, Vec::new());
        }
        self.end_with_stop(drive, StopReason::Removed, now);
        (true, self.tick(now))
    }

    pub(super) fn end_with_stop(&mut self, drive: usize, reason: StopReason, now: Instant) {
        let slot = self.slot(drive);
        let action = slot.lease.as_ref().map_or(StopAction::None, |l| l.action);
        self.end_with(drive, reason, action, now);
    }

    /// Ends `drive`'s lease (if any) with a stop by `action`; without a
    /// lease, the stop is begun all the same.
    pub(super) fn end_with(
        &mut self,
        drive: usize,
        reason: StopReason,
        action: StopAction,
        now: Instant,
    ) {
        let lease = self.slot(drive).lease.take();
        let (ended, mode) = match lease {
            Some(lease) => {
                let ended = (lease.id, lease.owner.clone(), lease.holder);
                self.slot(drive).last = Some(Ended {
                    id: lease.id,
                    owner: lease.owner,
                    holder: lease.holder,
                    mode: lease.mode,
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

    /// Records `lease` as ended and stopping for `reason` (its stop not
    /// numbered yet), and begins that stop.
    pub(super) fn stop_ended_lease(
        &mut self,
        drive: usize,
        lease: (LeaseId, Arc<str>, Holder),
        reason: StopReason,
        action: StopAction,
        mode: Mode,
        now: Instant,
    ) {
        self.slot(drive).last = Some(Ended {
            id: lease.0,
            owner: lease.1.clone(),
            holder: lease.2,
            mode,
            at: now,
            how: How::Stopping {
                reason: reason.clone(),
                stop: StopId(0),
            },
        });
        self.begin_stop(drive, Some(lease), reason, action, mode, now);
    }

    /// Begins a stop of `drive`. A stop still pending there is merged into
    /// it: the stronger action (the brake) wins.
    pub(super) fn begin_stop(
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
        // A stop begun beside a lease (one owed before a lease put back
        // at a restart) waits for it, and ends none.
        let ends_lease = lease.is_some() && slot.lease.is_none();
        let mut action = action;
        let mut lease = lease;
        let mut reason = reason;
        let mut mode = mode;
        if let Some(old) = slot.stop.take() {
            if old.state == StopState::InFlight {
                slot.orphans.push((old.id, old.seen, old.brake));
            }
            if old.action == StopAction::Brake {
                action = StopAction::Brake;
            }
            if lease.is_none() {
                // A brake applied again still ends the lease of the stop
                // it joins, and the motion of that lease's mode.
                lease = old.lease;
                reason = old.reason;
                mode = old.mode;
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
        let owner = lease.as_ref().map(|(_, owner, _)| owner.clone());
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
            brake: None,
        });
        self.note(Note::Stop {
            drive,
            owner,
            action,
            mode,
            ends_lease,
        });
    }

    pub(super) fn abandon_last(slot: &mut Slot) {
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

    /// Lease `id` on `drive` ended before its setpoint was settled, so a
    /// stop may have gone out first and the setpoint landed after it: the
    /// stop is sent again (after the try under way, if there is one). Its
    /// own stop, or the stop of a lease that replaced it: the setpoint of a
    /// replaced lease can land after that lease's stop as well. A lease on
    /// the drive now covers the motor; its end stops it.
    pub(super) fn stop_again(&mut self, drive: usize, id: LeaseId, now: Instant) {
        if self.shut_down {
            return;
        }
        let slot = self.slot(drive);
        if let Some(stop) = slot.stop.as_mut() {
            if stop.state == StopState::InFlight {
                stop.again = true;
            }
            return;
        }
        if slot.lease.is_some() {
            return;
        }
        let Some(Ended {
            id: ended,
            owner,
            holder,
            mode,
            how:
                How::Stopped {
                    reason,
                    action,
                    end: StopEnd::Done(_) | StopEnd::Superseded(_),
                },
            ..
        }) = slot.last.as_ref()
        else {
            // Released, ended by a brake (its guard sees to that), or left
            // to the safe stop.
            return;
        };
        if *ended < id {
            // Ended before this lease was granted: not its stop to repeat.
            return;
        }
        let lease = (*ended, owner.clone(), *holder);
        let (reason, action, mode) = (reason.clone(), *action, *mode);
        self.stop_ended_lease(drive, lease, reason, action, mode, now);
        if let Some(stop) = self.slot(drive).stop.as_mut() {
            // Its end was published with the first stop.
            stop.announced = true;
        }
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
            let orphan = slot.orphans.iter().position(|(o, _, _)| *o == id);
            if let Some(at) = orphan {
                let (_, seen, brake) = slot.orphans.swap_remove(at);
                match brake {
                    // A brake releases no brake; one that a write sent
                    // before it overtook (and took it over) is owed again.
                    Some(number) => {
                        let braking = self.slots.get(&drive).and_then(|s| s.stop.as_ref());
                        let covered = braking.is_some_and(|s| s.action == StopAction::Brake);
                        if self.stop_brake_back(drive, number, &report)
                            && !covered
                            && !self.shut_down
                        {
                            let by: Arc<str> = "a write sent before the stop's brake".into();
                            self.rebrake(drive, StopReason::BrakeReleased(by), now);
                        }
                    }
                    None if report.released_brake => {
                        self.released(drive, seen, &"a lease's stop".into(), now);
                    }
                    None => {}
                }
            }
            effects.extend(self.tick(now));
            return effects;
        }
        let Some(mut stop) = slot.stop.take() else {
            return effects;
        };
        let released = (report.released_brake && stop.brake.is_none()).then_some(stop.seen);
        // Its brake, if it sent one, overtaken by a write sent before it:
        // applied again once this stop is done.
        let overtaken = match stop.brake.take() {
            Some(number) => self.stop_brake_back(drive, number, &report),
            None => false,
        };
        let slot = self.slot(drive);
        let first = !stop.announced;
        let lease = stop.lease.clone();
        let mut finished = None;
        match &report.result {
            StopResult::Failed(error) => {
                let wait = backoff(retry_first, retry_max, stop.tries);
                stop.last_error = Some(error.to_string());
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
            _ if stop.again && !shut_down => {
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
            _ => {
                finished = Some(stop.action);
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
                            end: StopEnd::Done(report.text()),
                        };
                    }
                }
            }
        }
        if let Some(action) = finished {
            self.note(Note::StopEnded { drive });
            if action == StopAction::Brake {
                self.note_brake(drive, BrakeState::Confirmed);
            } else if report.released_brake {
                self.note_brake(drive, BrakeState::Off);
            }
        }
        if let Some(seen) = released {
            self.released(drive, seen, &"a lease's stop".into(), now);
        }
        if overtaken && finished.is_some() && !shut_down {
            let by: Arc<str> = "a write sent before the stop's brake".into();
            self.rebrake(drive, StopReason::BrakeReleased(by), now);
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
}

pub(super) fn backoff(first: Duration, max: Duration, tries: u32) -> Duration {
    let doublings = tries.saturating_sub(1).min(16);
    (first * 2u32.pow(doublings)).min(max)
}

/// What the stream shows as a stop's result: whether it was carried out,
/// and the drive's answer, or why not.
pub(super) fn shown(report: &StopReport) -> (bool, String) {
    match &report.result {
        StopResult::Confirmed if report.sent.is_some() => {
            (true, "confirmed by the drive".to_string())
        }
        _ => (report.is_ok(), report.text()),
    }
}

pub(super) fn expired(
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
        ok: result.0,
        result: result.1,
        retrying,
    }
}

pub(super) fn settled(
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
        stopped: result.0,
        attempts: stop.tries,
        result: result.1,
    }
}
