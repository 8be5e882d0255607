//! The drives and the bus the core talks to in the model.
//!
//! The drives are the simulator's own drive model (`sim::model`, through
//! its Modbus slave `sim::slave`): its registers, its CONFIG commands, its
//! refusals (a setpoint to a drive that is not active), its brake (held
//! until a setpoint or a mode command releases it). Its physics is not
//! run: a motor turns when its drive drives it at a setpoint that is not
//! zero, at once, and a status read says so. Ramps and inertia are not
//! what the rules are about, and a millisecond physics step for every
//! simulated second would cost the suite most of its cases.
//!
//! The bus is a real `BusHandle` (its queue, its status cache, its events)
//! with no scheduler behind it: the bench takes the jobs off the queue in
//! the scheduler's order (emergency first, round robin between callers),
//! drops those whose caller went away, and answers each one, with the
//! faults the steps inject: a silent drive, requests or replies lost, bad
//! CRCs, the bus held or its port down.

use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

use crate::bus::fault::Fault;
use crate::bus::handle::PortState;
use crate::bus::job::{Exchange, Job};
use crate::bus::{BusError, BusHandle, Origin, Priority, SourceId};
use crate::drive::writes::{self, PduMeaning};
use crate::drive::{ConfigCommand, DriveRequest, Mode, Status};
use crate::modbus::function::READ_HOLDING_REGISTERS;
use crate::sim::model::DriveModel;
use crate::sim::slave;

use super::steps::{DRIVES, Trouble};

/// The bus's retries (one retry: two attempts).
pub(super) const ATTEMPTS: u8 = 2;
/// The bus's response timeout, ms.
pub(super) const TIMEOUT_MS: u64 = 100;

/// What a drive's motor does, as far as the rules are concerned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Motion {
    /// The drive drives the motor at a setpoint that is not zero.
    pub(super) driven: bool,
    /// Its emergency brake is engaged.
    pub(super) braking: bool,
    /// The mode and setpoint it is driven at (when driven).
    pub(super) setpoint: Option<(Mode, i16)>,
}

/// How a job ended on the bench.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Outcome {
    /// The drive carried it out and answered (perhaps with an exception).
    Answered { refused: bool },
    /// The drive carried it out; its reply was lost or garbled.
    LandedUnanswered,
    /// It never reached the drive; nothing came back.
    Lost,
    /// Dropped unsent: its caller had gone away, or the port went down.
    Dropped,
    /// The process died with it on the wire: the drive carried it out.
    Killed,
}

impl Outcome {
    /// True when the drive carried it out.
    pub(super) fn landed(self) -> bool {
        matches!(
            self,
            Outcome::Answered { refused: false } | Outcome::LandedUnanswered | Outcome::Killed
        )
    }
}

/// One job as the bench served it.
#[derive(Debug, Clone)]
pub(super) struct Served {
    /// When (the core's clock).
    pub(super) at: Instant,
    /// Whose turn it took.
    pub(super) source: SourceId,
    /// Why it was sent (a lease's stop, a brake applied again, a face).
    pub(super) origin: Origin,
    /// When it was put on the queue: the order writes were sent in.
    pub(super) submitted: Instant,
    /// The drive.
    pub(super) drive: usize,
    /// The request PDU.
    pub(super) pdu: Vec<u8>,
    /// The message it is, if it is one.
    pub(super) request: Option<DriveRequest>,
    /// What became of it.
    pub(super) outcome: Outcome,
    /// The drive's motor before and after.
    pub(super) before: Motion,
    pub(super) after: Motion,
    /// The journal's length when the bus last sent something, as of this
    /// job (what a torn journal keeps at least).
    pub(super) floor: u64,
}

/// A drive's trouble now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ailment {
    Fine,
    Dead(Instant),
    LostRequests(u8),
    LostReplies(u8),
    BadCrc(u8),
}

/// The drives and the bus.
pub(super) struct Bench {
    drives: Vec<DriveModel>,
    ailments: Vec<Ailment>,
    /// The bus carries nothing until then.
    held_until: Option<Instant>,
    /// The port is down until then.
    down_until: Option<Instant>,
    /// The last moment each drive could not be reached (a fault, the bus
    /// held or down).
    trouble: Vec<Option<Instant>>,
    /// What was served since the last look.
    served: Vec<Served>,
    /// The journal file of the running process, and its length when the
    /// bus last sent something: what was written after may be torn by a
    /// power cut (its writes were not sent yet).
    journal: Option<PathBuf>,
    journal_floor: u64,
}

impl Bench {
    /// Drives 1 to `DRIVES`, in speed mode; those `active` activated.
    pub(super) fn new(active: [bool; DRIVES]) -> Self {
        let mut drives = Vec::new();
        for (i, active) in active.iter().enumerate() {
            let mut d = DriveModel::new(unit(i), 1.0, true, 0.0);
            let mut scratch = Vec::new();
            let mut command = |c: ConfigCommand| {
                if let Ok(pdu) = DriveRequest::Config(c).pdu() {
                    slave::answer(&mut d, &pdu, &mut scratch);
                }
            };
            command(ConfigCommand::SpeedMode);
            if *active {
                command(ConfigCommand::Activate);
            }
            drives.push(d);
        }
        Bench {
            drives,
            ailments: vec![Ailment::Fine; DRIVES],
            held_until: None,
            down_until: None,
            trouble: vec![None; DRIVES],
            served: Vec::new(),
            journal: None,
            journal_floor: 0,
        }
    }

    /// What drive `d`'s motor does.
    pub(super) fn motion(&self, d: usize) -> Motion {
        motion(&self.drives[d])
    }

    /// The jobs served since the last call.
    pub(super) fn take_served(&mut self) -> Vec<Served> {
        std::mem::take(&mut self.served)
    }

    /// The journal the running process writes.
    pub(super) fn follow_journal(&mut self, path: PathBuf) {
        self.journal_floor = std::fs::metadata(&path).map_or(0, |m| m.len());
        self.journal = Some(path);
    }

    /// The journal's length when the bus last sent something.
    pub(super) fn journal_floor(&self) -> u64 {
        self.journal_floor
    }

    /// Drive `d` misbehaves from `now` on.
    pub(super) fn inject(&mut self, d: usize, trouble: Trouble, now: Instant) {
        self.ailments[d] = match trouble {
            Trouble::Dead(ms) => Ailment::Dead(now + Duration::from_millis(ms.into())),
            Trouble::LostRequests(n) => Ailment::LostRequests(n),
            Trouble::LostReplies(n) => Ailment::LostReplies(n),
            Trouble::BadCrc(n) => Ailment::BadCrc(n),
        };
    }

    /// The bus carries nothing until `until`.
    pub(super) fn hold(&mut self, until: Instant) {
        self.held_until = Some(self.held_until.map_or(until, |u| u.max(until)));
    }

    /// The port fails until `until`: the jobs waiting fail unsent.
    pub(super) fn port_down(&mut self, handle: &BusHandle, until: Instant, now: Instant) {
        self.down_until = Some(self.down_until.map_or(until, |u| u.max(until)));
        set_port(handle, false);
        for job in handle.shared.queue.drain() {
            self.finish_unsent(job, now);
        }
    }

    /// When something the bench waits for happens next (a drive comes
    /// back, the bus is free again, the port reopens).
    pub(super) fn next_change(&self) -> Option<Instant> {
        let dead = self.ailments.iter().filter_map(|a| match a {
            Ailment::Dead(until) => Some(*until),
            _ => None,
        });
        dead.chain(self.held_until).chain(self.down_until).min()
    }

    /// Ends what ended by `now`: the port reopens, the hold ends, drives
    /// come back.
    pub(super) fn catch_up(&mut self, handle: &BusHandle, now: Instant) {
        if self.held_until.is_some_and(|u| u <= now) {
            self.held_until = None;
        }
        if self.down_until.is_some_and(|u| u <= now) {
            self.down_until = None;
            set_port(handle, true);
        }
        for a in &mut self.ailments {
            if matches!(a, Ailment::Dead(until) if *until <= now) {
                *a = Ailment::Fine;
            }
        }
        for d in 0..DRIVES {
            if self.unreachable(d) {
                self.trouble[d] = Some(now);
            }
        }
    }

    /// True while drive `d` cannot be reached at all.
    pub(super) fn unreachable(&self, d: usize) -> bool {
        self.held_until.is_some()
            || self.down_until.is_some()
            || matches!(self.ailments[d], Ailment::Dead(_))
    }

    /// True when drive `d` could not be reached, or a request to it
    /// failed, within `window` before `now`.
    pub(super) fn troubled(&self, d: usize, now: Instant, window: Duration) -> bool {
        self.unreachable(d) || self.trouble[d].is_some_and(|t| now <= t + window)
    }

    /// A new process opens its bus: a hold of the old one's is over.
    pub(super) fn reopen(&mut self) {
        self.held_until = None;
    }

    /// A new process opened its bus: the port is up (unless it is down).
    pub(super) fn attach(&self, handle: &BusHandle) {
        set_port(handle, self.down_until.is_none());
    }

    /// The poller's round: every drive's status into the cache (or its
    /// silence). True when a drive came online or went offline.
    pub(super) fn poll(&mut self, handle: &BusHandle, now: Instant) -> bool {
        if self.held_until.is_some() {
            return false;
        }
        let mut changed = false;
        for d in 0..DRIVES {
            let cache = &handle.shared.cache;
            let was = handle.drive(unit(d)).map(|s| s.link);
            if self.unreachable(d) {
                self.trouble[d] = Some(now);
                cache.record_failure(unit(d), "no answer");
            } else {
                cache.record_status(unit(d), status(&self.drives[d]));
            }
            changed |= handle.drive(unit(d)).map(|s| s.link) != was;
        }
        changed
    }

    /// Serves the next job, if the bus carries one now; false when there
    /// is none.
    pub(super) fn serve_one(&mut self, handle: &BusHandle, now: Instant) -> bool {
        if self.held_until.is_some() || self.down_until.is_some() {
            return false;
        }
        let queue = &handle.shared.queue;
        let Some(job) = queue
            .pop(Priority::Emergency)
            .or_else(|| queue.pop(Priority::Command))
        else {
            return false;
        };
        self.serve(job, now, false);
        true
    }

    /// The process dies with the next job on the wire: the drive carries
    /// it out, its caller never learns it.
    pub(super) fn kill_on_wire(&mut self, handle: &BusHandle, now: Instant) {
        if self.held_until.is_some() || self.down_until.is_some() {
            return;
        }
        let queue = &handle.shared.queue;
        if let Some(job) = queue
            .pop(Priority::Emergency)
            .or_else(|| queue.pop(Priority::Command))
        {
            self.serve(job, now, true);
        }
    }

    /// The process died: its queue takes nothing more, what waits in it is
    /// lost.
    pub(super) fn abandon(handle: &BusHandle) {
        for job in handle.shared.queue.stop() {
            job.finish(Err(BusError::ShuttingDown));
        }
    }

    fn finish_unsent(&mut self, job: Job, now: Instant) {
        if let Some(d) = drive_of(job.unit) {
            let motion = self.motion(d);
            self.record(&job, d, now, Outcome::Dropped, motion, motion);
        }
        let bus = "line".to_string();
        job.finish(Err(BusError::BusDown {
            bus,
            reason: "the port failed".to_string().into(),
        }));
    }

    fn serve(&mut self, job: Job, now: Instant, killed: bool) {
        if let Some(path) = &self.journal {
            self.journal_floor = std::fs::metadata(path).map_or(0, |m| m.len());
        }
        let Some(d) = drive_of(job.unit) else {
            let unit = job.unit;
            job.finish(Err(timeout(unit)));
            return;
        };
        let before = self.motion(d);
        if job.reply.is_closed() && !killed {
            // Its caller went away: the scheduler drops it unsent.
            self.record(&job, d, now, Outcome::Dropped, before, before);
            return;
        }
        let ailment = self.ailments[d];
        let lands = match ailment {
            Ailment::Fine | Ailment::LostReplies(_) | Ailment::BadCrc(_) => true,
            Ailment::Dead(_) | Ailment::LostRequests(_) => false,
        };
        self.ailments[d] = match ailment {
            Ailment::LostRequests(n) if n > 1 => Ailment::LostRequests(n - 1),
            Ailment::LostReplies(n) if n > 1 => Ailment::LostReplies(n - 1),
            Ailment::BadCrc(n) if n > 1 => Ailment::BadCrc(n - 1),
            Ailment::LostRequests(_) | Ailment::LostReplies(_) | Ailment::BadCrc(_) => {
                Ailment::Fine
            }
            other => other,
        };
        if ailment != Ailment::Fine {
            self.trouble[d] = Some(now);
        }
        let mut reply = Vec::new();
        let mut refused = false;
        if lands {
            if job.pdu.first() == Some(&READ_HOLDING_REGISTERS)
                && Ok(&job.pdu) == DriveRequest::ReadStatus.pdu().as_ref()
            {
                let bytes = status(&self.drives[d]).to_bytes();
                reply.push(READ_HOLDING_REGISTERS);
                reply.push(bytes.len() as u8);
                reply.extend_from_slice(&bytes);
            } else {
                refused = slave::answer(&mut self.drives[d], &job.pdu, &mut reply).is_some();
            }
        }
        let after = self.motion(d);
        let outcome = match (killed, ailment, lands) {
            (true, _, true) => Outcome::Killed,
            (true, _, false) => Outcome::Lost,
            (false, Ailment::Fine, _) => Outcome::Answered { refused },
            (false, _, true) => Outcome::LandedUnanswered,
            (false, _, false) => Outcome::Lost,
        };
        self.record(&job, d, now, outcome, before, after);
        if killed {
            return;
        }
        let result = match ailment {
            Ailment::Fine => Ok(Exchange {
                reply,
                attempts: 1,
                queued: Duration::ZERO,
                on_wire: Duration::ZERO,
            }),
            Ailment::BadCrc(_) => Err(BusError::BadReply {
                unit: job.unit,
                attempts: ATTEMPTS,
                fault: Fault::Crc,
            }),
            _ => Err(timeout(job.unit)),
        };
        job.finish(result);
    }

    fn record(
        &mut self,
        job: &Job,
        d: usize,
        now: Instant,
        outcome: Outcome,
        before: Motion,
        after: Motion,
    ) {
        let request = match writes::decode(&job.pdu) {
            PduMeaning::Message(r) => Some(r),
            _ if Ok(&job.pdu) == DriveRequest::ReadStatus.pdu().as_ref() => {
                Some(DriveRequest::ReadStatus)
            }
            _ => None,
        };
        self.served.push(Served {
            at: now,
            source: job.source,
            origin: job.origin.clone(),
            submitted: job.submitted,
            drive: d,
            pdu: job.pdu.clone(),
            request,
            outcome,
            before,
            after,
            floor: self.journal_floor,
        });
    }
}

/// The unit of drive `d`.
pub(super) fn unit(d: usize) -> u8 {
    u8::try_from(d + 1).unwrap_or(u8::MAX)
}

fn drive_of(unit: u8) -> Option<usize> {
    let d = usize::from(unit).checked_sub(1)?;
    (d < DRIVES).then_some(d)
}

fn timeout(unit: u8) -> BusError {
    BusError::Timeout {
        unit,
        attempts: ATTEMPTS,
        timeout_ms: TIMEOUT_MS,
    }
}

fn set_port(handle: &BusHandle, up: bool) {
    let since = SystemTime::now();
    handle.shared.set_state(if up {
        PortState::Up { since }
    } else {
        PortState::Down {
            since,
            reason: "the adapter failed".to_string(),
        }
    });
    handle.shared.cache.record_port(up, "the adapter failed");
}

fn motion(d: &DriveModel) -> Motion {
    let v = d.view();
    let setpoint = match v.mode {
        Mode::Speed => Some((Mode::Speed, v.setpoints.speed_rpm)),
        Mode::Torque => Some((Mode::Torque, v.setpoints.current_counts)),
        Mode::Position | Mode::OpenLoop => None,
    };
    let driving = v.online
        && v.active
        && !v.braking
        && v.rs485_control
        && !v.stalled
        && v.procedure.is_none()
        && v.fault == crate::drive::Fault::None;
    let setpoint = setpoint.filter(|(_, value)| driving && *value != 0);
    Motion {
        driven: setpoint.is_some(),
        braking: v.braking,
        setpoint,
    }
}

/// What a status read of the drive says: its flags, and its motor at its
/// setpoint.
fn status(d: &DriveModel) -> Status {
    let mut s = d.status();
    let m = motion(d);
    s.speed_rpm = match m.setpoint {
        Some((Mode::Speed, rpm)) => rpm,
        _ => 0,
    };
    s.current_counts = match m.setpoint {
        Some((Mode::Torque, counts)) => counts,
        _ => 0,
    };
    s
}
