//! What the rules promise, kept apart from the core that keeps them: which
//! leases the clients hold and until when, who set each motor turning, the
//! brakes owed; and the invariants, checked against the drives and the
//! core after every step (docs/safety.md, "The invariant, checked by a
//! model").
//!
//! The spec's leases follow the documented rules, not the lease book's
//! code: a lease is taken when its write is queued, runs for its length
//! plus the bus allowance until its write is settled and for its length
//! from then on; a renewal, or for a communication-loss lease any request
//! of its session, runs it for its length from then; a brake confirmed (or
//! sent and not confirmed) ends it; a release, its session closing or its
//! time running out ends it. The core may end a lease sooner (the journal
//! keeps a deadline up to half a length early); never later.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::bus::SourceId;
use crate::control::LeaseView;
use crate::control::lease_book::RETRY_MAX;
use crate::control::outcome::Applied;
use crate::control::policy::Role;
use crate::control::stop_action::StopAction;
use crate::drive::Mode;

use super::bench::{Motion, Outcome, Served};

mod restart;
use super::steps::{Cmd, DRIVES, Damage, Setup, Who};

/// Whether a drive's unknown state at a start must survive a second start
/// before it answers (see [`Oracle::forget_unknown`]).
pub(super) const UNKNOWN_SURVIVES_RESTARTS: bool = false;

/// Slack for what happens at one instant in several steps of the core.
pub(super) const SLACK: Duration = Duration::from_millis(50);

/// The lease a write takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Terms {
    pub(super) length: Duration,
    pub(super) action: StopAction,
    pub(super) comm_loss: bool,
}

/// Where a request of a client stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    /// Being checked by the core.
    Asked,
    /// On the bus queue (its lease, if any, in place).
    Queued,
    /// Settled (or abandoned: the core settles it without its caller).
    Settled,
}

/// A write a client sent.
#[derive(Debug, Clone)]
pub(super) struct Req {
    pub(super) who: Who,
    pub(super) role: Role,
    pub(super) source: SourceId,
    pub(super) drive: usize,
    pub(super) cmd: Cmd,
    pub(super) pdu: Vec<u8>,
    /// The lease it takes when it is queued.
    pub(super) terms: Option<Terms>,
    /// The session generation it was sent in.
    pub(super) session: Option<u64>,
    /// Who holds its lease, as lease views show it.
    pub(super) owner: Arc<str>,
    stage: Stage,
    /// It replaced a lease on the drive when queued.
    replaced: bool,
    /// What the bus did with it.
    served: Option<Outcome>,
    /// Its caller went away before its result: the core settles it.
    abandoned: bool,
    /// Its lease was released (by a caller of this role) before it
    /// landed: it lands unguarded, as the release said.
    released: Option<Role>,
    /// When it was put on the queue, in the bus's order.
    sent: Option<Instant>,
    /// It did not come live (an MQTT command retained, queued or older
    /// than the connection): nothing of it may reach a drive.
    pub(super) stale: bool,
}

impl Req {
    /// A request of `who` (`role`, `source`) for `cmd` on `drive`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        who: Who,
        role: Role,
        source: SourceId,
        drive: usize,
        cmd: Cmd,
        pdu: Vec<u8>,
        terms: Option<Terms>,
        session: Option<u64>,
        owner: Arc<str>,
    ) -> Self {
        Req {
            who,
            role,
            source,
            drive,
            cmd,
            pdu,
            terms,
            session,
            owner,
            stage: Stage::Asked,
            replaced: false,
            served: None,
            abandoned: false,
            released: None,
            sent: None,
            stale: false,
        }
    }

    /// True for an explicit command that releases a brake.
    fn releases_brake(&self) -> bool {
        matches!(
            self.cmd,
            Cmd::Speed(_) | Cmd::Torque(_) | Cmd::SpeedMode | Cmd::TorqueMode
        )
    }

    /// True for a brake or deactivation: the core follows it to its end
    /// whoever waits for it.
    fn followed(&self) -> bool {
        matches!(self.cmd, Cmd::Brake | Cmd::Deactivate)
    }
}

/// A lease as the spec sees it.
#[derive(Debug, Clone)]
pub(super) struct Lease {
    /// The request that took it.
    pub(super) req: usize,
    pub(super) owner: Arc<str>,
    /// Its session (who, generation), if a session holds it.
    pub(super) session: Option<(Who, u64)>,
    pub(super) terms: Terms,
    /// It runs until then at the latest.
    pub(super) end: Instant,
    /// Its write was settled.
    pub(super) settled: bool,
}

/// Why a drive's motor may turn without a live lease.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Authority {
    /// Nothing set it turning (or it stands).
    None,
    /// A write with a lease set it turning: the lease must cover it.
    Leased,
    /// A write without a lease, from a caller of this role.
    Unleased(Role),
    /// Its lease was released (without a stop) by a caller of this role.
    Released(Role),
    /// Its lease ended with the action `none`, as configured.
    ActionNone,
    /// It was silent at a start that could not know who owned it, and a
    /// second start came before it answered: nobody knows any more (see
    /// [`Oracle::forget_unknown`]).
    Forgotten,
}

/// What the core shows of one drive, for the checks.
#[derive(Debug, Clone)]
pub(super) struct CoreDrive {
    pub(super) lease: Option<LeaseView>,
    pub(super) stopping: bool,
}

/// What the core shows, and the drives do, at a check.
pub(super) struct Look<'a> {
    pub(super) now: Instant,
    pub(super) core: &'a [CoreDrive],
    pub(super) motion: &'a [Motion],
    /// Whether each drive could not be reached lately.
    pub(super) troubled: &'a [bool],
    /// Whether each drive answers now.
    pub(super) reachable: &'a [bool],
}

/// A drive's leases and motion at a kill, for the restart's check.
#[derive(Debug, Clone)]
struct AtKill {
    lease: Option<Lease>,
    core: Option<LeaseView>,
    driven: bool,
    /// A brake to the drive was on its way: the journal says it may have
    /// been sent, and a restart applies it (ending the lease).
    brake_on_its_way: bool,
}

/// The rules' promises.
pub(super) struct Oracle {
    setup: Setup,
    allowance: Duration,
    pub(super) reqs: Vec<Req>,
    leases: [Option<Lease>; DRIVES],
    authority: [Authority; DRIVES],
    /// Each client's session generation while open.
    sessions: [Option<u64>; 7],
    generation: u64,
    /// The brake holding each drive: when it was sent.
    brake_sent: [Option<Instant>; DRIVES],
    /// A write sent before the brake holding the drive released it: the
    /// brake is owed again.
    rebrake: [bool; DRIVES],
    /// The last explicit command to release each drive's brake, from a
    /// caller allowed to: when it was sent.
    release_asked: [Option<Instant>; DRIVES],
    /// The request whose write set each drive's motor turning.
    motion_req: [Option<usize>; DRIVES],
    /// When drivegate's last stop of each drive began (its status read
    /// was sent): its writes follow.
    stop_began: [Option<Instant>; DRIVES],
    /// A drive that turned, silent at a start whose journal said nothing
    /// to trust: it gets `on_unknown_state` when it answers (unless a
    /// face's write reaches it first).
    unknown: [bool; DRIVES],
    kill: Option<(Instant, [AtKill; DRIVES])>,
    /// The journal's floor (its length when the bus last sent something)
    /// as last seen.
    floor: u64,
    /// The latest end each drive's lease had since the floor last moved:
    /// a journal torn after the floor may give a lease back with any of
    /// them (a shortening renewal, the settling of its write lost).
    torn_end: [Option<Instant>; DRIVES],
    /// Each drive's leases since the floor last moved, by owner, with the
    /// latest end each had.
    since_floor: [Vec<(Arc<str>, Instant)>; DRIVES],
    /// What a torn journal may give back after the last restart: those
    /// leases, each until its latest end.
    revivable: [Vec<(Arc<str>, Instant)>; DRIVES],
}

impl Oracle {
    /// The promises of a plant set up so, whose bus allows `allowance`
    /// for a write to be settled.
    pub(super) fn new(setup: Setup, allowance: Duration) -> Self {
        Oracle {
            setup,
            allowance,
            reqs: Vec::new(),
            leases: Default::default(),
            authority: [Authority::None; DRIVES],
            sessions: [None; 7],
            generation: 0,
            brake_sent: [None; DRIVES],
            rebrake: [false; DRIVES],
            release_asked: [None; DRIVES],
            motion_req: [None; DRIVES],
            stop_began: [None; DRIVES],
            unknown: [false; DRIVES],
            kill: None,
            floor: 0,
            torn_end: [None; DRIVES],
            since_floor: Default::default(),
            revivable: Default::default(),
        }
    }

    /// The lease a write of `who` for `cmd` takes, with `lease_ms` asked.
    pub(super) fn terms(&self, who: Who, cmd: Cmd, lease_ms: Option<u32>) -> Option<Terms> {
        let setpoint = matches!(cmd, Cmd::Speed(_) | Cmd::Torque(_));
        let mode = matches!(cmd, Cmd::SpeedMode | Cmd::TorqueMode);
        if let Some(ms) = lease_ms {
            return setpoint.then_some(Terms {
                length: Duration::from_millis(ms.into()),
                action: self.setup.on_lease_expiry,
                comm_loss: false,
            });
        }
        let (after, action) = self.setup.comm_loss_of(who)?;
        (setpoint || mode).then_some(Terms {
            length: Duration::from_millis(after.into()),
            action,
            comm_loss: true,
        })
    }

    /// Keeps the latest end of each drive's lease since the floor moved.
    pub(super) fn note_ends(&mut self) {
        for d in 0..DRIVES {
            let Some(lease) = &self.leases[d] else {
                continue;
            };
            let torn = &mut self.torn_end[d];
            *torn = Some(torn.map_or(lease.end, |t| t.max(lease.end)));
            let seen = &mut self.since_floor[d];
            match seen.iter_mut().find(|(owner, _)| *owner == lease.owner) {
                Some((_, end)) => *end = (*end).max(lease.end),
                None => seen.push((lease.owner.clone(), lease.end)),
            }
        }
    }

    /// `who`'s session opens: its generation.
    pub(super) fn open(&mut self, who: Who) -> u64 {
        self.generation += 1;
        self.sessions[who.index()] = Some(self.generation);
        self.generation
    }

    /// `who`'s session generation, if open.
    pub(super) fn session(&self, who: Who) -> Option<u64> {
        self.sessions[who.index()]
    }

    /// A request was put on the queue at `now` (in the bus's order at
    /// `sent`): its lease is in place.
    pub(super) fn queued(&mut self, id: usize, now: Instant, sent: Instant) {
        let req = &mut self.reqs[id];
        req.stage = Stage::Queued;
        req.sent = Some(sent);
        if req.releases_brake() && req.role.allows(Role::Operator) {
            let asked = &mut self.release_asked[req.drive];
            *asked = Some(asked.map_or(sent, |a| a.max(sent)));
        }
        let Some(terms) = req.terms else {
            return;
        };
        let d = req.drive;
        req.replaced = self.leases[d].is_some();
        let session = req.session.map(|g| (req.who, g));
        self.leases[d] = Some(Lease {
            req: id,
            owner: req.owner.clone(),
            session,
            terms,
            end: now + terms.length + self.allowance,
            settled: false,
        });
    }

    /// A request's result came back at `now` (or the core settled it for
    /// a caller that went away).
    pub(super) fn settled(&mut self, id: usize, applied: Applied, now: Instant) {
        let req = &mut self.reqs[id];
        if req.stage == Stage::Settled {
            return;
        }
        req.stage = Stage::Settled;
        let (d, cmd, replaced) = (req.drive, req.cmd, req.replaced);
        if let Some(lease) = self.leases[d].as_mut().filter(|l| l.req == id) {
            let closed = lease
                .session
                .is_some_and(|(who, g)| self.sessions[who.index()] != Some(g));
            if (applied == Applied::No && !replaced) || closed {
                self.end_lease(d, closed);
            } else if let Some(lease) = self.leases[d].as_mut() {
                lease.settled = true;
                lease.end = now + lease.terms.length;
            }
        }
        // A brake ends the leases granted before it was sent; one taken
        // after it releases it as asked.
        let sent = self.reqs[id].sent;
        let older = self.leases[d]
            .as_ref()
            .is_some_and(|l| self.reqs[l.req].sent < sent);
        match (cmd, applied) {
            (Cmd::Brake, Applied::Yes | Applied::Maybe) | (Cmd::Deactivate, Applied::Yes)
                if older =>
            {
                self.leases[d] = None;
            }
            _ => {}
        }
    }

    /// The bus took nothing of a request (its port down, its queue full)
    /// after its lease was taken: settled as never sent.
    pub(super) fn not_sent(&mut self, id: usize, now: Instant, sent: Instant) {
        self.queued(id, now, sent);
        self.reqs[id].served = Some(Outcome::Dropped);
        self.settled(id, Applied::No, now);
    }

    /// The core refused a request before sending it.
    pub(super) fn refused(&mut self, id: usize) {
        self.reqs[id].stage = Stage::Settled;
    }

    /// `who` renewed `drive`'s lease at `now` (with a new length).
    pub(super) fn renewed(
        &mut self,
        who: Who,
        role: Role,
        drive: usize,
        length: Option<Duration>,
        now: Instant,
    ) {
        let _ = who;
        if !role.allows(Role::Operator) {
            return;
        }
        if let Some(lease) = self.leases[drive].as_mut() {
            if let Some(length) = length {
                lease.terms.length = length;
            }
            let renewed = now + lease.terms.length;
            lease.end = if lease.settled {
                renewed
            } else {
                renewed.max(lease.end)
            };
        }
    }

    /// A caller of `role` released `drive`'s lease.
    pub(super) fn released(&mut self, role: Role, drive: usize) {
        if !role.allows(Role::Operator) {
            return;
        }
        if self.leases[drive].take().is_none() {
            return;
        }
        // What its writes still on their way set going is unguarded too.
        for req in &mut self.reqs {
            if req.drive == drive && req.terms.is_some() && req.served.is_none() {
                req.released = Some(role);
            }
        }
        if self.authority[drive] == Authority::Leased {
            self.authority[drive] = Authority::Released(role);
        }
    }

    /// A request came on `who`'s session at `now`.
    pub(super) fn active(&mut self, who: Who, now: Instant) {
        let generation = self.sessions[who.index()];
        for lease in self.leases.iter_mut().flatten() {
            if lease.terms.comm_loss
                && lease.session.map(|s| (s.0, Some(s.1))) == Some((who, generation))
            {
                let renewed = now + lease.terms.length;
                lease.end = if lease.settled {
                    renewed
                } else {
                    renewed.max(lease.end)
                };
            }
        }
    }

    /// `who` went away: its session closes, and its requests waiting for a
    /// result are settled by the core (as maybe carried out, unless the
    /// bus answered already).
    pub(super) fn gone(&mut self, who: Who, now: Instant) {
        for id in 0..self.reqs.len() {
            let req = &self.reqs[id];
            if req.who != who || req.stage != Stage::Queued || req.abandoned {
                continue;
            }
            self.reqs[id].abandoned = true;
            if self.reqs[id].followed() {
                continue;
            }
            let applied = match self.reqs[id].served {
                Some(outcome) => applied(outcome),
                None => Applied::Maybe,
            };
            self.settled(id, applied, now);
        }
        if self.sessions[who.index()].take().is_some() {
            for d in 0..DRIVES {
                if self.leases[d]
                    .as_ref()
                    .is_some_and(|l| l.session.is_some_and(|(w, _)| w == who))
                {
                    self.end_lease(d, true);
                }
            }
        }
    }

    /// Ends the leases that ran out by `now`.
    pub(super) fn expire(&mut self, now: Instant) {
        for d in 0..DRIVES {
            if self.leases[d].as_ref().is_some_and(|l| l.end <= now) {
                self.end_lease(d, true);
            }
        }
    }

    /// The lease on `d` ends; with its stop, unless its action is none.
    fn end_lease(&mut self, d: usize, with_stop: bool) {
        if let Some(lease) = self.leases[d].take()
            && with_stop
            && lease.terms.action == StopAction::None
            && self.authority[d] == Authority::Leased
        {
            self.authority[d] = Authority::ActionNone;
        }
    }

    /// What the bus did with a job: who set the motor turning, which brake
    /// holds, what a request came to. Returns what the job broke of the
    /// brake's rule, if anything.
    pub(super) fn served(&mut self, s: &Served) -> Option<String> {
        let d = s.drive;
        if s.floor != self.floor {
            self.floor = s.floor;
            self.torn_end = [None; DRIVES];
            self.since_floor = Default::default();
            self.note_ends();
        }
        let req = self.match_request(s);
        if s.source == SourceId::INTERNAL
            && s.request == Some(crate::drive::DriveRequest::ReadStatus)
        {
            self.stop_began[d] = Some(s.submitted);
        }
        if let Some(id) = req {
            if self.reqs[id].stale {
                return Some(format!(
                    "drive {d}: an MQTT command that did not come live ({:?}) was sent to the drive",
                    self.reqs[id].cmd
                ));
            }
            if s.outcome.landed() {
                self.unknown[d] = false;
            }
            let req = &mut self.reqs[id];
            req.served = Some(s.outcome);
            if req.abandoned && req.followed() && req.stage == Stage::Queued {
                self.settled(id, applied(s.outcome), s.at);
            }
        }
        if !s.outcome.landed() {
            return None;
        }
        let mut broken = None;
        if s.before.braking && !s.after.braking {
            broken = self.brake_released(s, req);
        } else if let Some(id) = req
            && self.reqs[id].releases_brake()
            && self.reqs[id].role.allows(Role::Operator)
            && self.brake_sent[d].is_none_or(|b| s.submitted > b)
        {
            // Sent after the brake: it releases it as asked, whatever a
            // write sent before the brake did.
            self.rebrake[d] = false;
        }
        if s.after.braking && !s.before.braking
            || matches!(
                s.request,
                Some(crate::drive::DriveRequest::Config(
                    crate::drive::ConfigCommand::EmergencyBrake
                ))
            )
        {
            self.brake_sent[d] = Some(s.submitted);
            self.rebrake[d] = false;
        }
        // Who set the motor turning.
        if !s.after.driven {
            self.authority[d] = Authority::None;
            self.motion_req[d] = None;
        } else if let Some(id) = req {
            let req = &self.reqs[id];
            let current_mode = s.after.setpoint.map(|(m, _)| m);
            let sets = match req.cmd {
                Cmd::Speed(_) => current_mode == Some(Mode::Speed),
                Cmd::Torque(_) => current_mode == Some(Mode::Torque),
                _ => false,
            };
            // A write that set it turning again (a brake released onto
            // the setpoint it held) owns its motion too. A setpoint of
            // another mode than the drive's sets no motion: the motor is
            // not its caller's (docs/safety.md, "What takes over a failing
            // stop").
            if sets || s.before.setpoint != s.after.setpoint || !s.before.driven {
                self.authority[d] = match (req.terms, req.released) {
                    (Some(_), Some(role)) => Authority::Released(role),
                    (Some(_), None) => Authority::Leased,
                    (None, _) => Authority::Unleased(req.role),
                };
                self.motion_req[d] = Some(id);
            }
        }
        broken
    }

    /// A job released drive `s.drive`'s brake. Allowed: an operator's
    /// setpoint or mode command; drivegate's own write (a lease's zero-speed
    /// stop) once such a command was sent after the brake (the command may
    /// have landed: its stop leaves the motor as the command and its stop
    /// would). A write sent before the brake (overtaken by it on the bus)
    /// has the brake owed again.
    fn brake_released(&mut self, s: &Served, req: Option<usize>) -> Option<String> {
        let d = s.drive;
        // A write of drivegate's belongs to the stop that read the drive
        // just before it: sent before the brake if that stop began before.
        let sent = match req {
            None => self.stop_began[d].map_or(s.submitted, |b| b.min(s.submitted)),
            Some(_) => s.submitted,
        };
        let before_brake = self.brake_sent[d].is_some_and(|b| sent < b);
        let asked = match (self.release_asked[d], self.brake_sent[d]) {
            (Some(asked), Some(brake)) => asked > brake,
            (Some(_), None) => true,
            (None, _) => false,
        };
        match req {
            Some(id) => {
                let r = &self.reqs[id];
                if !r.releases_brake() || !r.role.allows(Role::Operator) {
                    return Some(format!(
                        "drive {d}'s brake was released by {:?} from {:?} ({:?}), which may not",
                        r.cmd, r.who, r.role
                    ));
                }
                self.rebrake[d] = before_brake;
                None
            }
            None if before_brake => {
                self.rebrake[d] = true;
                None
            }
            None if asked => None,
            None => Some(format!(
                "drive {d}'s brake was released by drivegate itself: {:?} ({:?}) sent after the brake, and nobody asked for its release",
                s.request, s.origin
            )),
        }
    }

    /// The request a served job was sent for: the oldest of its caller
    /// with that PDU to that drive, not yet served (a caller's jobs of one
    /// class leave the queue in their order).
    fn match_request(&self, s: &Served) -> Option<usize> {
        if s.source == SourceId::INTERNAL {
            return None;
        }
        self.reqs.iter().position(|r| {
            r.source == s.source
                && r.drive == s.drive
                && r.pdu == s.pdu
                && r.sent.is_some()
                && r.served.is_none()
        })
    }

    /// Invariant 1 (and the brake owed again), at a check.
    pub(super) fn check(&mut self, look: &Look) -> Result<(), String> {
        for d in 0..DRIVES {
            let motion = look.motion[d];
            let core = &look.core[d];
            let stopping = (core.stopping || self.unknown[d]) && look.troubled[d];
            if self.unknown[d] && look.reachable[d] {
                self.unknown[d] = false;
                if motion.driven && !core.stopping {
                    return Err(format!(
                        "drive {d} was silent at a start with the safety journal unknown, and turned when it answered: not stopped (on_unknown_state)"
                    ));
                }
            }
            if self.rebrake[d] && !motion.braking && !stopping {
                return Err(format!(
                    "drive {d}: a write sent before its brake released it, and the brake was not applied again"
                ));
            }
            if !motion.driven {
                continue;
            }
            let covered = match (&self.leases[d], &core.lease) {
                (Some(spec), Some(shown)) => {
                    spec.end > look.now && look.now + shown.expires_in <= spec.end + SLACK
                }
                _ => false,
            };
            // A lease a torn journal gave back as it stood since the floor.
            let revived = core.lease.as_ref().is_some_and(|shown| {
                self.revivable[d].iter().any(|(owner, end)| {
                    *owner == shown.owner
                        && *end > look.now
                        && look.now + shown.expires_in <= *end + SLACK
                })
            });
            let covered = covered || revived;
            let allowed = match self.authority[d] {
                Authority::Unleased(role) | Authority::Released(role) => {
                    role.allows(Role::Operator)
                }
                Authority::ActionNone | Authority::Forgotten => true,
                Authority::None | Authority::Leased => false,
            };
            if !(covered || allowed || stopping) {
                return Err(format!(
                    "drive {d} turns at {:?} with no live owner: the spec's lease {:?}, the core's {:?}, set turning by {:?}, the core {} its stop",
                    motion.setpoint,
                    self.leases[d]
                        .as_ref()
                        .map(|l| (l.owner.clone(), l.end.saturating_duration_since(look.now))),
                    core.lease.as_ref().map(|l| (l.owner.clone(), l.expires_in)),
                    self.authority[d],
                    if core.stopping {
                        "is carrying out"
                    } else {
                        "is not carrying out"
                    },
                ));
            }
        }
        Ok(())
    }

    /// How long a drive's stop may be tried again before it goes once
    /// more.
    pub(super) fn retry_window() -> Duration {
        RETRY_MAX + SLACK
    }
}

/// What the core makes of a job's outcome.
fn applied(outcome: Outcome) -> Applied {
    match outcome {
        Outcome::Answered { refused: false } => Applied::Yes,
        Outcome::Answered { refused: true } | Outcome::Dropped => Applied::No,
        Outcome::LandedUnanswered | Outcome::Lost | Outcome::Killed => Applied::Maybe,
    }
}
