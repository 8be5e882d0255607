//! What can happen to the core, one step at a time, and the plant each case
//! runs on: the steps a case is made of and their random choice.

use std::fmt;

use proptest::prelude::*;

use crate::control::stop_action::StopAction;

/// The drives of the plant, units 1 to `DRIVES` on one bus.
pub(super) const DRIVES: usize = 2;

/// Who sends a write: each face's client, as the core sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Who {
    /// An HTTP client with an operator's token.
    Panel,
    /// An HTTP client with an admin's token.
    Engineer,
    /// An HTTP client with a viewer's token.
    Display,
    /// A WebSocket stream (an operator's token): its leases end with it.
    Hmi,
    /// A Modbus TCP connection whose network has a communication-loss time.
    Plc,
    /// The MQTT session (a Sparkplug host's commands).
    Scada,
    /// An OPC UA session.
    Opcua,
}

impl Who {
    /// Every client, in the order of [`Who::index`].
    pub(super) const ALL: [Who; 7] = [
        Who::Panel,
        Who::Engineer,
        Who::Display,
        Who::Hmi,
        Who::Plc,
        Who::Scada,
        Who::Opcua,
    ];

    /// Its place in [`Who::ALL`].
    pub(super) fn index(self) -> usize {
        self as usize
    }

    /// True for a client whose requests come on a session of the core.
    pub(super) fn has_session(self) -> bool {
        matches!(self, Who::Hmi | Who::Plc | Who::Scada | Who::Opcua)
    }

    /// True for a session with a communication-loss function.
    pub(super) fn comm_loss(self) -> bool {
        matches!(self, Who::Plc | Who::Scada | Who::Opcua)
    }

    /// True for a client that can ask for a lease of its own (`lease_ms`),
    /// renew it and release it.
    pub(super) fn asks_leases(self) -> bool {
        matches!(self, Who::Panel | Who::Engineer | Who::Display | Who::Hmi)
    }
}

/// A write a client sends to a drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Cmd {
    Activate,
    Deactivate,
    Brake,
    SpeedMode,
    TorqueMode,
    /// A speed setpoint, rpm.
    Speed(i16),
    /// A torque setpoint, counts.
    Torque(i16),
}

/// How a drive or the bus misbehaves from now on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Trouble {
    /// The drive answers nothing for this long (ms): powered off.
    Dead(u32),
    /// The next `count` requests to the drive are lost on the way there.
    LostRequests(u8),
    /// The next `count` requests reach the drive, their replies are lost.
    LostReplies(u8),
    /// The next `count` replies of the drive arrive with a bad CRC.
    BadCrc(u8),
}

/// What a `kill -9` (or a power cut) leaves of the safety journal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Damage {
    /// All of it.
    Intact,
    /// Cut at a byte of what was written after the last write went out on
    /// the bus (the fraction, in thousandths, of those bytes that remain):
    /// an append the power cut interrupted, whose write was never sent.
    Torn(u16),
    /// Its magic garbled: not a journal any more.
    Garbled,
    /// Empty (0 bytes): what ext4 can leave of a file written shortly
    /// before a power loss.
    Emptied,
    /// Its header only.
    HeaderOnly,
    /// Gone, the rest of the state directory still there.
    Deleted,
}

impl Damage {
    /// True for a journal that says nothing of what the last run promised
    /// (the start-up then treats the plant's state as unknown).
    pub(super) fn lost(self) -> bool {
        matches!(self, Damage::Emptied | Damage::HeaderOnly | Damage::Deleted)
    }
}

/// How a command that is not live reached the MQTT face.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Stale {
    Retained,
    Queued,
    Older,
}

/// One step of a case.
#[derive(Clone, PartialEq, Eq)]
pub(super) enum Step {
    /// `who` sends `cmd` to drive `drive`, with a lease of `lease_ms` if
    /// it asks for one (HTTP and the stream only).
    Write {
        who: Who,
        drive: usize,
        cmd: Cmd,
        lease_ms: Option<u32>,
    },
    /// The MQTT session hands the core a command for `drive` that did not
    /// come live: retained by the broker, queued for an earlier session,
    /// or older than the connection. Refused: nothing of it is sent.
    Stale {
        drive: usize,
        cmd: Cmd,
        delivery: Stale,
    },
    /// `who` renews the lease on `drive` (with a new length, if given).
    Renew {
        who: Who,
        drive: usize,
        length_ms: Option<u32>,
    },
    /// `who` releases the lease on `drive`: the motor keeps its setpoint.
    Release { who: Who, drive: usize },
    /// A request comes on `who`'s session: its communication-loss leases
    /// run on (for MQTT: the broker is there and the host online).
    Activity { who: Who },
    /// `who` goes away: its session closes (its queued requests dropped
    /// first), or its HTTP requests still waiting are given up.
    Gone { who: Who },
    /// Time passes.
    Advance { ms: u32 },
    /// The bus carries nothing for this long (ms): a long transaction, a
    /// stalled adapter. Jobs wait in the queue.
    Hold { ms: u32 },
    /// A drive misbehaves.
    Fault { drive: usize, trouble: Trouble },
    /// The serial port fails for this long (ms): nothing can be sent.
    BusDown { ms: u32 },
    /// `kill -9`: the process dies (with the job on the wire carried out
    /// by its drive, if `wire`), the journal is left so, and drivegate is
    /// started again after `down_ms`.
    Restart {
        wire: bool,
        damage: Damage,
        down_ms: u32,
    },
}

impl fmt::Debug for Step {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Step::Write {
                who,
                drive,
                cmd,
                lease_ms,
            } => {
                write!(f, "{who:?} writes {cmd:?} to drive {drive}")?;
                match lease_ms {
                    Some(ms) => write!(f, " with a {ms} ms lease"),
                    None => Ok(()),
                }
            }
            Step::Stale {
                drive,
                cmd,
                delivery,
            } => write!(f, "Scada's {delivery:?} command {cmd:?} to drive {drive}"),
            Step::Renew {
                who,
                drive,
                length_ms,
            } => match length_ms {
                Some(ms) => write!(f, "{who:?} renews drive {drive}'s lease for {ms} ms"),
                None => write!(f, "{who:?} renews drive {drive}'s lease"),
            },
            Step::Release { who, drive } => write!(f, "{who:?} releases drive {drive}'s lease"),
            Step::Activity { who } => write!(f, "a request on {who:?}'s session"),
            Step::Gone { who } => write!(f, "{who:?} goes away"),
            Step::Advance { ms } => write!(f, "{ms} ms pass"),
            Step::Hold { ms } => write!(f, "the bus carries nothing for {ms} ms"),
            Step::Fault { drive, trouble } => write!(f, "drive {drive}: {trouble:?}"),
            Step::BusDown { ms } => write!(f, "the port is down for {ms} ms"),
            Step::Restart {
                wire,
                damage,
                down_ms,
            } => write!(
                f,
                "kill -9{}, journal {damage:?}, started again {down_ms} ms later",
                if *wire { " with a job on the wire" } else { "" }
            ),
        }
    }
}

/// The plant's settings for one case.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Setup {
    /// `[safety] on_lease_expiry`.
    pub(super) on_lease_expiry: StopAction,
    /// `[safety] on_unknown_state`.
    pub(super) on_unknown_state: StopAction,
    /// Each communication-loss session's time (ms) and action: the PLC's
    /// network, MQTT, OPC UA.
    pub(super) comm_loss: [(u32, StopAction); 3],
    /// Drives active (and in speed mode) at the start.
    pub(super) active: [bool; DRIVES],
}

impl Setup {
    /// The communication-loss time and action of `who`'s session.
    pub(super) fn comm_loss_of(&self, who: Who) -> Option<(u32, StopAction)> {
        match who {
            Who::Plc => Some(self.comm_loss[0]),
            Who::Scada => Some(self.comm_loss[1]),
            Who::Opcua => Some(self.comm_loss[2]),
            _ => None,
        }
    }
}

fn stop_action() -> impl Strategy<Value = StopAction> {
    prop_oneof![Just(StopAction::ZeroSpeed), Just(StopAction::Brake)]
}

fn comm_loss_action() -> impl Strategy<Value = StopAction> {
    prop_oneof![
        4 => Just(StopAction::ZeroSpeed),
        3 => Just(StopAction::Brake),
        1 => Just(StopAction::None),
    ]
}

/// A case's plant.
pub(super) fn setup() -> impl Strategy<Value = Setup> {
    let comm_loss = || (200u32..=2000, comm_loss_action());
    (
        stop_action(),
        stop_action(),
        [comm_loss(), comm_loss(), comm_loss()],
        [any::<bool>(), any::<bool>()],
    )
        .prop_map(
            |(on_lease_expiry, on_unknown_state, comm_loss, active)| Setup {
                on_lease_expiry,
                on_unknown_state,
                comm_loss,
                active,
            },
        )
}

fn who() -> impl Strategy<Value = Who> {
    prop_oneof![
        3 => Just(Who::Panel),
        1 => Just(Who::Engineer),
        1 => Just(Who::Display),
        2 => Just(Who::Hmi),
        2 => Just(Who::Plc),
        2 => Just(Who::Scada),
        2 => Just(Who::Opcua),
    ]
}

fn leasing() -> impl Strategy<Value = Who> {
    prop_oneof![
        3 => Just(Who::Panel),
        1 => Just(Who::Engineer),
        1 => Just(Who::Display),
        2 => Just(Who::Hmi),
    ]
}

fn cmd() -> impl Strategy<Value = Cmd> {
    prop_oneof![
        6 => prop_oneof![Just(150i16), Just(-80), Just(300), Just(0)].prop_map(Cmd::Speed),
        2 => Just(Cmd::Activate),
        2 => Just(Cmd::Brake),
        1 => Just(Cmd::Deactivate),
        1 => Just(Cmd::SpeedMode),
        1 => Just(Cmd::TorqueMode),
        1 => prop_oneof![Just(200i16), Just(0)].prop_map(Cmd::Torque),
    ]
}

fn lease_ms() -> impl Strategy<Value = Option<u32>> {
    prop_oneof![
        1 => Just(None),
        2 => prop_oneof![Just(100u32), 200u32..=3000].prop_map(Some),
    ]
}

fn trouble() -> impl Strategy<Value = Trouble> {
    prop_oneof![
        (100u32..=8000).prop_map(Trouble::Dead),
        (1u8..=4).prop_map(Trouble::LostRequests),
        (1u8..=4).prop_map(Trouble::LostReplies),
        (1u8..=4).prop_map(Trouble::BadCrc),
    ]
}

fn damage() -> impl Strategy<Value = Damage> {
    prop_oneof![
        12 => Just(Damage::Intact),
        6 => (0u16..=1000).prop_map(Damage::Torn),
        2 => Just(Damage::Garbled),
        1 => Just(Damage::Emptied),
        1 => Just(Damage::HeaderOnly),
        2 => Just(Damage::Deleted),
    ]
}

fn drive() -> impl Strategy<Value = usize> {
    0..DRIVES
}

/// One step.
pub(super) fn step() -> impl Strategy<Value = Step> {
    prop_oneof![
        14 => (who(), drive(), cmd(), lease_ms()).prop_map(|(who, drive, cmd, lease_ms)| {
            Step::Write { who, drive, cmd, lease_ms: lease_ms.filter(|_| who.asks_leases()) }
        }),
        10 => prop_oneof![
            3 => 1u32..=400,
            2 => 400u32..=3000,
            1 => 3000u32..=12000,
        ].prop_map(|ms| Step::Advance { ms }),
        1 => (drive(), cmd(), prop_oneof![Just(Stale::Retained), Just(Stale::Queued), Just(Stale::Older)])
            .prop_map(|(drive, cmd, delivery)| Step::Stale { drive, cmd, delivery }),
        3 => (leasing(), drive(), prop::option::weighted(0.2, 100u32..=3000))
            .prop_map(|(who, drive, length_ms)| Step::Renew { who, drive, length_ms }),
        1 => (leasing(), drive()).prop_map(|(who, drive)| Step::Release { who, drive }),
        3 => prop_oneof![Just(Who::Plc), Just(Who::Scada), Just(Who::Opcua)]
            .prop_map(|who| Step::Activity { who }),
        2 => who().prop_map(|who| Step::Gone { who }),
        2 => (50u32..=2000).prop_map(|ms| Step::Hold { ms }),
        3 => (drive(), trouble()).prop_map(|(drive, trouble)| Step::Fault { drive, trouble }),
        1 => (50u32..=6000).prop_map(|ms| Step::BusDown { ms }),
        2 => (any::<bool>(), damage(), prop_oneof![Just(0u32), 1u32..=20000])
            .prop_map(|(wire, damage, down_ms)| Step::Restart { wire, damage, down_ms }),
    ]
}

/// The most steps of a case (`DRIVEGATE_MODEL_STEPS` sets another).
pub(super) const STEPS: usize = 20;

/// A case: its plant and its steps.
pub(super) fn case() -> impl Strategy<Value = (Setup, Vec<Step>)> {
    let most = std::env::var("DRIVEGATE_MODEL_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(STEPS);
    (setup(), prop::collection::vec(step(), 1..=most))
}
