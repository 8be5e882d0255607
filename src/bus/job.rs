//! A job: one Modbus request waiting for its turn on the wire.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use super::error::BusError;
use super::origin::Origin;
pub use super::priority::Priority;

/// Who submitted a job: queues are fair between sources, so one flooding
/// client (a Modbus TCP connection, say) cannot starve the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SourceId(pub u64);

static NEXT_SOURCE: AtomicU64 = AtomicU64::new(1);

impl SourceId {
    /// The daemon itself (safe-stop actions, leases, internal reads). Its
    /// emergency jobs (safe stops) are never refused for queue limits, so
    /// it must not be used for work a client can multiply.
    pub const INTERNAL: SourceId = SourceId(0);

    /// A new, never used source id.
    pub fn new_unique() -> SourceId {
        SourceId(NEXT_SOURCE.fetch_add(1, Ordering::Relaxed))
    }
}

/// What the wire gave back for a job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Exchange {
    /// The reply PDU (function code onward, CRC stripped); an exception reply
    /// is returned as is. Empty for a broadcast.
    pub reply: Vec<u8>,
    /// Attempts it took (1 = no retry).
    pub attempts: u8,
    /// Time spent waiting in the queue.
    pub queued: Duration,
    /// Time from the first byte sent to the reply's last byte received.
    pub on_wire: Duration,
}

/// The result sent back to a job's submitter.
pub type JobResult = Result<Exchange, BusError>;

/// A request waiting for the wire.
#[derive(Debug)]
pub struct Job {
    /// Unit address (0 = broadcast).
    pub unit: u8,
    /// The request PDU (function code onward).
    pub pdu: Vec<u8>,
    /// Priority class.
    pub priority: Priority,
    /// Who asked, for fair queuing.
    pub source: SourceId,
    /// What caused it, for the bus monitor and the scope's write trigger.
    pub origin: Origin,
    /// Drop the job unsent once this passes.
    pub deadline: Option<Instant>,
    /// Attempts allowed, overriding the bus's retries (e.g. 1 for an offline drive).
    pub max_attempts: Option<u8>,
    /// When it was submitted.
    pub submitted: Instant,
    /// Where the result goes; a closed receiver means the caller has gone.
    pub reply: oneshot::Sender<JobResult>,
}

impl Job {
    /// True when nobody waits for the result any more or its deadline passed:
    /// such a job is dropped before it reaches the wire.
    pub fn is_stale(&self, now: Instant) -> bool {
        self.reply.is_closed() || self.deadline.is_some_and(|d| now >= d)
    }

    /// Completes the job.
    pub fn finish(self, result: JobResult) {
        // The caller may have gone; then nobody needs the result.
        let _ = self.reply.send(result);
    }
}
