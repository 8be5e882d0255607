//! What became of a write, as typed values from the bus to the faces:
//! whether it reached the wire, whether the drive confirmed it, and why
//! not. Safety decisions read these, never a face's rendering of them.

use super::policy::{Role, StillReason};
use crate::bus::BusError;
use crate::drive::DriveReply;
use crate::modbus::ExceptionCode;

/// Whether a write reached the drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Applied {
    /// The drive confirmed it.
    Yes,
    /// Surely not: it was never sent, or the drive refused it.
    No,
    /// It was sent, but not confirmed: it may have been carried out.
    Maybe,
}

/// A write carried out.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// The drive confirmed it.
    Confirmed {
        /// The drive's reply PDU, as it came.
        reply: Vec<u8>,
        /// The typed reply, for one of the manual's messages.
        typed: Option<DriveReply>,
    },
    /// Sent as a broadcast: drives do not reply.
    Broadcast,
}

/// A rule that refused a write before anything was sent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Rule {
    /// The caller's role does not allow it.
    Role {
        /// The role it needs.
        needed: Role,
        /// The caller's.
        has: Role,
    },
    /// It needs the motor standing still, and the motor turns.
    Moving {
        /// What needs it.
        still: StillReason,
        /// The speed read, rpm.
        speed_rpm: i16,
    },
    /// An address broadcast without the caller's confirmation that only
    /// one drive is connected to the bus: every drive that hears it takes
    /// the address.
    SharedBusAddress,
    /// A lease length outside `[safety] lease_min_ms` to `lease_max_ms`.
    LeaseLength {
        /// The length asked for, ms.
        asked: u64,
        /// The shortest allowed, ms.
        min: u64,
        /// The longest allowed, ms.
        max: u64,
    },
    /// A setpoint to a drive that is not active (the drive would refuse
    /// it itself).
    NotActive,
    /// A write whose effect the core cannot decode (a function code no
    /// register table describes, a mask write keeping bits of a value
    /// nobody read): no rule can be checked on it, so it is refused for
    /// every role, unless the face lets an admin send the function code
    /// unchecked (never as a broadcast).
    NotDecoded,
    /// A command that did not come live from its sender (an MQTT retained
    /// message, one queued for an earlier session): nothing of it is
    /// carried out ([`super::live`]).
    NotLive,
}

impl Rule {
    /// Stable name for metrics and the audit log.
    pub fn name(&self) -> &'static str {
        match self {
            Rule::Role { .. } => "role",
            Rule::Moving { .. } => "moving",
            Rule::SharedBusAddress => "shared-bus-address",
            Rule::NotActive => "not-active",
            Rule::LeaseLength { .. } => "lease-length",
            Rule::NotDecoded => "not-decoded",
            Rule::NotLive => "not-live",
        }
    }
}

/// A write refused by a rule, with the words for the caller.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refusal {
    /// The rule.
    pub rule: Rule,
    /// What happened and what to do, for a plant engineer.
    pub detail: String,
}

/// Why a write was not carried out, or is not known to be.
#[derive(Debug, Clone, PartialEq)]
pub enum Failure {
    /// Refused by a rule; nothing was sent.
    Refused(Refusal),
    /// The drive's state could not be read for a check the write needs;
    /// the write was not sent.
    CheckFailed(BusError),
    /// The bus did not send it.
    NotSent(BusError),
    /// The drive refused it with a Modbus exception: not carried out.
    DriveRefused {
        /// The unit that answered.
        unit: u8,
        /// Its exception code.
        code: ExceptionCode,
        /// Its reply PDU.
        reply: Vec<u8>,
    },
    /// Sent, but not confirmed: it may have been carried out.
    Unknown {
        /// What went wrong.
        error: BusError,
        /// The reply, when the drive answered something else.
        reply: Option<Vec<u8>>,
    },
}

impl Failure {
    /// Whether the write may have reached the drive.
    pub fn applied(&self) -> Applied {
        match self {
            Failure::Unknown { .. } => Applied::Maybe,
            _ => Applied::No,
        }
    }

    /// The failure as a bus error (a refusal has none), for faces that
    /// render bus errors.
    pub fn bus_error(&self) -> Option<BusError> {
        match self {
            Failure::Refused(_) => None,
            Failure::CheckFailed(e) | Failure::NotSent(e) | Failure::Unknown { error: e, .. } => {
                Some(e.clone())
            }
            Failure::DriveRefused { unit, code, .. } => Some(BusError::Exception {
                unit: *unit,
                code: *code,
            }),
        }
    }
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Failure::Refused(r) => write!(f, "refused: {}", r.detail),
            Failure::CheckFailed(e) => {
                write!(
                    f,
                    "not sent: the drive's state could not be read first: {e}"
                )
            }
            Failure::NotSent(e) | Failure::Unknown { error: e, .. } => write!(f, "{e}"),
            Failure::DriveRefused { code, .. } => write!(f, "the drive refused it: {code}"),
        }
    }
}

/// What a finished write came to.
pub type WriteResult = Result<Outcome, Failure>;

/// Whether the result of a write means it reached the drive.
pub fn applied(result: &WriteResult) -> Applied {
    match result {
        Ok(Outcome::Confirmed { .. }) => Applied::Yes,
        // Nobody answers a broadcast: it went out, whether every drive
        // heard it nobody knows.
        Ok(Outcome::Broadcast) => Applied::Maybe,
        Err(f) => f.applied(),
    }
}
