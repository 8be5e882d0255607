//! The task that owns a serial port: it takes one job at a time (emergency
//! first, then commands, then due status polls), runs it through the RTU
//! master, and reports the result. It runs on its own thread with its own
//! single-threaded runtime, so the wire's microsecond timing never competes
//! with HTTP or Modbus TCP work.

use std::io;
use std::sync::{Arc, LazyLock, Mutex, OnceLock};
use std::thread;
use std::time::{Duration, Instant, SystemTime};

use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::cache::StatusCache;
use super::error::BusError;
use super::error::PortCause;
use super::handle::{BusHandle, PortState, Shared, Tuned};
use super::interframe::Use;
use super::job::{Exchange, Job, Priority};
use super::master::{Fault, PortFailure, Report, RtuMaster};
use super::observers::Steer;
use super::origin::Origin;
use super::poller::{PollPlan, PollResult};
use super::queue::JobQueue;
pub use super::settings::BusSettings;
use super::stats::{BusStats, Outcome};
use super::tcp_port;
use super::transport;
use crate::clock;
use crate::drive::{DriveReply, DriveRequest};

mod retune;

/// Starts the bus's thread; returns its handle and the thread to join.
pub fn spawn(settings: BusSettings) -> io::Result<(BusHandle, thread::JoinHandle<()>)> {
    let shared = new_shared(&settings);
    let handle = BusHandle {
        shared: shared.clone(),
    };
    let thread = thread::Builder::new()
        .name(format!("bus-{}", shared.name))
        .spawn(move || {
            let runtime = match tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            {
                Ok(rt) => rt,
                Err(e) => {
                    warn!(bus = %shared.name, "cannot start the bus runtime: {e}");
                    never_started(&shared, format!("cannot start the bus runtime: {e}"));
                    return;
                }
            };
            runtime.block_on(Scheduler::new(settings, shared).run());
        })?;
    Ok((handle, thread))
}

/// What the handles and the bus thread share, for `settings`.
pub(crate) fn new_shared(settings: &BusSettings) -> Arc<Shared> {
    let name: Arc<str> = settings.name.as_str().into();
    Arc::new(Shared {
        name: name.clone(),
        queue: JobQueue::new(settings.queue),
        cache: StatusCache::new(
            name.clone(),
            settings.drives.iter().map(|d| d.0),
            settings.offline_after,
        )
        .expecting(settings.expected()),
        feed: Default::default(),
        stats: BusStats::new(),
        state: Mutex::new(PortState::Opening),
        line: settings.master.line,
        tuned: Mutex::new(Tuned {
            response_timeout: settings.master.response_timeout,
            queue_timeout: settings.queue_timeout,
        }),
        retune: Mutex::new(None),
        retuning: tokio::sync::Notify::new(),
        stop: CancellationToken::new(),
        ended: OnceLock::new(),
        stopped: OnceLock::new(),
    })
}

/// The bus could not start: it is down for good, the jobs already queued
/// fail with the reason, and so does every later one.
fn never_started(shared: &Shared, reason: String) {
    let down = BusError::BusDown {
        bus: shared.name.to_string(),
        reason: reason.clone().into(),
    };
    let _ = shared.ended.set(down.clone());
    shared.set_state(PortState::Down {
        since: SystemTime::now(),
        reason,
    });
    for job in shared.queue.stop() {
        shared
            .stats
            .record_transaction(job.pdu[0], Outcome::PortError, 0);
        job.finish(Err(down.clone()));
    }
}

enum Work {
    Job(Job),
    Poll(u8),
    /// A status read in idle time, to try a shorter silence before it.
    Trial(u8),
    Idle(Option<Instant>),
}

struct Scheduler {
    settings: BusSettings,
    shared: Arc<Shared>,
    plan: PollPlan,
    /// Commands run in a row while a poll was due.
    commands_in_a_row: u32,
    reopen: ReopenBackoff,
    /// When the line last became free for the next request: work waiting
    /// since then went out after the master's own overhead only.
    line_free_at: Instant,
}

/// The wait before each attempt to (re)open the port: it doubles from the
/// first to the longest delay while the port keeps failing, and starts over
/// only once the port has proven itself (a transaction went through, or it
/// stayed open as long as the longest delay). An open that succeeds proves
/// nothing: an adapter that opens and fails at once would otherwise be
/// reopened in a tight loop.
#[derive(Debug)]
struct ReopenBackoff {
    first: Duration,
    longest: Duration,
    next: Duration,
    /// When the port last opened, while it is open.
    opened_at: Option<Instant>,
    /// A transaction went through since it opened.
    proven: bool,
}

impl ReopenBackoff {
    fn new((first, longest): (Duration, Duration)) -> Self {
        Self {
            first,
            longest: longest.max(first),
            next: first,
            opened_at: None,
            proven: false,
        }
    }

    /// The port opened at `now`.
    fn opened(&mut self, now: Instant) {
        self.opened_at = Some(now);
        self.proven = false;
    }

    /// A transaction went through on the open port.
    fn worked(&mut self) {
        self.proven = true;
    }

    /// New first and longest delays (a reload): the next wait starts from
    /// the first.
    fn retune(&mut self, (first, longest): (Duration, Duration)) {
        self.first = first;
        self.longest = longest.max(first);
        self.next = first;
    }

    /// The port failed (or could not be opened) at `now`: how long to wait
    /// before the next attempt.
    fn failed(&mut self, now: Instant) -> Duration {
        let stayed_up = self
            .opened_at
            .take()
            .is_some_and(|t| now.saturating_duration_since(t) >= self.longest);
        if std::mem::take(&mut self.proven) || stayed_up {
            self.next = self.first;
        }
        let delay = self.next;
        self.next = (self.next * 2).min(self.longest);
        delay
    }
}

/// The status read's PDU, built once.
static STATUS_PDU: LazyLock<Vec<u8>> =
    LazyLock::new(|| DriveRequest::ReadStatus.pdu().unwrap_or_default());

impl Scheduler {
    fn new(settings: BusSettings, shared: Arc<Shared>) -> Self {
        let plan = PollPlan::new(
            settings.drives.iter().copied(),
            settings.offline_backoff.0,
            settings.offline_backoff.1,
            Instant::now(),
        );
        Self {
            reopen: ReopenBackoff::new(settings.reopen_backoff),
            settings,
            shared,
            plan,
            commands_in_a_row: 0,
            line_free_at: Instant::now(),
        }
    }

    fn cache(&self) -> &StatusCache {
        &self.shared.cache
    }

    fn stats(&self) -> &BusStats {
        &self.shared.stats
    }

    async fn run(mut self) {
        clock::tighten_timer_slack();
        let name = self.shared.name.clone();
        let mut master: Option<RtuMaster> = None;
        let mut opened_before = false;
        let mut last_open_error = String::new();

        loop {
            if self.shared.stop.is_cancelled() {
                self.finish(master.as_mut()).await;
                break;
            }
            // Between two transactions: new settings (a reload) are taken
            // here, on the open port.
            self.take_retune(master.as_mut());
            let Some(m) = master.as_mut() else {
                let opened = tokio::select! {
                    opened = transport::open(
                        &self.settings.port,
                        self.settings.master.line.baud(),
                        &self.settings.master.rs485,
                    ) => opened,
                    () = self.shared.stop.cancelled() => continue,
                };
                match opened.map_err(|e| e.to_string()).and_then(|p| {
                    RtuMaster::new(p, self.settings.master).map_err(|e| e.to_string())
                }) {
                    Ok(mut m) => {
                        info!(bus = %name, port = %self.settings.port, "{} open", self.port_kind());
                        m.tap().attach(self.settings.observers.wire.clone());
                        master = Some(m);
                        self.stats().set_port_open(true, opened_before);
                        opened_before = true;
                        self.reopen.opened(Instant::now());
                        last_open_error.clear();
                        self.shared.set_state(PortState::Up {
                            since: SystemTime::now(),
                        });
                        self.cache().record_port(true, "");
                    }
                    Err(reason) => {
                        if reason != last_open_error {
                            warn!(bus = %name, "{reason}; retrying every {:?} at most", self.settings.reopen_backoff.1);
                            self.stats().record_port_error(&reason);
                            last_open_error = reason.clone();
                        }
                        self.mark_down(reason.into());
                        let delay = self.reopen.failed(Instant::now());
                        self.pause(delay).await;
                    }
                }
                continue;
            };

            // Let the line go quiet first, then choose: whatever arrived in
            // the meantime (an emergency brake) is considered.
            let result = match m.settle().await {
                Ok(stray) => {
                    if stray > 0 {
                        self.stats().add_stray_bytes(stray);
                    }
                    self.line_free_at = m.line_free_at();
                    match self.next_work(Instant::now(), m) {
                        Work::Job(job) => self.run_job(m, job).await,
                        Work::Poll(unit) => self.run_poll(m, unit).await,
                        Work::Trial(unit) => self.run_trial(m, unit).await,
                        Work::Idle(until) => {
                            self.idle(until).await;
                            Ok(())
                        }
                    }
                }
                Err(e) => Err(e),
            };
            if let Err(e) = result {
                // An adapter that opens and fails at once must not make this
                // thread spin: the reopen waits, longer each time, until the
                // port has proven itself again.
                let delay = self.reopen.failed(Instant::now());
                let reason = format!("{} {} failed: {e}", self.port_kind(), self.settings.port);
                warn!(bus = %name, "{reason}; reopening in {delay:?}");
                self.stats().record_port_error(&reason);
                master = None;
                self.mark_down(PortCause::io(&e, reason));
                self.pause(delay).await;
            }
        }
        // The port is closed now. The counters (port_open included) keep
        // the last state of the run: a scrape after the stop describes it,
        // and so does the drives' freshness.
        drop(master);
        let _ = self
            .shared
            .stopped
            .set((self.shared.state(), Instant::now()));
        self.shared.set_state(PortState::Down {
            since: SystemTime::now(),
            reason: "the bus has stopped: drivegate is shutting down".to_string(),
        });
        info!(bus = %name, "bus stopped");
    }

    /// Waits for a job, for `until` (when something falls due), or for
    /// the stop.
    async fn idle(&self, until: Option<Instant>) {
        let sleep = async {
            match until {
                Some(t) => tokio::time::sleep_until(t.into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = self.shared.queue.notified() => {}
            () = self.shared.retuning.notified() => {}
            () = sleep => {}
            () = self.shared.stop.cancelled() => {}
        }
    }

    /// What the port is, for messages.
    fn port_kind(&self) -> &'static str {
        if tcp_port::address(&self.settings.port).is_some() {
            "connection to the serial device server"
        } else {
            "serial port"
        }
    }

    /// Waits `delay` before the next attempt to open the port, or until the
    /// bus is stopped.
    /// New settings that come meanwhile are taken at once (the port is
    /// closed: nothing is on the wire).
    async fn pause(&mut self, delay: Duration) {
        let until = tokio::time::Instant::now() + delay;
        loop {
            tokio::select! {
                () = tokio::time::sleep_until(until) => return,
                () = self.shared.stop.cancelled() => return,
                () = self.shared.retuning.notified() => self.take_retune(None),
            }
        }
    }

    /// Marks the port down and fails every waiting job: nobody should wait
    /// for a bus that may not come back soon.
    fn mark_down(&self, cause: PortCause) {
        let reason = cause.detail.clone();
        // Down since it first failed, not since the last attempt to reopen
        // it; the state is set before the news, so whoever the news sends
        // to look finds the port down.
        let (since, news) = match self.shared.state() {
            PortState::Down { since, .. } => (since, false),
            _ => (SystemTime::now(), true),
        };
        self.shared.set_state(PortState::Down {
            since,
            reason: reason.clone(),
        });
        if news {
            self.stats().set_port_open(false, false);
            self.cache().record_port(false, &reason);
        }
        for job in self.shared.queue.drain() {
            self.stats()
                .record_transaction(job.pdu[0], Outcome::PortError, 0);
            job.finish(Err(BusError::BusDown {
                bus: self.settings.name.clone(),
                reason: cause.clone(),
            }));
        }
    }

    /// Runs what is left at a stop: emergency jobs (safe-stop actions) still
    /// go out, everything else is refused. Emergencies that arrive while the
    /// first ones are on the wire get one more round; then the queue stops
    /// taking anything, in the same step as the last take, so every job it
    /// accepted gets an answer.
    async fn finish(&mut self, mut master: Option<&mut RtuMaster>) {
        let waiting = self.shared.queue.drain();
        self.run_or_refuse(waiting, &mut master).await;
        // Before the queue stops, so a job it refuses finds the answer.
        let _ = self.shared.ended.set(BusError::ShuttingDown);
        let last = self.shared.queue.stop();
        self.run_or_refuse(last, &mut master).await;
    }

    /// Sends the emergency jobs among `jobs` while the port works; refuses
    /// the others as shutting down.
    async fn run_or_refuse(&mut self, jobs: Vec<Job>, master: &mut Option<&mut RtuMaster>) {
        for job in jobs {
            match (master.as_deref_mut(), job.priority) {
                (Some(m), Priority::Emergency) => {
                    if self.run_job(m, job).await.is_err() {
                        *master = None;
                    }
                }
                _ => job.finish(Err(BusError::ShuttingDown)),
            }
        }
    }

    /// The next thing to do on the line. A job or poll whose reply a late
    /// reply could pass for waits until that reply cannot come any more
    /// ([`RtuMaster::held_until`]); the others go meanwhile. A silent
    /// drive's probe waits while clients' requests do, unless it has waited
    /// its longest backoff ([`PollPlan::probe_may_wait`]).
    fn next_work(&mut self, now: Instant, master: &RtuMaster) -> Work {
        let queue = &self.shared.queue;
        if let Some(job) = queue.pop(Priority::Emergency) {
            return Work::Job(job);
        }
        let may_go = |job: &Job| master.held_until(job.unit, &job.pdu, now).is_none();
        let [_, commands, client_polls] = queue.depths();
        let clients_wait = commands + client_polls > 0;
        // While a capture runs the scope says which drive's poll is due.
        let (plan, cache) = (&self.plan, &self.shared.cache);
        let steer = self.settings.observers.steering.as_ref().and_then(|s| {
            s.steer(now, &|unit| plan.is_due(unit, now), &|unit| {
                cache.is_offline(unit)
            })
        });
        let poll_due = match steer {
            Some(Steer::Poll(unit)) => Some(unit),
            Some(Steer::Wait(_)) => None,
            None => self.plan.due_among(now, |unit| {
                !(clients_wait && plan.probe_may_wait(unit, now))
                    && master.held_until(unit, &STATUS_PDU, now).is_none()
            }),
        };
        if let Some(unit) = poll_due
            && self.commands_in_a_row >= self.settings.poll_share
        {
            self.commands_in_a_row = 0;
            return Work::Poll(unit);
        }
        if let Some(job) = queue.pop_first(Priority::Command, may_go) {
            if poll_due.is_some() {
                self.commands_in_a_row += 1;
            }
            return Work::Job(job);
        }
        if let Some(unit) = poll_due {
            self.commands_in_a_row = 0;
            return Work::Poll(unit);
        }
        if let Some(job) = queue.pop_first(Priority::Poll, may_go) {
            return Work::Job(job);
        }
        // Idle: a drive learning its gap may try a shorter one.
        if let Some(unit) = self.settings.drives.iter().map(|d| d.0).find(|&unit| {
            master.wants_trial(unit, now)
                && cache.answering(unit)
                && master.held_until(unit, &STATUS_PDU, now).is_none()
        }) {
            return Work::Trial(unit);
        }
        // Whatever waits for a late reply's time to pass goes when it has,
        // and a probe that waited for the clients when its wait is over.
        let released = match (
            master.next_release(now),
            self.plan.waiting_probe_goes_at(now),
        ) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        let until = match steer {
            Some(Steer::Wait(until)) => Some(until),
            // A poll overdue now is one that waits (a probe behind the
            // clients, a held one): nothing to wake for before a release.
            _ => match self.plan.next_due() {
                Some(due) if due <= now => self.plan.next_due_after(now),
                due => due,
            },
        };
        Work::Idle(match (until, released) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        })
    }

    /// Counts a transaction that went through the port (whatever the drive
    /// answered): the port works. `waiting_since` is when its work was ready
    /// (submitted, or due): if that was before the line became free, the
    /// silence before it is the master's doing and is measured.
    fn account(&mut self, unit: u8, function: u8, report: &Report, waiting_since: Instant) {
        self.reopen.worked();
        let stats = self.stats();
        stats.record_timing(
            unit,
            report.reply_timeout,
            report.turnaround,
            report.late_replies,
            (report.interframe, report.interframe_fallbacks),
        );
        if waiting_since <= self.line_free_at {
            stats.interframe_idle.observe(report.idle_before);
        }
        stats.record_transaction(function, report.outcome, report.attempts);
        stats.transaction_duration.observe(report.on_wire);
        stats.add_busy(report.busy);
        if report.stray_bytes > 0 {
            stats.add_stray_bytes(report.stray_bytes);
        }
    }

    async fn run_job(&mut self, master: &mut RtuMaster, job: Job) -> io::Result<()> {
        let now = Instant::now();
        let function = job.pdu[0];
        if job.is_stale(now) {
            self.stats()
                .record_transaction(function, Outcome::Dropped, 0);
            let waited = now - job.submitted;
            debug!(bus = %self.shared.name, unit = job.unit, "dropped a job whose caller had gone or whose deadline passed");
            job.finish(Err(BusError::Expired { waited }));
            return Ok(());
        }
        // An offline drive is probed: one try and a short guard; its retries
        // would cost everybody. A job that asks for one attempt itself (a
        // scan of the line) gets the full response timeout instead.
        let offline = job.unit != 0 && self.cache().is_offline(job.unit);
        let queued = now - job.submitted;
        master.tap().cause(job.origin.clone());
        // An emergency keeps to a gap answered lately; a client's request
        // never tries a shorter one.
        let use_ = match job.priority {
            Priority::Emergency => Use::Emergency,
            _ => Use::Command,
        };
        let sent = if offline && job.max_attempts.is_none() {
            master.probe(job.unit, &job.pdu).await
        } else {
            master
                .transact_as(
                    job.unit,
                    &job.pdu,
                    job.max_attempts.or(offline.then_some(1)),
                    use_,
                )
                .await
        };
        let report = match sent {
            Ok(report) => report,
            Err(failure) => {
                self.stats()
                    .record_transaction(function, Outcome::PortError, 1);
                let (bus, unit) = (self.settings.name.clone(), job.unit);
                let (PortFailure::BeforeSend(e) | PortFailure::AfterSend(e)) = &failure;
                let reason = PortCause::io(e, failure.to_string());
                // Once the frame has started to go out, the drive may act on
                // it: the caller must not take it for never sent.
                job.finish(Err(if failure.request_sent() {
                    BusError::BusDownAfterSend { bus, unit, reason }
                } else {
                    BusError::BusDown { bus, reason }
                }));
                return Err(failure.into_io());
            }
        };
        self.account(job.unit, function, &report, job.submitted);
        let result = match (report.outcome, report.reply) {
            (Outcome::Ok | Outcome::Exception, Some(reply)) => {
                // A client's read of a drive's status is as good as a poll
                // (the plan may skip the next one); any answer says the
                // drive is there.
                let now = Instant::now();
                if job.pdu == *STATUS_PDU
                    && let Ok(DriveReply::Status(s)) = DriveRequest::ReadStatus.parse_reply(&reply)
                {
                    self.cache().record_status(job.unit, s);
                    // A drive learning its gap keeps its polls: only they
                    // may try a shorter silence.
                    if master.wants_trial(job.unit, now) {
                        self.plan.answered(job.unit, now);
                    } else {
                        self.plan.refreshed(job.unit, now);
                    }
                } else if job.unit != 0 {
                    self.plan.answered(job.unit, now);
                }
                Ok(Exchange {
                    reply,
                    attempts: report.attempts,
                    queued,
                    on_wire: report.on_wire,
                })
            }
            (Outcome::Timeout, _) => Err(BusError::Timeout {
                unit: job.unit,
                attempts: report.attempts,
                timeout_ms: self.settings.master.response_timeout.as_millis() as u64,
            }),
            (_, _) => Err(BusError::BadReply {
                unit: job.unit,
                attempts: report.attempts,
                fault: report.fault.unwrap_or(Fault::Mismatch("invalid reply")),
            }),
        };
        self.stats().job_latency.observe(job.submitted.elapsed());
        job.finish(result);
        Ok(())
    }

    /// A status read of `unit` in idle time with a shorter silence before
    /// it (a drive learning its gap): its status counts as a client's read
    /// would (the plan may skip the next poll), its failure is the trial's.
    async fn run_trial(&mut self, master: &mut RtuMaster, unit: u8) -> io::Result<()> {
        master.tap().cause(Origin::Poller);
        let report = master
            .transact_as(unit, &STATUS_PDU, None, Use::Poll)
            .await
            .map_err(PortFailure::into_io)?;
        let now = Instant::now();
        self.account(unit, STATUS_PDU[0], &report, now);
        if let Some(Ok(DriveReply::Status(s))) = report
            .reply
            .as_deref()
            .map(|r| DriveRequest::ReadStatus.parse_reply(r))
        {
            self.cache().record_status(unit, s);
            self.plan.refreshed(unit, now);
        }
        Ok(())
    }

    async fn run_poll(&mut self, master: &mut RtuMaster, unit: u8) -> io::Result<()> {
        let pdu: &[u8] = &STATUS_PDU;
        let offline = self.cache().is_offline(unit);
        let due = self.plan.due_at(unit).unwrap_or_else(Instant::now);
        // A drive that did not answer its last poll (or never has) is
        // probed: one attempt and a short guard. If it is off, a retry or a
        // long guard only costs everybody time, and the next poll comes
        // anyway.
        let origin = match &self.settings.observers.steering {
            Some(s) => s.poll_origin(unit),
            None => Origin::Poller,
        };
        master.tap().cause(origin);
        let report = if self.cache().answering(unit) {
            master.transact_as(unit, pdu, None, Use::Poll).await
        } else {
            master.probe(unit, pdu).await
        }
        .map_err(PortFailure::into_io)?;
        self.account(unit, pdu[0], &report, due);
        let status =
            report
                .reply
                .as_deref()
                .and_then(|r| match DriveRequest::ReadStatus.parse_reply(r) {
                    Ok(DriveReply::Status(s)) => Some(s),
                    _ => None,
                });
        match status {
            Some(s) => {
                if offline {
                    info!(bus = %self.shared.name, unit, "drive answers again");
                }
                self.cache().record_status(unit, s);
            }
            None => {
                let reason = match (&report.fault, report.reply) {
                    (Some(f), _) => f.describe(),
                    (None, Some(r)) if r.len() == 2 => format!("exception 0x{:02X}", r[1]),
                    _ => "invalid status reply".to_string(),
                };
                if self.cache().record_failure(unit, &reason) {
                    warn!(bus = %self.shared.name, unit, "drive stopped answering ({reason}); polling it with backoff");
                }
            }
        }
        self.stats().record_poll(status.is_some());
        let now = Instant::now();
        let result = if status.is_some() {
            PollResult::Answered
        } else {
            PollResult::Failed {
                offline: self.cache().is_offline(unit),
            }
        };
        self.plan.polled(unit, now, result);
        if let Some(s) = &self.settings.observers.steering {
            s.polled(unit, now);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::handle::JobOptions;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn a_bus_that_never_started_answers_every_job() {
        let shared = new_shared(&BusSettings::new("line1", "/dev/null", 115_200, vec![]));
        let bus = BusHandle {
            shared: shared.clone(),
        };
        let emergency = JobOptions::with_priority(Priority::Emergency);
        let mut queued = bus
            .submit(1, STATUS_PDU.clone(), emergency.clone())
            .unwrap();
        never_started(&shared, "cannot start the bus runtime: no memory".into());
        // The job that was waiting gets the reason...
        match queued.try_recv() {
            Ok(Err(BusError::BusDown { reason, .. })) => assert!(reason.detail.contains("runtime")),
            other => panic!("{other:?}"),
        }
        // ...and so does every later one, at once, emergencies included.
        let later = bus.submit(1, STATUS_PDU.clone(), emergency).unwrap_err();
        assert!(
            matches!(&later, BusError::BusDown { reason, .. } if reason.detail.contains("runtime")),
            "{later}"
        );
        assert_eq!(bus.queue_depths(), [0, 0, 0]);
    }

    #[test]
    fn a_port_that_opens_and_fails_at_once_backs_off_further_each_time() {
        let mut backoff = ReopenBackoff::new((100 * MS, 400 * MS));
        let mut now = Instant::now();
        let mut delays = vec![];
        for _ in 0..5 {
            backoff.opened(now);
            now += MS;
            let delay = backoff.failed(now);
            delays.push(delay);
            now += delay;
        }
        assert_eq!(delays, [100 * MS, 200 * MS, 400 * MS, 400 * MS, 400 * MS]);
    }

    #[test]
    fn failed_opens_back_off_too() {
        let mut backoff = ReopenBackoff::new((100 * MS, 400 * MS));
        let now = Instant::now();
        let delays: Vec<_> = (0..4).map(|_| backoff.failed(now)).collect();
        assert_eq!(delays, [100 * MS, 200 * MS, 400 * MS, 400 * MS]);
    }

    #[test]
    fn a_port_that_proved_itself_starts_over_at_the_first_delay() {
        let mut backoff = ReopenBackoff::new((100 * MS, 400 * MS));
        let now = Instant::now();
        for _ in 0..3 {
            backoff.failed(now);
        }
        // A transaction went through.
        backoff.opened(now);
        backoff.worked();
        assert_eq!(backoff.failed(now + MS), 100 * MS);
        // Failing on, it backs off again...
        assert_eq!(backoff.failed(now), 200 * MS);
        // ...until it stays open for as long as the longest delay, idle.
        backoff.opened(now);
        assert_eq!(backoff.failed(now + 400 * MS), 100 * MS);
        // A success before the last open does not count for this one.
        backoff.worked();
        backoff.opened(now);
        assert_eq!(backoff.failed(now + MS), 200 * MS);
    }
}
