//! The write path: the checks a write needs before it is sent, the lease
//! and brake bookkeeping around it, the bus job, and the settling of its
//! result (leases, audit, events), the same for every face.
//!
//! [`Control::submit`] returns once the write is on the bus queue, so a
//! face that pipelines (Modbus TCP) keeps its client's order; the
//! [`Pending`] it returns yields the typed result. A pending write dropped
//! before its result is settled all the same: a queued job is dropped
//! unsent (the client went away), and a brake or deactivation is followed
//! to its end whoever waits for it, since leases depend on it.

use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use tokio::sync::oneshot;
use tokio::sync::oneshot::error::TryRecvError;

use super::audit;
use super::caller::Caller;
use super::events::{ControlEvent, WriteEnd, WriteEvent};
use super::lease_book::{Grant, Holder, LeaseAsk, Ticket, WriteKind};
use super::live;
use super::outcome::{Applied, Failure, Outcome, WriteResult, applied};
use super::parts::Parts;
use super::policy::{Meaning, Stopper};
use super::request::Target;
use super::request::{ControlRequest, Write};
use super::rules::{self, Activity, Decision, Facts, Need, Speed};
use crate::bus::cache::Link;
use crate::bus::handle::JobOptions;
use crate::bus::job::JobResult;
use crate::bus::{BusError, BusHandle, Priority};
use crate::drive::{DriveReply, DriveRequest, ReplyError, Status};
use crate::modbus::ExceptionCode;
use crate::modbus::function::EXCEPTION_BIT;

/// What the audit log says of a write whose caller went away first.
const GONE: &str = "the client went away before the drive answered; a request already on the wire was carried out, a queued one was dropped";

/// Checks `request` for `caller`, puts it on the bus queue, and
/// returns the way to its result. A refusal, a failed check or a bus
/// that takes nothing is settled (audited) and returned at once.
pub(super) async fn submit(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    request: ControlRequest,
) -> Result<Pending, Failure> {
    let meaning = request.meaning();
    let mut settle = Settle::new(parts, caller, target, &request.write);
    if let Err(refusal) = check(parts, caller, target, &request, &meaning).await {
        return Err(settle.failed(refusal));
    }
    let pdu = match request.write.encode() {
        Ok(pdu) => pdu,
        Err(e) => return Err(settle.failed(Failure::NotSent(BusError::Invalid(e.to_string())))),
    };
    let bus = match parts.bus(target) {
        Ok(bus) => bus,
        Err(e) => return Err(settle.failed(Failure::NotSent(e))),
    };
    // Its wait for the bus counts from when its face received it: one
    // that waited as long as the bus lets a job wait is not sent. A brake
    // or a deactivation goes whenever it comes: it moves nothing.
    let received = request.received.filter(|_| !meaning.survives_caller());
    let queue_timeout = match live::queue_wait(received, Instant::now(), bus.queue_timeout()) {
        Ok(left) => left,
        Err(late) => {
            return Err(settle.failed(Failure::NotSent(BusError::Expired {
                waited: late.waited,
            })));
        }
    };
    // The lease is in place, and the brake guard knows of the write,
    // before it can reach the wire.
    settle.tickets = tickets(parts, caller, target, &request, &meaning);
    let options = JobOptions {
        priority: if meaning.emergency {
            Priority::Emergency
        } else {
            Priority::Command
        },
        source: caller.source,
        queue_timeout: Some(queue_timeout),
        max_attempts: None,
        origin: caller.origin.clone(),
    };
    match bus.submit(target.unit, pdu, options) {
        Ok(rx) => Ok(Pending {
            settle: Some(settle),
            state: State::Waiting(rx),
            follow: meaning.survives_caller(),
        }),
        Err(e) => Err(settle.failed(Failure::NotSent(e))),
    }
}

/// [`submit`], then waits for the result.
pub(super) async fn write(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    request: ControlRequest,
) -> WriteResult {
    let mut pending = submit(parts, caller, target, request).await?;
    pending.wait().await;
    pending.finish()
}

/// Reads the drive's status now (not from the poll cache), with the
/// caller's turn on the bus.
pub(super) async fn read_status(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
) -> Result<Status, BusError> {
    let bus = parts.bus(target)?;
    read(&bus, caller, target.unit).await
}

/// The rules checked before a write is sent ([`rules::decide`]), with
/// the facts they ask for gathered here.
async fn check(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    request: &ControlRequest,
    meaning: &Meaning,
) -> Result<(), Failure> {
    // What costs nothing first (a write nobody can decode, the role):
    // a caller they refuse costs no bus time.
    rules::admit(caller, meaning, request, target).map_err(Failure::Refused)?;
    let bus = parts.bus(target).map_err(Failure::NotSent)?;
    let mut facts = facts(parts, target, &bus);
    loop {
        match rules::decide(caller, meaning, request, target, &facts) {
            Err(refusal) => return Err(Failure::Refused(refusal)),
            Ok(Decision::Send { forced }) => {
                if let Some(still) = meaning.still {
                    for speed in forced {
                        audit::forced(
                            caller.face.name(),
                            &caller.who,
                            &speed.name,
                            still.what(),
                            speed.rpm,
                        );
                    }
                }
                return Ok(());
            }
            Ok(Decision::Read(Need::Active)) => {
                facts.active = Some(activity(&bus, caller, target).await?);
            }
            Ok(Decision::Read(Need::Speeds)) => {
                facts.speeds = Some(speeds(parts, &bus, caller, target, request.force).await?);
            }
        }
    }
}

/// The rules of every write of `requests` to `target`, decided before
/// any of them is sent, with the facts gathered once: several writes
/// that make one operation (a settings document) are refused whole,
/// before the first goes out. Nothing is audited here: each write is
/// checked again, and audited, when it is sent.
pub(super) async fn check_all(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    requests: &[ControlRequest],
) -> Result<(), Failure> {
    let bus = parts.bus(target).map_err(Failure::NotSent)?;
    let mut facts = facts(parts, target, &bus);
    for request in requests {
        let meaning = request.meaning();
        rules::admit(caller, &meaning, request, target).map_err(Failure::Refused)?;
        loop {
            match rules::decide(caller, &meaning, request, target, &facts) {
                Err(refusal) => return Err(Failure::Refused(refusal)),
                Ok(Decision::Send { .. }) => break,
                Ok(Decision::Read(Need::Active)) => {
                    facts.active = Some(activity(&bus, caller, target).await?);
                }
                Ok(Decision::Read(Need::Speeds)) => {
                    facts.speeds = Some(speeds(parts, &bus, caller, target, request.force).await?);
                }
            }
        }
    }
    Ok(())
}

/// What the rules know of `target` before anything is read.
fn facts(parts: &Arc<Parts>, target: Target, bus: &BusHandle) -> Facts {
    Facts {
        name: parts.name(target),
        bus: bus.name().to_string(),
        drives_on_bus: parts
            .plant()
            .drives()
            .iter()
            .filter(|d| d.bus == target.bus)
            .count(),
        lease_bounds: parts.lease_bounds(),
        active: None,
        speeds: None,
    }
}

/// Whether the drive a setpoint goes to is active. The poll cache may
/// predate an activation sent a moment ago, so an inactive cached
/// status is confirmed with a fresh read.
async fn activity(bus: &BusHandle, caller: &Caller, target: Target) -> Result<Activity, Failure> {
    match bus.drive(target.unit).and_then(|s| s.status) {
        Some(s) if s.active() => return Ok(Activity::Active),
        // Never polled (or not configured): the drive decides.
        None => return Ok(Activity::Unknown),
        Some(_) => {}
    }
    let status = read(bus, caller, target.unit)
        .await
        .map_err(Failure::CheckFailed)?;
    Ok(if status.active() {
        Activity::Active
    } else {
        Activity::Inactive
    })
}

/// The speed of every drive a write that needs standstill reaches. The
/// drive is read now: such writes are rare and the cache may be a poll
/// old. A broadcast reads every configured drive of the bus that
/// answers (one that does not is not there to move).
async fn speeds(
    parts: &Arc<Parts>,
    bus: &BusHandle,
    caller: &Caller,
    target: Target,
    force: bool,
) -> Result<Vec<Speed>, Failure> {
    let units: Vec<u8> = if target.unit == 0 {
        parts
            .plant()
            .now()
            .drives()
            .filter(|d| d.bus == target.bus)
            .filter(|d| bus.drive(d.unit).is_none_or(|s| s.link != Link::Offline))
            .map(|d| d.unit)
            .collect()
    } else {
        vec![target.unit]
    };
    let mut speeds = Vec::with_capacity(units.len());
    for unit in units {
        let status = match read(bus, caller, unit).await {
            Ok(s) => s,
            Err(_) if target.unit == 0 => continue,
            Err(e) => return Err(Failure::CheckFailed(e)),
        };
        speeds.push(Speed {
            name: parts.name(parts.unit_target(target.bus, unit)),
            rpm: status.speed_rpm,
        });
        // The first drive that turns decides, unless overridden: the
        // others need not be read.
        if status.speed_rpm != 0 && !force {
            break;
        }
    }
    Ok(speeds)
}

/// The lease and brake bookkeeping of a write about to be sent: one
/// ticket per configured drive it reaches (every drive of the bus for a
/// broadcast), with the lease granted for a setpoint.
fn tickets(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    request: &ControlRequest,
    meaning: &Meaning,
) -> Vec<Ticket> {
    let drives: Vec<usize> = if target.unit == 0 {
        parts
            .plant()
            .now()
            .indexed_drives()
            .filter(|(_, d)| d.bus == target.bus)
            .map(|(i, _)| i)
            .collect()
    } else {
        target.drive.into_iter().collect()
    };
    let Some(kind) = write_kind(meaning) else {
        return Vec::new();
    };
    let allowance = allowance(parts, target.bus);
    // A broadcast setpoint moves only the drives that are active: the
    // others refuse it, and would refuse the stop of a lease too.
    // Read before the book is locked: the poll cache has its own lock.
    let active = active_drives(parts, target, &drives);
    let leases = parts.leases();
    leases.with(|book, now| {
        // The lease asked for (a setpoint's over HTTP or the stream),
        // else the session's communication-loss lease, if it has one.
        let terms = book.terms(caller.session, request.lease, request.lease_action);
        let by: std::sync::Arc<str> = match meaning.stops {
            Some(stopper) => format!("{} from {}", stopper.name(), caller.describe()),
            None if meaning.setpoint.is_some() && terms.is_none() => {
                format!("a setpoint without a lease from {}", caller.describe())
            }
            None => format!("a write from {}", caller.describe()),
        }
        .into();
        let mut effects = Vec::new();
        let tickets = drives
            .iter()
            .map(|&drive| {
                // What the lease covers: a setpoint, or a mode command
                // under communication loss; a broadcast takes one per
                // active drive, only for communication loss.
                let mode = match kind {
                    WriteKind::Setpoint { mode, .. } => Some(mode),
                    WriteKind::ReleasesBrake { .. } if terms.is_some_and(|t| t.comm_loss) => {
                        meaning.mode
                    }
                    _ => None,
                };
                let grant = match (mode, terms) {
                    (Some(mode), Some(terms))
                        if target.unit != 0 || (terms.comm_loss && active.contains(&drive)) =>
                    {
                        let ask = LeaseAsk {
                            owner: caller.owner(),
                            holder: caller.session.map_or(Holder::Request, Holder::Session),
                            mode,
                            length: terms.length,
                            allowance,
                            action: terms.action,
                            comm_loss: terms.comm_loss,
                        };
                        let (grant, e): (Grant, _) = book.grant(drive, ask, now);
                        effects.extend(e);
                        Some(grant)
                    }
                    _ => None,
                };
                let kind = match kind {
                    WriteKind::Setpoint { mode, .. } => WriteKind::Setpoint { lease: grant, mode },
                    WriteKind::ReleasesBrake { .. } => WriteKind::ReleasesBrake { lease: grant },
                    other => other,
                };
                book.begin_write(drive, kind, by.clone())
            })
            .collect();
        (tickets, effects)
    })
}

/// What the lease book must know of a write of `meaning` (none: nothing).
fn write_kind(meaning: &Meaning) -> Option<WriteKind> {
    match (meaning.stops, meaning.setpoint) {
        (Some(Stopper::Brake), _) => Some(WriteKind::Brake),
        (Some(Stopper::Deactivate), _) => Some(WriteKind::Deactivate),
        (None, Some(mode)) => Some(WriteKind::Setpoint { lease: None, mode }),
        (None, None) if meaning.releases_brake => Some(WriteKind::ReleasesBrake { lease: None }),
        (None, None) => None,
    }
}

/// Of `drives`, those a broadcast to `target` reaches active (none for a
/// write to one unit), from the poll cache.
fn active_drives(parts: &Arc<Parts>, target: Target, drives: &[usize]) -> Vec<usize> {
    let now = parts.plant().now();
    drives
        .iter()
        .copied()
        .filter(|_| target.unit == 0)
        .filter(|&drive| {
            now.drive_at(drive)
                .and_then(|d| now.handle_of(d)?.drive(d.unit))
                .and_then(|s| s.status)
                .is_some_and(|s| s.active())
        })
        .collect()
}

/// How long a write on bus `bus` may take to be settled: the queue
/// wait and every attempt's timeout, with a margin.
fn allowance(parts: &Arc<Parts>, bus: usize) -> Duration {
    parts
        .plant()
        .now()
        .bus_at(bus)
        .map_or(Duration::from_secs(10), |b| {
            let c = &b.config;
            let per_attempt = c.response_timeout_ms + c.guard_ms.unwrap_or(c.response_timeout_ms);
            Duration::from_millis(c.queue_timeout_ms)
                + Duration::from_millis(per_attempt) * (u32::from(c.retries) + 1)
                + Duration::from_secs(1)
        })
}

/// Reads `unit`'s status with `caller`'s turn on the bus.
async fn read(bus: &BusHandle, caller: &Caller, unit: u8) -> Result<Status, BusError> {
    let options = JobOptions {
        priority: Priority::Command,
        source: caller.source,
        queue_timeout: None,
        max_attempts: None,
        origin: caller.origin.clone(),
    };
    match bus
        .execute(unit, &DriveRequest::ReadStatus, options)
        .await?
    {
        DriveReply::Status(s) => Ok(s),
        _ => Err(BusError::Unconfirmed {
            unit,
            detail: "the reply to a status read carried no status",
        }),
    }
}

/// Settles a write its face could not make into a request (a value out
/// of the drive's range, a mode the drive does not have, a request of the
/// wrong shape): nothing is sent, and it is audited and published like
/// every refusal, with what the caller asked for in `what`.
pub(super) fn refused_unmade(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    what: String,
    why: String,
) {
    let bus = bus_name(parts, target);
    record(parts, caller, target, bus, what, WriteEnd::Invalid(why));
}

/// The name of `target`'s bus, for the audit.
fn bus_name(parts: &Arc<Parts>, target: Target) -> Arc<str> {
    parts
        .plant()
        .now()
        .bus_at(target.bus)
        .map_or_else(|| "?".into(), |b| b.handle.name_arc())
}

/// Writes a settled write to the audit log and publishes it as an event.
fn record(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    bus: Arc<str>,
    what: String,
    words: WriteEnd,
) {
    audit::write(
        caller.face.name(),
        &caller.who,
        &bus,
        target.unit,
        &what,
        &words,
    );
    let event = ControlEvent::Write(WriteEvent {
        at: SystemTime::now(),
        face: caller.face,
        who: caller.who.clone(),
        bus,
        unit: target.unit,
        drive: target.drive,
        what,
        result: words,
    });
    parts.events().publish(event.into(), None);
}

/// Everything needed to settle a write once its result is known.
struct Settle {
    parts: Arc<Parts>,
    caller: Caller,
    target: Target,
    bus: Arc<str>,
    write: Write,
    what: String,
    tickets: Vec<Ticket>,
}

impl Settle {
    fn new(parts: &Arc<Parts>, caller: &Caller, target: Target, write: &Write) -> Self {
        Settle {
            parts: parts.clone(),
            caller: caller.clone(),
            target,
            bus: bus_name(parts, target),
            write: write.clone(),
            what: write.describe(),
            tickets: Vec::new(),
        }
    }

    /// Settles a write that failed before it was sent, and returns why.
    fn failed(self, failure: Failure) -> Failure {
        let result: WriteResult = Err(failure);
        self.settle(&result, None);
        match result {
            Err(f) => f,
            Ok(_) => Failure::NotSent(BusError::ShuttingDown),
        }
    }

    /// Hands the result to the lease book, the audit log and the events.
    /// `gone`: the caller went away before the result, which is unknown.
    fn settle(self, result: &WriteResult, gone: Option<&str>) {
        let applied = match gone {
            Some(_) => Applied::Maybe,
            None => applied(result),
        };
        if !self.tickets.is_empty() {
            let tickets = self.tickets;
            self.parts.leases().with(|book, now: Instant| {
                let effects = tickets
                    .iter()
                    .flat_map(|t| book.end_write(t, applied, now))
                    .collect();
                ((), effects)
            });
        }
        let words = match gone {
            Some(why) => WriteEnd::CallerGone(why.to_string()),
            None => WriteEnd::of(result),
        };
        record(
            &self.parts,
            &self.caller,
            self.target,
            self.bus,
            self.what,
            words,
        );
    }

    /// What the bus's result means for this write.
    fn interpret(&self, result: JobResult) -> WriteResult {
        let unit = self.target.unit;
        let exchange = match result {
            Ok(exchange) => exchange,
            Err(e) if e.not_sent() => return Err(Failure::NotSent(e)),
            Err(e) => {
                return Err(Failure::Unknown {
                    error: e,
                    reply: None,
                });
            }
        };
        if unit == 0 {
            return Ok(Outcome::Broadcast);
        }
        let reply = exchange.reply;
        match &self.write {
            Write::Drive(request) => match request.parse_reply(&reply) {
                Ok(typed) => Ok(Outcome::Confirmed {
                    reply,
                    typed: Some(typed),
                }),
                Err(ReplyError::Exception(code)) => {
                    Err(Failure::DriveRefused { unit, code, reply })
                }
                Err(ReplyError::Mismatch(detail)) => Err(Failure::Unknown {
                    error: BusError::Unconfirmed { unit, detail },
                    reply: Some(reply),
                }),
            },
            // The master checked that the reply answers this request.
            Write::Pdu { .. } => match reply.first() {
                Some(f) if f & EXCEPTION_BIT != 0 => {
                    let code = ExceptionCode(reply.get(1).copied().unwrap_or(0));
                    Err(Failure::DriveRefused { unit, code, reply })
                }
                _ => Ok(Outcome::Confirmed { reply, typed: None }),
            },
        }
    }
}

enum State {
    Waiting(oneshot::Receiver<JobResult>),
    Done(JobResult),
}

/// A write on the bus queue. Wait for it with [`wait`](Self::wait) (or
/// poll [`try_ready`](Self::try_ready)), then take the result with
/// [`finish`](Self::finish). Dropped first, it is settled all the same.
pub struct Pending {
    settle: Option<Settle>,
    state: State,
    /// Followed to its end even if dropped: a brake or a deactivation.
    follow: bool,
}

impl std::fmt::Debug for Pending {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pending")
            .field("what", &self.settle.as_ref().map(|s| &s.what))
            .finish()
    }
}

impl Pending {
    /// Waits until the bus has a result. Cancel-safe.
    pub async fn wait(&mut self) {
        if let State::Waiting(rx) = &mut self.state {
            let result = rx.await.unwrap_or(Err(BusError::ShuttingDown));
            self.state = State::Done(result);
        }
    }

    /// True when the bus has a result (without waiting).
    pub fn try_ready(&mut self) -> bool {
        match &mut self.state {
            State::Done(_) => true,
            State::Waiting(rx) => match rx.try_recv() {
                Ok(result) => {
                    self.state = State::Done(result);
                    true
                }
                Err(TryRecvError::Closed) => {
                    self.state = State::Done(Err(BusError::ShuttingDown));
                    true
                }
                Err(TryRecvError::Empty) => false,
            },
        }
    }

    /// The result, settled (leases, audit, events). Call after
    /// [`wait`](Self::wait): a result not in yet is given up on, and the
    /// write settled as one whose caller went away (it may still run).
    pub fn finish(mut self) -> WriteResult {
        let Some(settle) = self.settle.take() else {
            return Err(Failure::NotSent(BusError::ShuttingDown));
        };
        self.try_ready();
        let state = std::mem::replace(&mut self.state, State::Done(Err(BusError::ShuttingDown)));
        match state {
            State::Done(r) => {
                let result = settle.interpret(r);
                settle.settle(&result, None);
                result
            }
            State::Waiting(mut rx) => {
                rx.close();
                let result = Err(Failure::Unknown {
                    error: BusError::ShuttingDown,
                    reply: None,
                });
                settle.settle(&result, Some(GONE));
                result
            }
        }
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        let Some(settle) = self.settle.take() else {
            return;
        };
        let state = std::mem::replace(&mut self.state, State::Done(Err(BusError::ShuttingDown)));
        match state {
            State::Done(r) => {
                let result = settle.interpret(r);
                settle.settle(&result, None);
            }
            State::Waiting(rx) if self.follow => match tokio::runtime::Handle::try_current() {
                // Leases depend on a brake's result: follow it whoever waits.
                Ok(runtime) => {
                    runtime.spawn(async move {
                        let result = rx.await.unwrap_or(Err(BusError::ShuttingDown));
                        let result = settle.interpret(result);
                        settle.settle(&result, None);
                    });
                }
                Err(_) => settle.settle(&Err(Failure::NotSent(BusError::ShuttingDown)), Some(GONE)),
            },
            State::Waiting(mut rx) => {
                // Closed, a job still queued is dropped unsent; one on the
                // wire runs, and its result is lost with the caller.
                rx.close();
                match rx.try_recv() {
                    Ok(r) => {
                        let result = settle.interpret(r);
                        settle.settle(&result, None);
                    }
                    Err(_) => {
                        settle.settle(&Err(Failure::NotSent(BusError::ShuttingDown)), Some(GONE))
                    }
                }
            }
        }
    }
}
