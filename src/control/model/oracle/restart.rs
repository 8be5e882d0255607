//! What a `kill -9` and the start after it owe, checked: every lease held
//! at the kill is back with its time or has had its stop, and with a
//! journal that says nothing to trust, every drive found turning gets
//! `on_unknown_state` (invariant 2).

use std::time::Instant;

use super::*;

impl Oracle {
    /// The process was killed at `now`, the journal left with `damage`:
    /// its sessions ended with it; the state at the kill is kept for the
    /// restart's check.
    pub(crate) fn killed(
        &mut self,
        now: Instant,
        damage: Damage,
        core: &[CoreDrive],
        motion: &[Motion],
    ) {
        if matches!(damage, Damage::Torn(_)) {
            for d in 0..DRIVES {
                self.torn(d);
            }
            self.revivable = self.since_floor.clone();
        } else {
            self.revivable = Default::default();
        }
        let at = std::array::from_fn(|d| AtKill {
            lease: self.leases[d].clone(),
            core: core[d].lease.clone(),
            driven: motion[d].driven,
            brake_on_its_way: self
                .reqs
                .iter()
                .any(|r| r.drive == d && r.cmd == Cmd::Brake && r.stage == Stage::Queued),
        });
        self.kill = Some((now, at));
        for req in &mut self.reqs {
            if req.stage != Stage::Settled {
                req.stage = Stage::Settled;
                req.abandoned = true;
            }
            // What waited in the queue died with the process: a job of
            // the next one is not it.
            if req.sent.is_some() && req.served.is_none() {
                req.served = Some(Outcome::Dropped);
            }
        }
        for who in Who::ALL {
            self.sessions[who.index()] = None;
        }
        for d in 0..DRIVES {
            if self.leases[d].as_ref().is_some_and(|l| l.session.is_some()) {
                self.end_lease(d, true);
            }
        }
    }

    /// A journal torn by the power cut may have lost the lease on `d`
    /// taken since the bus last sent something (its write was not sent):
    /// the lease under which the motor was set turning decides again, and
    /// if its action is none, the motor may go on.
    fn torn(&mut self, d: usize) {
        let unsent = self.leases[d].as_ref().is_some_and(|l| {
            self.reqs[l.req]
                .served
                .is_none_or(|o| o == Outcome::Dropped)
        });
        let motion_action = self.motion_req[d]
            .and_then(|id| self.reqs[id].terms)
            .map(|t| t.action);
        if unsent
            && self.authority[d] == Authority::Leased
            && motion_action == Some(StopAction::None)
        {
            self.authority[d] = Authority::ActionNone;
        }
    }

    /// Invariant 2, once the restart after the last kill has replayed the
    /// journal left with `damage`: every lease held at the kill is back
    /// with its time (an HTTP lease) or has had its stop, or the state
    /// being unknown, `on_unknown_state`.
    pub(crate) fn check_restart(&self, damage: Damage, look: &Look) -> Result<(), String> {
        let Some((killed_at, at)) = &self.kill else {
            return Ok(());
        };
        for (d, was) in at.iter().enumerate() {
            let now_core = &look.core[d].lease;
            let Some(lease) = &was.lease else {
                continue;
            };
            let back = now_core.as_ref().filter(|v| v.owner == lease.owner);
            if lease.session.is_some() {
                if back.is_some() {
                    return Err(format!(
                        "drive {d}: the lease of {} came back after the restart, though its session ended with the old process",
                        lease.owner
                    ));
                }
                continue;
            }
            // An HTTP lease: back with no more than the time promised.
            let promised = was
                .core
                .as_ref()
                .filter(|v| v.owner == lease.owner)
                .map(|v| killed_at.checked_add(v.expires_in));
            // A torn journal may give it back as it stood at any record
            // since the floor.
            let end = match (damage, self.torn_end[d]) {
                (Damage::Torn(_), Some(torn)) => lease.end.max(torn),
                _ => lease.end,
            };
            if let Some(back) = back
                && look.now + back.expires_in > end + SLACK
            {
                return Err(format!(
                    "drive {d}: {}'s lease came back with {:?} left, more than promised ({:?})",
                    lease.owner,
                    back.expires_in,
                    end.saturating_duration_since(look.now)
                ));
            }
            let Some(Some(promised)) = promised else {
                continue;
            };
            // The journal keeps a deadline at most half a length early (a
            // lease whose write was not settled: its length from the grant).
            let horizon = if lease.settled {
                lease.terms.length / 2
            } else {
                lease.terms.length / 2 + self.allowance
            };
            let kept = promised
                .checked_sub(horizon)
                .is_some_and(|k| k > look.now + SLACK);
            if damage == Damage::Intact
                && kept
                && back.is_none()
                && was.driven
                && !was.brake_on_its_way
            {
                return Err(format!(
                    "drive {d}: {}'s HTTP lease, promised for {:?} more, is not back after the restart",
                    lease.owner,
                    promised.saturating_duration_since(look.now)
                ));
            }
        }
        Ok(())
    }

    /// After a restart whose journal said nothing that can be trusted:
    /// every drive found turning at its first poll is stopped.
    pub(crate) fn check_unknown(&mut self, found: &[Motion], look: &Look) -> Result<(), String> {
        for (d, found) in found.iter().enumerate() {
            if !found.driven {
                continue;
            }
            if !look.reachable[d] {
                self.unknown[d] = true;
                continue;
            }
            if look.motion[d].driven && !(look.core[d].stopping && look.troubled[d]) {
                return Err(format!(
                    "drive {d} turned at the start with the safety journal unknown, and was not stopped (on_unknown_state)"
                ));
            }
        }
        Ok(())
    }

    /// After the restart's checks, the drives found turning are no
    /// longer the kill's concern.
    pub(crate) fn restarted(&mut self) {
        self.kill = None;
        self.torn_end = [None; DRIVES];
        self.since_floor = Default::default();
        self.note_ends();
    }

    /// A start forgets what an earlier start could not decide: a drive
    /// silent at a start whose journal was unknown is decided at its first
    /// answer, and the journal keeps no mark of that, so a second start
    /// before it answers does not know it either (a limit of the journal's
    /// format, docs/safety.md). Unless [`UNKNOWN_SURVIVES_RESTARTS`].
    pub(crate) fn forget_unknown(&mut self) {
        if !UNKNOWN_SURVIVES_RESTARTS {
            for d in 0..DRIVES {
                if std::mem::take(&mut self.unknown[d]) {
                    self.authority[d] = Authority::Forgotten;
                }
            }
        }
    }
}
