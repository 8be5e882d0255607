//! Who watches a bus from above it: the bus defines what it shows and
//! asks, the observers (the bus monitor, the scope) implement it, so the
//! bus never names them.
//!
//! - A [`WireObserver`] is shown every frame the master sends or receives,
//!   on the bus thread, through the master's [`WireTap`](super::tap::WireTap).
//! - A [`PollSteering`] may decide which drive's status is read next (the
//!   scope while a capture runs); without one the poll plan decides.
//!
//! Both are called on the bus thread between transactions: they must not
//! block or wait.

use std::fmt;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::fault::Fault;
use super::origin::Origin;

/// A request the master put on the wire.
#[derive(Debug, Clone, Copy)]
pub struct Sent<'a> {
    /// The unit addressed (0: broadcast).
    pub unit: u8,
    /// Attempt number, 1 for the first.
    pub attempt: u8,
    /// The whole frame: unit, PDU, CRC.
    pub frame: &'a [u8],
    /// When its first byte went out.
    pub at: Instant,
    /// The silence before it: from the end of the last frame (as the master
    /// received or sent it) to its first byte.
    pub silence: Duration,
    /// Who caused the transaction.
    pub origin: &'a Origin,
}

/// The end of the wait for a reply to the request in progress.
#[derive(Debug, Clone, Copy)]
pub struct Received<'a> {
    /// The unit the request was for.
    pub unit: u8,
    /// Attempt number, 1 for the first.
    pub attempt: u8,
    /// Who caused the transaction.
    pub origin: &'a Origin,
    /// The first bytes of the request (at most
    /// [`REQUEST_HEAD`](super::tap::REQUEST_HEAD)).
    pub request: &'a [u8],
    /// Whether `request` is the whole request.
    pub request_whole: bool,
    /// When the request's last byte left the wire.
    pub request_end: Instant,
    /// The bytes framed; empty when the wait ended without a whole frame.
    pub frame: &'a [u8],
    /// When the reply's last byte arrived (or the wait ended).
    pub end: Instant,
    /// What was wrong with it (`None`: a valid frame, maybe an exception).
    pub fault: Option<&'a Fault>,
}

/// Shown every frame on the wire.
pub trait WireObserver: Send + Sync {
    /// A request went out.
    fn sent(&self, sent: &Sent<'_>);
    /// The wait for its reply ended.
    fn received(&self, received: &Received<'_>);
    /// `bytes` that belong to no reply arrived at `at`; `unit` is the unit
    /// of the last transaction, to which they are put down.
    fn stray(&self, unit: u8, bytes: &[u8], at: Instant);
}

/// What the scheduler should do instead of its poll plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Steer {
    /// Read this unit's status.
    Poll(u8),
    /// Nothing is due: look again at this time (or when a job arrives).
    Wait(Instant),
}

/// May take the polling over from the poll plan for a while.
pub trait PollSteering: Send + Sync {
    /// What to poll at `now`; `None` leaves it to the poll plan.
    /// `plan_due` and `offline` are the poll plan's and the status cache's
    /// views of a unit.
    fn steer(
        &self,
        now: Instant,
        plan_due: &dyn Fn(u8) -> bool,
        offline: &dyn Fn(u8) -> bool,
    ) -> Option<Steer>;
    /// `unit`'s status was polled at `now`.
    fn polled(&self, unit: u8, now: Instant);
    /// Who a poll of `unit` is for.
    fn poll_origin(&self, unit: u8) -> Origin;
}

/// The observers of one bus, given to it when it starts.
#[derive(Clone, Default)]
pub struct Observers {
    /// Shown every frame, in this order.
    pub wire: Vec<Arc<dyn WireObserver>>,
    /// Steers the polling while it wants to.
    pub steering: Option<Arc<dyn PollSteering>>,
}

impl fmt::Debug for Observers {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Observers")
            .field("wire", &self.wire.len())
            .field("steering", &self.steering.is_some())
            .finish()
    }
}
