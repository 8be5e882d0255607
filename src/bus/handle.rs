//! The handle the faces hold: submit jobs, read the cache, subscribe to
//! events, read the counters. Cheap to clone; never touches the port.

use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::{Notify, broadcast, oneshot};
use tokio_util::sync::CancellationToken;

use super::cache::{BusEvent, DriveSnapshot, StatusCache};
use super::error::BusError;
use super::feed::{BusFollower, Feed};
use super::freshness::{self, Verdict};
use super::job::{Exchange, Job, Priority, SourceId};
pub use super::link::PortState;
use super::origin::Origin;
use super::queue::{JobQueue, Refused};
use super::settings::BusSettings;
use super::stats::{BusStats, BusStatsSnapshot, Outcome};
use crate::drive::{ConfigCommand, DriveReply, DriveRequest};
use crate::modbus::timing::LineTiming;

/// Options of one submission.
#[derive(Debug, Clone)]
pub struct JobOptions {
    /// Priority class.
    pub priority: Priority,
    /// Who submits, for fair queuing.
    pub source: SourceId,
    /// Give up unsent after this long in the queue (`None`: the bus default).
    pub queue_timeout: Option<Duration>,
    /// Attempts allowed (`None`: the bus's retries).
    pub max_attempts: Option<u8>,
    /// Who caused the job, shown by the bus monitor (set by the face).
    pub origin: Origin,
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            priority: Priority::Command,
            source: SourceId::INTERNAL,
            queue_timeout: None,
            max_attempts: None,
            origin: Origin::Internal,
        }
    }
}

impl JobOptions {
    /// Default options at `priority`.
    pub fn with_priority(priority: Priority) -> Self {
        Self {
            priority,
            ..Self::default()
        }
    }

    /// Default options for `source`.
    pub fn from_source(source: SourceId) -> Self {
        Self {
            source,
            ..Self::default()
        }
    }
}

/// What the handle and the scheduler share.
pub(crate) struct Shared {
    pub(crate) name: Arc<str>,
    pub(crate) queue: JobQueue,
    pub(crate) cache: StatusCache,
    /// Whoever follows the cache's events, called in one task.
    pub(crate) feed: Arc<Feed>,
    pub(crate) stats: BusStats,
    pub(crate) state: Mutex<PortState>,
    pub(crate) line: LineTiming,
    /// The timeouts the handles read, as last retuned.
    pub(crate) tuned: Mutex<Tuned>,
    /// New settings the scheduler takes at its next transaction boundary.
    pub(crate) retune: Mutex<Option<Retune>>,
    /// Wakes the scheduler for them, whatever it waits for.
    pub(crate) retuning: Notify,
    pub(crate) stop: CancellationToken,
    /// Set once the bus has stopped for good (shut down, or never started):
    /// the answer to every later submission.
    pub(crate) ended: OnceLock<BusError>,
    /// The port's state and the moment the bus stopped at a shutdown: the
    /// drives' freshness stays what it was then, as the counters do.
    pub(crate) stopped: OnceLock<(PortState, Instant)>,
}

/// What of a bus's settings its handles read.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Tuned {
    pub(crate) response_timeout: Duration,
    pub(crate) queue_timeout: Duration,
}

/// New settings for a running bus, and who waits until they are taken.
pub(crate) struct Retune {
    pub(crate) settings: BusSettings,
    pub(crate) taken: oneshot::Sender<()>,
}

impl Shared {
    pub(crate) fn tuned(&self) -> Tuned {
        *self.tuned.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(crate) fn set_state(&self, state: PortState) {
        *self.state.lock().unwrap_or_else(|p| p.into_inner()) = state;
    }

    pub(crate) fn state(&self) -> PortState {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The port's state and the time to judge freshness at, for `now`:
    /// after a shutdown's stop, those of the stop.
    fn judged_at(&self, now: Instant) -> (PortState, Instant) {
        match self.stopped.get() {
            Some((port, at)) => (port.clone(), now.min(*at)),
            None => (self.state(), now),
        }
    }
}

impl std::fmt::Debug for BusHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("BusHandle").field(&self.name()).finish()
    }
}

/// A cheap, cloneable way to one bus.
#[derive(Clone)]
pub struct BusHandle {
    pub(crate) shared: Arc<Shared>,
}

impl BusHandle {
    /// The bus's configured name.
    pub fn name(&self) -> &str {
        &self.shared.name
    }

    /// True when both are handles of the same running bus (a bus reopened
    /// is another; one changed in place is the same).
    pub fn is(&self, other: &BusHandle) -> bool {
        Arc::ptr_eq(&self.shared, &other.shared)
    }

    /// The bus's name, shared.
    pub fn name_arc(&self) -> Arc<str> {
        self.shared.name.clone()
    }

    /// The line's timing (baud, character time, silences).
    pub fn line(&self) -> LineTiming {
        self.shared.line
    }

    /// The bus's response timeout.
    pub fn response_timeout(&self) -> Duration {
        self.shared.tuned().response_timeout
    }

    /// Hands `settings` to the running bus, which takes them between two
    /// transactions without closing its port (`settings.reach` must be
    /// [`Reach::InPlace`](super::settings::Reach) from what it runs: the
    /// caller reopens the bus otherwise). The receiver answers once they
    /// are in force; it fails if the bus stopped first. Settings handed
    /// over before and not taken yet are replaced.
    pub fn retune(&self, settings: BusSettings) -> oneshot::Receiver<()> {
        let (taken, rx) = oneshot::channel();
        *self.shared.retune.lock().unwrap_or_else(|p| p.into_inner()) =
            Some(Retune { settings, taken });
        self.shared.retuning.notify_one();
        rx
    }

    /// How long a job may wait in the queue before it is dropped unsent
    /// (`queue_timeout_ms`), unless its submission says less.
    pub fn queue_timeout(&self) -> Duration {
        self.shared.tuned().queue_timeout
    }

    /// Queues a raw request PDU for `unit`; the receiver yields the result.
    pub fn submit(
        &self,
        unit: u8,
        pdu: Vec<u8>,
        options: JobOptions,
    ) -> Result<oneshot::Receiver<super::job::JobResult>, BusError> {
        if pdu.is_empty() || pdu.len() > 253 {
            return Err(BusError::Invalid(format!(
                "a Modbus request PDU is 1 to 253 bytes, this one is {}",
                pdu.len()
            )));
        }
        if let Some(ended) = self.shared.ended.get() {
            return Err(ended.clone());
        }
        if let PortState::Down { reason, .. } = self.shared.state() {
            return Err(BusError::BusDown {
                bus: self.name().to_string(),
                reason: reason.into(),
            });
        }
        let now = Instant::now();
        let (tx, rx) = oneshot::channel();
        let job = Job {
            unit,
            pdu,
            priority: options.priority,
            source: options.source,
            deadline: Some(
                now + options
                    .queue_timeout
                    .unwrap_or(self.shared.tuned().queue_timeout),
            ),
            max_attempts: options.max_attempts,
            origin: options.origin,
            submitted: now,
            reply: tx,
        };
        let pushed = match self.shared.queue.push(job) {
            // A class full of abandoned jobs (clients that sent a request
            // and left, many times over) must not turn away a caller who is
            // still waiting: those are dropped, as the scheduler would, and
            // the job tried again.
            Err(Refused::Full(job, capacity)) => {
                let stale = self.shared.queue.take_stale(job.priority, now);
                if stale.is_empty() {
                    Err(Refused::Full(job, capacity))
                } else {
                    for gone in stale {
                        self.shared
                            .stats
                            .record_transaction(gone.pdu[0], Outcome::Dropped, 0);
                        let waited = now - gone.submitted;
                        gone.finish(Err(BusError::Expired { waited }));
                    }
                    self.shared.queue.push(job)
                }
            }
            other => other,
        };
        match pushed {
            Ok(()) => Ok(rx),
            Err(Refused::Full(job, capacity)) => {
                self.shared.stats.record_busy_rejection();
                Err(BusError::Busy {
                    bus: self.name().to_string(),
                    priority: job.priority,
                    capacity,
                })
            }
            Err(Refused::Closed(_)) => Err(BusError::ShuttingDown),
            Err(Refused::Stopped(_)) => Err(self
                .shared
                .ended
                .get()
                .cloned()
                .unwrap_or(BusError::ShuttingDown)),
        }
    }

    /// Sends a raw request PDU and waits for the drive's reply PDU (an
    /// exception reply is returned as a reply, not an error).
    pub async fn transact(
        &self,
        unit: u8,
        pdu: Vec<u8>,
        options: JobOptions,
    ) -> Result<Exchange, BusError> {
        let rx = self.submit(unit, pdu, options)?;
        rx.await.unwrap_or(Err(BusError::ShuttingDown))
    }

    /// Sends a typed drive request and checks that the drive confirmed it.
    /// An emergency brake always goes as an emergency.
    pub async fn execute(
        &self,
        unit: u8,
        request: &DriveRequest,
        mut options: JobOptions,
    ) -> Result<DriveReply, BusError> {
        if *request == DriveRequest::Config(ConfigCommand::EmergencyBrake) {
            options.priority = Priority::Emergency;
        }
        let pdu = request
            .pdu()
            .map_err(|e| BusError::Invalid(e.to_string()))?;
        let target = if request.is_broadcast() { 0 } else { unit };
        let exchange = self.transact(target, pdu, options).await?;
        request
            .parse_reply(&exchange.reply)
            .map_err(|e| BusError::from_reply(unit, e))
    }

    /// What is known of one drive.
    pub fn drive(&self, unit: u8) -> Option<DriveSnapshot> {
        self.shared.cache.get(unit)
    }

    /// What is known of every configured drive.
    pub fn drives(&self) -> Vec<DriveSnapshot> {
        self.shared.cache.all()
    }

    /// How often `unit` is polled when nothing else uses the bus: its
    /// poll interval, or (polled as fast as the bus allows) one round of
    /// the bus's status polls; never later than it can be (see
    /// [`freshness::Expected::poll`]).
    pub fn poll_period(&self, unit: u8) -> std::time::Duration {
        self.shared.cache.expected(unit).poll
    }

    /// How fresh `unit`'s data is now (`None`: not a drive of this bus).
    pub fn freshness(&self, unit: u8) -> Option<Verdict> {
        self.freshness_at(unit, Instant::now())
    }

    /// How fresh `unit`'s data is at `now`.
    pub fn freshness_at(&self, unit: u8, now: Instant) -> Option<Verdict> {
        let (port, now) = self.shared.judged_at(now);
        let facts = self.shared.cache.facts(unit)?;
        Some(freshness::judge(
            &port,
            &facts,
            self.shared.cache.expected(unit),
            now,
        ))
    }

    /// How fresh every drive's data is at `now`, by unit.
    pub fn freshness_all(&self, now: Instant) -> Vec<(u8, Verdict)> {
        let (port, now) = self.shared.judged_at(now);
        self.shared
            .cache
            .all_facts()
            .into_iter()
            .map(|(unit, facts)| {
                let expected = self.shared.cache.expected(unit);
                (unit, freshness::judge(&port, &facts, expected, now))
            })
            .collect()
    }

    /// Every future status, online/offline and bus event of this bus.
    pub fn subscribe(&self) -> broadcast::Receiver<BusEvent> {
        self.shared.cache.subscribe()
    }

    /// Hands every future event of this bus to `follower` until `stop`, in
    /// one task with the bus's other followers: a poll wakes one task, not
    /// one per follower (see [`feed`](super::feed)).
    pub fn follow(&self, follower: Arc<dyn BusFollower>, stop: CancellationToken) {
        let cache = &self.shared.cache;
        self.shared
            .feed
            .follow(follower, stop, || cache.subscribe());
    }

    /// The future online/offline and bus events of this bus, without the
    /// statuses: for whoever follows the links, not every poll.
    pub fn subscribe_links(&self) -> broadcast::Receiver<BusEvent> {
        self.shared.cache.subscribe_links()
    }

    /// The bus's counters.
    pub fn stats(&self) -> BusStatsSnapshot {
        self.shared.stats.snapshot()
    }

    /// Wakes the bus thread to look at its work again (a capture was armed,
    /// so the polling its steering asks for follows at once).
    pub fn wake(&self) {
        self.shared.queue.wake();
    }

    /// Jobs waiting per priority class (emergency, command, poll).
    pub fn queue_depths(&self) -> [usize; 3] {
        self.shared.queue.depths()
    }

    /// The serial port's state.
    pub fn port_state(&self) -> PortState {
        self.shared.state()
    }

    /// Stops taking normal work (emergency jobs still pass): the first step
    /// of a graceful stop.
    pub fn close(&self) {
        self.shared.queue.close();
    }

    /// Lets the scheduler exit: it runs the emergency jobs still waiting,
    /// refuses the rest, and from then on every submission is refused.
    pub fn stop(&self) {
        self.shared.queue.close();
        self.shared.stop.cancel();
    }
}
