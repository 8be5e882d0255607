//! What can go wrong with a job on the bus, in words a plant engineer can act on,
//! with the cause kept typed: whether the request reached the wire (the
//! variant), the port's I/O error kind, the fault of the last reply. The
//! control core decides on these, never on the words.

use std::fmt;
use std::io;
use std::time::Duration;

use crate::drive::ReplyError;
use crate::modbus::ExceptionCode;

use super::fault::Fault;
use super::priority::Priority;

/// Why a serial port carries no requests.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PortCause {
    /// The kind of the I/O error the port failed with, if it was one (not
    /// for a bus that never started or has stopped).
    pub kind: Option<io::ErrorKind>,
    /// What the system or drivegate said, for people.
    pub detail: String,
}

impl PortCause {
    /// The port failed with `error`; `detail` says so in words.
    pub fn io(error: &io::Error, detail: impl Into<String>) -> Self {
        PortCause {
            kind: Some(error.kind()),
            detail: detail.into(),
        }
    }

    /// A cause that is no I/O error (the bus never started, or stopped).
    pub fn other(detail: impl Into<String>) -> Self {
        PortCause {
            kind: None,
            detail: detail.into(),
        }
    }
}

impl fmt::Display for PortCause {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.detail)
    }
}

impl From<String> for PortCause {
    fn from(detail: String) -> Self {
        PortCause::other(detail)
    }
}

/// Why a job submitted to a bus did not produce a confirmed reply.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BusError {
    /// The queue for this priority is full; nothing was sent.
    #[error(
        "bus {bus} is busy: the {priority} queue is full ({capacity} waiting); try again shortly"
    )]
    Busy {
        /// Bus name.
        bus: String,
        /// Priority class whose queue was full.
        priority: Priority,
        /// The queue's capacity.
        capacity: usize,
    },
    /// The serial port is closed (adapter unplugged or failing; it is being
    /// reopened) or failed before the request was written: nothing was sent.
    #[error("bus {bus} is down: {reason}")]
    BusDown {
        /// Bus name.
        bus: String,
        /// Why the port is closed.
        reason: PortCause,
    },
    /// The serial port failed after the request had (at least partly) gone
    /// out: the drive may have received it and carried it out, but its
    /// reply was lost with the port.
    #[error(
        "bus {bus} went down after the request was sent to the drive at unit {unit} ({reason}): the drive may have carried it out; check its state before repeating it"
    )]
    BusDownAfterSend {
        /// Bus name.
        bus: String,
        /// Unit address the request went to (0: broadcast).
        unit: u8,
        /// What happened to the port.
        reason: PortCause,
    },
    /// The drive did not answer in time, on every attempt.
    #[error("drive at unit {unit} did not answer ({attempts} attempt(s), {timeout_ms} ms each)")]
    Timeout {
        /// Unit address.
        unit: u8,
        /// Attempts made.
        attempts: u8,
        /// Response timeout of each attempt.
        timeout_ms: u64,
    },
    /// Every attempt got a corrupted or unrelated reply.
    #[error("drive at unit {unit} gave no valid reply in {attempts} attempt(s): {}", fault.describe())]
    BadReply {
        /// Unit address.
        unit: u8,
        /// Attempts made.
        attempts: u8,
        /// What was wrong with the last reply.
        fault: Fault,
    },
    /// The drive refused the request with a Modbus exception.
    #[error("drive at unit {unit} refused the request: {code}")]
    Exception {
        /// Unit address.
        unit: u8,
        /// The exception code the drive sent.
        code: ExceptionCode,
    },
    /// The drive's reply was valid Modbus but did not confirm this request.
    #[error("drive at unit {unit} answered something else: {detail}")]
    Unconfirmed {
        /// Unit address.
        unit: u8,
        /// What did not match.
        detail: &'static str,
    },
    /// The job's deadline passed while it waited; it never reached the wire.
    #[error("gave up after waiting {waited:?} for the bus; the request was not sent")]
    Expired {
        /// Time spent in the queue.
        waited: Duration,
    },
    /// The daemon is stopping and takes no new work.
    #[error("the daemon is shutting down; the request was not sent")]
    ShuttingDown,
    /// The request cannot be put on the wire at all.
    #[error("invalid request: {0}")]
    Invalid(String),
}

impl BusError {
    /// Maps a typed reply check failure for `unit`.
    pub fn from_reply(unit: u8, err: ReplyError) -> Self {
        match err {
            ReplyError::Exception(code) => BusError::Exception { unit, code },
            ReplyError::Mismatch(detail) => BusError::Unconfirmed { unit, detail },
        }
    }

    /// True when the drive answered and confirmed nothing: its exception,
    /// or a reply that does not confirm the request.
    pub fn answered(&self) -> bool {
        matches!(
            self,
            BusError::Exception { .. } | BusError::Unconfirmed { .. }
        )
    }

    /// True when the request surely never reached the wire.
    pub fn not_sent(&self) -> bool {
        matches!(
            self,
            BusError::Busy { .. }
                | BusError::BusDown { .. }
                | BusError::Expired { .. }
                | BusError::ShuttingDown
                | BusError::Invalid(_)
        )
    }
}
