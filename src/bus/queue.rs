//! The bounded job queue of one bus: strict priority between classes, round
//! robin between sources inside a class.
//!
//! Fairness matters for the Modbus TCP face: a client that pipelines hundreds
//! of requests gets one turn per round like every other connection, and a
//! per-source bound keeps it from filling the class for everybody.
//!
//! The daemon's own safe stops (emergency jobs of [`SourceId::INTERNAL`])
//! are outside both bounds: a shutdown stops every drive at once, and a stop
//! refused as busy would leave a motor running. They are bounded anyway, by
//! the number of drives: each safe stop has one job in flight at a time.

use std::collections::{HashMap, VecDeque};
use std::sync::Mutex;
use std::time::Instant;

use tokio::sync::Notify;

use super::job::{Job, Priority, SourceId};

/// Capacities of a queue (the daemon's own safe stops are not counted, see
/// the module's documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueLimits {
    /// Jobs a class may hold in all.
    pub per_class: usize,
    /// Jobs one source may hold in a class.
    pub per_source: usize,
}

impl Default for QueueLimits {
    fn default() -> Self {
        Self {
            per_class: 256,
            per_source: 64,
        }
    }
}

/// Why a job was not queued; the job comes back to the caller.
#[derive(Debug)]
pub enum Refused {
    /// The class (or the source's share of it) is full.
    Full(Job, usize),
    /// The queue is closed (shutting down or bus down).
    Closed(Job),
    /// The bus has stopped for good: nobody will ever take the job.
    Stopped(Job),
}

#[derive(Default)]
struct Class {
    /// Sources with waiting jobs, in round-robin order.
    turn: VecDeque<SourceId>,
    jobs: HashMap<SourceId, VecDeque<Job>>,
    len: usize,
}

impl Class {
    fn push(&mut self, job: Job) {
        let source = job.source;
        let queue = self.jobs.entry(source).or_default();
        if queue.is_empty() {
            self.turn.push_back(source);
        }
        queue.push_back(job);
        self.len += 1;
    }

    fn source_len(&self, source: SourceId) -> usize {
        self.jobs.get(&source).map_or(0, VecDeque::len)
    }

    /// Jobs that count against the class's capacity: all but the daemon's
    /// own safe stops.
    fn counted_len(&self, priority: Priority) -> usize {
        if priority == Priority::Emergency {
            self.len - self.source_len(SourceId::INTERNAL)
        } else {
            self.len
        }
    }

    /// Takes the next job of the source whose turn it is.
    fn pop(&mut self) -> Option<Job> {
        let source = self.turn.pop_front()?;
        let queue = self.jobs.get_mut(&source)?;
        let job = queue.pop_front();
        if queue.is_empty() {
            self.jobs.remove(&source);
        } else {
            self.turn.push_back(source);
        }
        if job.is_some() {
            self.len -= 1;
        }
        job
    }

    /// Takes the next job, in turn, among the sources whose first job
    /// `may_go`; a source passed over keeps its turn.
    fn pop_first(&mut self, may_go: impl Fn(&Job) -> bool) -> Option<Job> {
        let at = self.turn.iter().position(|source| {
            self.jobs
                .get(source)
                .and_then(VecDeque::front)
                .is_some_and(&may_go)
        })?;
        let source = self.turn.remove(at)?;
        let queue = self.jobs.get_mut(&source)?;
        let job = queue.pop_front();
        if queue.is_empty() {
            self.jobs.remove(&source);
        } else {
            self.turn.push_back(source);
        }
        if job.is_some() {
            self.len -= 1;
        }
        job
    }

    /// Takes out the jobs nobody waits for any more.
    fn take_stale(&mut self, now: Instant) -> Vec<Job> {
        let mut stale = Vec::new();
        for queue in self.jobs.values_mut() {
            let (gone, kept): (VecDeque<Job>, VecDeque<Job>) =
                queue.drain(..).partition(|job| job.is_stale(now));
            stale.extend(gone);
            *queue = kept;
        }
        self.jobs.retain(|_, queue| !queue.is_empty());
        let jobs = &self.jobs;
        self.turn.retain(|source| jobs.contains_key(source));
        self.len -= stale.len();
        stale
    }

    fn drain(&mut self) -> Vec<Job> {
        self.turn.clear();
        self.len = 0;
        self.jobs.drain().flat_map(|(_, q)| q).collect()
    }
}

struct Inner {
    classes: [Class; 3],
    /// Normal submissions refused (emergency still accepted while draining).
    closed: bool,
    /// Everything refused: the scheduler has taken its last job.
    stopped: bool,
    /// Its capacities now (a reload may change them).
    limits: QueueLimits,
}

/// The queue shared by the handles (producers) and the scheduler (consumer).
pub struct JobQueue {
    inner: Mutex<Inner>,
    notify: Notify,
}

impl JobQueue {
    /// An empty, open queue.
    pub fn new(limits: QueueLimits) -> Self {
        Self {
            inner: Mutex::new(Inner {
                classes: Default::default(),
                closed: false,
                stopped: false,
                limits,
            }),
            notify: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        // A panic while holding this lock cannot leave the queue inconsistent
        // (every method restores its invariants before returning), so a
        // poisoned lock is still usable.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues a job, or gives it back with the reason.
    pub fn push(&self, job: Job) -> Result<(), Refused> {
        let mut inner = self.lock();
        if inner.stopped {
            return Err(Refused::Stopped(job));
        }
        if inner.closed && job.priority != Priority::Emergency {
            return Err(Refused::Closed(job));
        }
        let limits = inner.limits;
        let class = &mut inner.classes[job.priority.index()];
        if !is_safe_stop(&job) {
            if class.counted_len(job.priority) >= limits.per_class {
                return Err(Refused::Full(job, limits.per_class));
            }
            if class.source_len(job.source) >= limits.per_source {
                return Err(Refused::Full(job, limits.per_source));
            }
        }
        class.push(job);
        drop(inner);
        self.notify.notify_one();
        Ok(())
    }

    /// New capacities, from the next submission on; what waits already
    /// stays (a class over its new capacity takes nothing more until it
    /// drains below it).
    pub fn set_limits(&self, limits: QueueLimits) {
        self.lock().limits = limits;
    }

    /// Takes the next job of `priority`, if any.
    pub fn pop(&self, priority: Priority) -> Option<Job> {
        self.lock().classes[priority.index()].pop()
    }

    /// Takes the next job of `priority` that `may_go` (in turn among the
    /// submitters whose first job may), if any.
    pub fn pop_first(&self, priority: Priority, may_go: impl Fn(&Job) -> bool) -> Option<Job> {
        self.lock().classes[priority.index()].pop_first(may_go)
    }

    /// Jobs waiting in each class, most urgent first.
    pub fn depths(&self) -> [usize; 3] {
        let inner = self.lock();
        [
            inner.classes[0].len,
            inner.classes[1].len,
            inner.classes[2].len,
        ]
    }

    /// Refuses normal submissions from now on (emergency jobs still pass).
    pub fn close(&self) {
        self.lock().closed = true;
        self.notify.notify_one();
    }

    /// Accepts submissions again (after the bus came back).
    pub fn open(&self) {
        self.lock().closed = false;
    }

    /// True once [`close`](Self::close) was called and not reopened.
    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    /// Takes the jobs of `priority` whose caller has gone or whose deadline
    /// passed out of the queue: a class filled with abandoned jobs (clients
    /// that sent a request and left, many times over) must not turn away a
    /// caller who is still waiting.
    pub fn take_stale(&self, priority: Priority, now: Instant) -> Vec<Job> {
        self.lock().classes[priority.index()].take_stale(now)
    }

    /// Removes every waiting job (to fail them when the bus goes down).
    pub fn drain(&self) -> Vec<Job> {
        let mut inner = self.lock();
        inner.classes.iter_mut().flat_map(Class::drain).collect()
    }

    /// Refuses every submission from now on, emergencies included, and
    /// hands back what is still waiting: the consumer's last take. In one
    /// step, so no job can slip in after it and wait for ever.
    pub fn stop(&self) -> Vec<Job> {
        let mut inner = self.lock();
        inner.stopped = true;
        inner.classes.iter_mut().flat_map(Class::drain).collect()
    }

    /// True once [`stop`](Self::stop) was called.
    pub fn is_stopped(&self) -> bool {
        self.lock().stopped
    }

    /// Wakes the scheduler as a push would: something else it weighs
    /// changed (a capture was armed).
    pub fn wake(&self) {
        self.notify.notify_one();
    }

    /// Waits until something was pushed (or the queue was closed) since the
    /// last wait; a push before the wait is not lost.
    pub async fn notified(&self) {
        self.notify.notified().await;
    }
}

/// True for the daemon's own safe-stop jobs, which no limit may refuse.
fn is_safe_stop(job: &Job) -> bool {
    job.priority == Priority::Emergency && job.source == SourceId::INTERNAL
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;
    use tokio::sync::oneshot;

    fn job(
        priority: Priority,
        source: u64,
        tag: u8,
    ) -> (Job, oneshot::Receiver<super::super::job::JobResult>) {
        let (tx, rx) = oneshot::channel();
        (
            Job {
                unit: tag,
                pdu: vec![0x03],
                priority,
                source: SourceId(source),
                origin: Default::default(),
                deadline: None,
                max_attempts: None,
                submitted: Instant::now(),
                reply: tx,
            },
            rx,
        )
    }

    #[test]
    fn round_robin_between_sources() {
        let q = JobQueue::new(QueueLimits::default());
        let mut keep = vec![];
        // source 1 floods with 5 jobs, source 2 and 3 send one each.
        for tag in 0..5 {
            let (j, rx) = job(Priority::Command, 1, tag);
            q.push(j).unwrap();
            keep.push(rx);
        }
        for (source, tag) in [(2, 10), (3, 20)] {
            let (j, rx) = job(Priority::Command, source, tag);
            q.push(j).unwrap();
            keep.push(rx);
        }
        let order: Vec<u8> =
            std::iter::from_fn(|| q.pop(Priority::Command).map(|j| j.unit)).collect();
        assert_eq!(order, vec![0, 10, 20, 1, 2, 3, 4]);
        assert_eq!(q.depths(), [0, 0, 0]);
    }

    #[test]
    fn a_held_job_lets_the_next_source_go_and_keeps_its_turn() {
        let q = JobQueue::new(QueueLimits::default());
        let mut keep = vec![];
        for (source, tag) in [(1, 1), (2, 2), (3, 3), (1, 4)] {
            let (j, rx) = job(Priority::Command, source, tag);
            q.push(j).unwrap();
            keep.push(rx);
        }
        // Unit 1 is held: source 1 is passed over, source 2 goes.
        let first = q.pop_first(Priority::Command, |j| j.unit != 1).unwrap();
        assert_eq!(first.unit, 2);
        // Source 1 kept its turn: it goes first once its job may.
        let order: Vec<u8> = std::iter::from_fn(|| q.pop_first(Priority::Command, |_| true))
            .map(|j| j.unit)
            .collect();
        assert_eq!(order, vec![1, 3, 4]);
        assert!(q.pop_first(Priority::Command, |_| true).is_none());
    }

    #[test]
    fn bounds_per_class_and_per_source() {
        let q = JobQueue::new(QueueLimits {
            per_class: 3,
            per_source: 2,
        });
        let mut keep = vec![];
        for (source, expect_ok) in [(1, true), (1, true), (1, false), (2, true), (3, false)] {
            let (j, rx) = job(Priority::Command, source, 0);
            keep.push(rx);
            assert_eq!(q.push(j).is_ok(), expect_ok, "source {source}");
        }
        assert_eq!(q.depths(), [0, 3, 0]);
        // Other classes have their own room.
        let (j, _rx) = job(Priority::Emergency, 1, 0);
        assert!(q.push(j).is_ok());
    }

    #[test]
    fn the_daemons_safe_stops_are_never_refused() {
        let q = JobQueue::new(QueueLimits {
            per_class: 2,
            per_source: 1,
        });
        let mut keep = vec![];
        // A shutdown of ten drives: ten emergency jobs from the daemon at once.
        for unit in 1..=10 {
            let (j, rx) = job(Priority::Emergency, SourceId::INTERNAL.0, unit);
            keep.push(rx);
            assert!(q.push(j).is_ok(), "safe stop of unit {unit} refused");
        }
        // They leave a client's brake its room in the class...
        let (j, rx) = job(Priority::Emergency, 7, 11);
        keep.push(rx);
        assert!(q.push(j).is_ok());
        // ...and the client is still held to its own share.
        let (j, rx) = job(Priority::Emergency, 7, 12);
        keep.push(rx);
        assert!(matches!(q.push(j), Err(Refused::Full(_, 1))));
        // Only emergencies are exempt: the daemon's commands are bounded.
        let (j, rx) = job(Priority::Command, SourceId::INTERNAL.0, 13);
        keep.push(rx);
        assert!(q.push(j).is_ok());
        let (j, rx) = job(Priority::Command, SourceId::INTERNAL.0, 14);
        keep.push(rx);
        assert!(matches!(q.push(j), Err(Refused::Full(_, 1))));
        assert_eq!(q.depths(), [11, 1, 0]);
    }

    #[test]
    fn abandoned_jobs_can_be_taken_out_of_a_full_class() {
        let q = JobQueue::new(QueueLimits {
            per_class: 4,
            per_source: 4,
        });
        // Three callers that left, one still waiting, in one class.
        let mut waiting = None;
        for source in 1..=4 {
            let (j, rx) = job(Priority::Command, source, source as u8);
            q.push(j).unwrap();
            if source == 2 {
                waiting = Some(rx);
            }
        }
        let (j, _rx) = job(Priority::Command, 9, 9);
        assert!(matches!(q.push(j), Err(Refused::Full(..))));
        let stale = q.take_stale(Priority::Command, Instant::now());
        assert_eq!(stale.len(), 3);
        assert_eq!(q.depths(), [0, 1, 0]);
        // The one still waiting keeps its place; the class has room again.
        let (j, _rx9) = job(Priority::Command, 9, 9);
        q.push(j).unwrap();
        let order: Vec<u8> =
            std::iter::from_fn(|| q.pop(Priority::Command).map(|j| j.unit)).collect();
        assert_eq!(order, vec![2, 9]);
        drop(waiting);
    }

    #[test]
    fn closed_queue_still_takes_emergencies() {
        let q = JobQueue::new(QueueLimits::default());
        q.close();
        let (j, _rx1) = job(Priority::Command, 1, 0);
        assert!(matches!(q.push(j), Err(Refused::Closed(_))));
        let (j, _rx2) = job(Priority::Emergency, 1, 0);
        assert!(q.push(j).is_ok());
        assert_eq!(q.drain().len(), 1);
        q.open();
        let (j, _rx3) = job(Priority::Command, 1, 0);
        assert!(q.push(j).is_ok());
    }

    #[test]
    fn a_stopped_queue_hands_back_its_jobs_and_takes_nothing_more() {
        let q = JobQueue::new(QueueLimits::default());
        let (j, _rx1) = job(Priority::Emergency, 0, 1);
        q.push(j).unwrap();
        let (j, _rx2) = job(Priority::Command, 1, 2);
        q.push(j).unwrap();
        let last: Vec<u8> = q.stop().iter().map(|j| j.unit).collect();
        assert_eq!(last, [1, 2]);
        assert!(q.is_stopped());
        // Not even the daemon's own safe stop: nobody would take it.
        let (j, _rx3) = job(Priority::Emergency, 0, 3);
        assert!(matches!(q.push(j), Err(Refused::Stopped(_))));
        q.open();
        let (j, _rx4) = job(Priority::Command, 1, 4);
        assert!(matches!(q.push(j), Err(Refused::Stopped(_))));
        assert_eq!(q.depths(), [0, 0, 0]);
    }
}
