//! The lease book's public types: what faces and the driver hand in, and
//! what the book hands back (its effects and its news).

use std::sync::Arc;
use std::time::Duration;

use crate::bus::BusError;
use crate::control::caller::{Face, SessionId};
use crate::control::stop_action::StopAction;
use crate::drive::Mode;

/// A lease's identity, unique for the daemon's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct LeaseId(pub u64);

/// A stop's identity, unique for the daemon's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct StopId(pub u64);

/// What holds a lease: a single request (it ends only by time or by a
/// write), or a session whose closing ends it too.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Holder {
    /// A request on its own (a REST call).
    Request,
    /// A session (a WebSocket, a Modbus TCP connection).
    Session(SessionId),
}

impl Holder {
    /// The session, if the lease has one.
    pub fn session(self) -> Option<SessionId> {
        match self {
            Holder::Request => None,
            Holder::Session(s) => Some(s),
        }
    }
}

/// A session's communication-loss function: a lease for each of its
/// setpoints and mode commands, renewed by any request of the session, and
/// ended by `after` of silence or by the session closing, with `action`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommLoss {
    /// Silence that ends its leases.
    pub after: Duration,
    /// What their end sends (`None`: nothing; the end is still shown).
    pub action: StopAction,
    /// The face whose session it is: the ends are counted per face.
    pub face: Face,
}

/// The lease a write takes: its length, its stop, and whether its
/// session's silence ends it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Terms {
    /// Its length.
    pub length: Duration,
    /// Its stop, if not the book's.
    pub action: Option<StopAction>,
    /// A communication-loss lease: renewed by any request of its session.
    pub comm_loss: bool,
}

/// What a lease is asked for with.
#[derive(Debug, Clone)]
pub struct LeaseAsk {
    /// Who takes it (token name, client address).
    pub owner: Arc<str>,
    /// What holds it.
    pub holder: Holder,
    /// The mode its setpoint drives the motor in (kept by the journal; a
    /// stop reads the drive's, and zeroes both setpoints when it cannot).
    pub mode: Mode,
    /// Its length: each renewal pushes the deadline this far.
    pub length: Duration,
    /// How long its setpoint may take to be settled (queue and retries).
    pub allowance: Duration,
    /// Its stop, if not the book's (a face's own setting, such as a
    /// communication-loss action).
    pub action: Option<StopAction>,
    /// A communication-loss lease: any request of its session renews it,
    /// and its end by time reads as communication lost.
    pub comm_loss: bool,
}

/// A lease as faces show it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LeaseView {
    /// Its id.
    pub id: LeaseId,
    /// Who holds it.
    pub owner: Arc<str>,
    /// What holds it.
    pub holder: Holder,
    /// Its length.
    pub length: Duration,
    /// Time left before the stop.
    pub expires_in: Duration,
    /// What its end sends.
    pub action: StopAction,
    /// A communication-loss lease (renewed by any request of its session).
    pub comm_loss: bool,
    /// The face of its session's communication-loss function, when its
    /// session has one (an MQTT session, a Modbus TCP client's network):
    /// such a session is no WebSocket, whichever lease it holds.
    pub comm_loss_face: Option<Face>,
}

/// What [`LeaseBook::grant`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grant {
    /// The new lease.
    pub id: LeaseId,
    /// True when it replaced a lease on the drive.
    pub replaced: bool,
}

/// How a write bears on leases and on the brake.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteKind {
    /// A speed, position or torque setpoint, with the lease granted for it.
    Setpoint {
        /// Its lease, if it came with one.
        lease: Option<Grant>,
        /// The mode whose setpoint it writes: without a lease, it takes
        /// over a failing stop only if that stop's motion is of this mode.
        mode: Mode,
    },
    /// The emergency brake.
    Brake,
    /// A deactivation.
    Deactivate,
    /// Anything else that releases a brake (a mode command), with the
    /// lease granted for it (a communication-loss lease).
    ReleasesBrake {
        /// Its lease, if it came with one.
        lease: Option<Grant>,
    },
}

/// A write in progress, as the book tracks it: taken before the write is
/// sent, given back with its result.
#[derive(Debug, Clone)]
pub struct Ticket {
    pub(super) drive: usize,
    pub(super) kind: WriteKind,
    /// Brakes sent to the drive before this write (for a brake: its own
    /// number).
    pub(super) seen: u64,
    /// Who sent it, in words ("the brake from scada (Modbus TCP)").
    pub(super) by: Arc<str>,
    /// When it was begun, in the book's order of leases and writes: a
    /// lease granted later is newer than it.
    pub(super) order: u64,
}

impl Ticket {
    /// The write's kind.
    pub fn kind(&self) -> WriteKind {
        self.kind
    }
}

/// Why a lease ended with its stop.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StopReason {
    /// Nobody renewed it in time.
    NotRenewed,
    /// Its session sent nothing for this long (communication loss).
    CommLost(Duration),
    /// Its session closed (the text says how: "its WebSocket closed").
    SessionClosed(&'static str),
    /// A brake was sent but the drive did not confirm it: the brake is
    /// applied until it does.
    BrakeUnconfirmed(Arc<str>),
    /// A write that releases the brake landed after a brake.
    BrakeReleased(Arc<str>),
    /// drivegate restarted owing this stop (why, in words).
    Restarted(Arc<str>),
    /// A reload removed the drive from the configuration.
    Removed,
    /// Its setpoint reached the drive after this ended the lease (the
    /// drive had been activated again meanwhile).
    LandedAfter(Arc<str>),
}

impl StopReason {
    /// In words, after "lease ended because".
    pub fn text(&self) -> String {
        match self {
            StopReason::NotRenewed => "it was not renewed in time".to_string(),
            StopReason::CommLost(after) => format!(
                "communication was lost: no request came on its connection for {} ms",
                after.as_millis()
            ),
            StopReason::SessionClosed(how) => (*how).to_string(),
            StopReason::BrakeUnconfirmed(by) => {
                format!("{by} was sent but not confirmed by the drive")
            }
            StopReason::BrakeReleased(by) => {
                format!("{by}, sent before a brake, reached the drive after it")
            }
            StopReason::Restarted(why) => why.to_string(),
            StopReason::Removed => {
                "the drive was removed from the configuration by a reload".to_string()
            }
            StopReason::LandedAfter(what) => {
                format!("{what} ended it, and its setpoint reached the drive afterwards")
            }
        }
    }
}

/// A stop the driver must send.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StopOrder {
    /// Index of the drive in the plant.
    pub drive: usize,
    /// The stop.
    pub id: StopId,
    /// Who held the lease it ends (`None`: a brake applied again).
    pub owner: Option<Arc<str>>,
    /// What to send.
    pub action: StopAction,
    /// The mode of the lease it ends (a stop reads the drive's own, and
    /// zeroes both setpoints when it cannot).
    pub mode: Mode,
    /// 1 for the first try.
    pub attempt: u32,
}

/// What one try of a stop came to.
#[derive(Debug, Clone, PartialEq)]
pub enum StopResult {
    /// The drive confirmed what was sent.
    Confirmed,
    /// Nothing to send: `action` in this mode already holds the motor.
    NothingToSend {
        /// The stop action.
        action: StopAction,
        /// The drive's mode, if it could be read.
        mode: Option<Mode>,
    },
    /// The lease's action is "none".
    ActionNone,
    /// The try failed.
    Failed(BusError),
}

/// What became of one try of a stop, as the driver reports it.
#[derive(Debug, Clone, PartialEq)]
pub struct StopReport {
    /// What was sent, in words, if anything may have reached the drive.
    pub sent: Option<String>,
    /// What the drive confirmed, or why the try failed.
    pub result: StopResult,
    /// True when something that can release a brake may have reached the
    /// drive (a zero-speed setpoint).
    pub released_brake: bool,
}

impl StopReport {
    /// True unless the try failed.
    pub fn is_ok(&self) -> bool {
        !matches!(self.result, StopResult::Failed(_))
    }

    /// The try in words: what the drive confirmed, or why it failed.
    pub fn text(&self) -> String {
        match (&self.result, &self.sent) {
            (StopResult::Confirmed, Some(sent)) => format!("{sent} confirmed by the drive"),
            (StopResult::Confirmed, None) => "confirmed by the drive".to_string(),
            (StopResult::NothingToSend { action, mode }, _) => format!(
                "nothing to send: {} in {} mode holds the motor",
                action.name(),
                mode.map_or("unknown", |m| m.name())
            ),
            (StopResult::ActionNone, _) => {
                "the lease's action is \"none\": nothing sent".to_string()
            }
            (StopResult::Failed(error), _) => error.to_string(),
        }
    }
}

/// News of a lease, for the stream and the event log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LeaseEvent {
    /// A lease ended without a stop: released, replaced, or ended by a
    /// write that stops the motor itself.
    Ended {
        /// Drive index.
        drive: usize,
        /// Who held it.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// Why, in words.
        reason: String,
    },
    /// A lease ended with its stop, and the stop's first try ended (or
    /// something took over before it was sent).
    Expired {
        /// Drive index.
        drive: usize,
        /// Who held it.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// Why it ended.
        reason: String,
        /// The stop action.
        action: StopAction,
        /// What was sent, if anything.
        sent: Option<String>,
        /// True when the stop was carried out (or nothing was needed).
        ok: bool,
        /// The drive's answer, or why it failed.
        result: String,
        /// True when drivegate keeps trying.
        retrying: bool,
    },
    /// A stop that failed at first ended: carried out, or taken over.
    StopSettled {
        /// Drive index.
        drive: usize,
        /// Who held the lease.
        owner: Arc<str>,
        /// What held it.
        holder: Holder,
        /// The stop action.
        action: StopAction,
        /// What was sent at last, if anything.
        sent: Option<String>,
        /// True when the drive confirmed it.
        stopped: bool,
        /// Tries made.
        attempts: u32,
        /// The drive's answer, or what took over.
        result: String,
    },
}

impl LeaseEvent {
    /// The drive it concerns.
    pub fn drive(&self) -> usize {
        match self {
            LeaseEvent::Ended { drive, .. }
            | LeaseEvent::Expired { drive, .. }
            | LeaseEvent::StopSettled { drive, .. } => *drive,
        }
    }

    /// The holder of the lease it concerns.
    pub fn holder(&self) -> Holder {
        match self {
            LeaseEvent::Ended { holder, .. }
            | LeaseEvent::Expired { holder, .. }
            | LeaseEvent::StopSettled { holder, .. } => *holder,
        }
    }
}

/// What the book asks of its driver.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Effect {
    /// Send a stop and report with [`LeaseBook::stop_tried`].
    Stop(StopOrder),
    /// Publish this.
    Event(LeaseEvent),
    /// A communication-loss lease on `drive` ended: by silence (`closed`
    /// false) or by its session closing. Counted per bus.
    CommLoss {
        /// Drive index.
        drive: usize,
        /// True when its session closed.
        closed: bool,
        /// The face of the session that held it.
        face: Face,
    },
}

/// Why there is no lease to renew or release, in words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NoLease(pub String);

/// How the end of a session reads when nothing more precise is known.
pub(super) const SESSION_CLOSED: &str = "its session closed";
