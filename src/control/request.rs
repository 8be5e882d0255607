//! What a face asks the core to write, in one form whichever face it came
//! from: one of the manual's messages (typed faces), or a Modbus PDU with
//! what the register table makes of it (passthrough faces); with the
//! lease, override and confirmation that come with it.

use std::time::{Duration, Instant};

use super::policy::{self, Meaning, StillReason};
use super::written::{describe, describe_pdu};
use crate::control::stop_action::StopAction;
use crate::drive::writes::{self, PduMeaning};
use crate::drive::{DriveRequest, RangeError};

/// Where a write goes: a bus, a unit on it (0: every drive, a broadcast),
/// and the configured drive at that unit, if there is one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Target {
    /// Index of the bus in the plant.
    pub bus: usize,
    /// Unit address; 0 for a broadcast.
    pub unit: u8,
    /// Index of the configured drive in the plant.
    pub drive: Option<usize>,
}

/// The write itself.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Write {
    /// One of the manual's messages.
    Drive(DriveRequest),
    /// A Modbus write PDU; the drive's reply goes back as it came.
    Pdu {
        /// Function code and data, as the client sent them.
        pdu: Vec<u8>,
        /// What the drive will make of it.
        meaning: PduMeaning,
        /// What is sent, when not `pdu` itself: the drives have 0x06 and
        /// 0x10 only, so a mask write with an AND mask of 0 goes as a 0x06
        /// and a read/write multiple's write as a 0x10
        /// ([`writes::carried`]).
        sent: Option<Vec<u8>>,
    },
}

impl Write {
    /// A write PDU to a drive (or a broadcast), decoded with the drive's
    /// register table.
    pub fn pdu(pdu: Vec<u8>) -> Self {
        let meaning = writes::decode(&pdu);
        let sent = writes::carried(&pdu);
        Write::Pdu { pdu, meaning, sent }
    }

    /// A write PDU to a unit that is not a configured drive (another
    /// device on the bus): the drive's register table says nothing about
    /// it, so it is sent as it came and its meaning is unknown, whatever
    /// its addresses (or not decoded at all, for other function codes).
    pub fn device_pdu(pdu: Vec<u8>) -> Self {
        Write::Pdu {
            meaning: writes::decode_for_device(&pdu),
            pdu,
            sent: None,
        }
    }

    /// True for one whole message of the manual with valid values (not a
    /// part of one, nor values the drive would refuse).
    pub fn is_message(&self) -> bool {
        matches!(
            self,
            Write::Drive(_)
                | Write::Pdu {
                    meaning: PduMeaning::Message(_),
                    ..
                }
        )
    }

    /// What it means for the motor.
    pub fn meaning(&self) -> Meaning {
        match self {
            Write::Drive(r) => policy::of_request(r),
            Write::Pdu { meaning, .. } => policy::of_pdu(meaning),
        }
    }

    /// In words, for the audit log.
    pub fn describe(&self) -> String {
        match self {
            Write::Drive(r) => describe(r),
            Write::Pdu { pdu, meaning, sent } => describe_pdu(pdu, meaning, sent.as_deref()),
        }
    }

    /// The PDU to send.
    pub fn encode(&self) -> Result<Vec<u8>, RangeError> {
        match self {
            Write::Drive(r) => r.pdu(),
            Write::Pdu { pdu, sent, .. } => Ok(sent.as_ref().unwrap_or(pdu).clone()),
        }
    }
}

/// A write with what comes with it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ControlRequest {
    /// The write.
    pub write: Write,
    /// For a setpoint: a lease of this length (the motor is stopped unless
    /// it is renewed in time).
    pub lease: Option<Duration>,
    /// The lease's stop, if not `[safety] on_lease_expiry`.
    pub lease_action: Option<StopAction>,
    /// The face's override of the still-check (HTTP `force`, a Modbus TCP
    /// network's `allow_saves_while_moving`): write even while the motor
    /// turns.
    pub force: bool,
    /// For an address broadcast: the caller confirmed that only one drive
    /// is connected to the bus.
    pub single_drive: bool,
    /// For a function code the core cannot decode: the face's
    /// configuration lets it through unchecked for an admin (`[modbus_tcp]
    /// raw_functions`); refused for everyone otherwise.
    pub unchecked: bool,
    /// The caller's own reason for the write to need standstill, beside
    /// what the write means (drivegate applying declared settings).
    pub still: Option<StillReason>,
    /// When its face received it from its client, if it may have waited
    /// before reaching the core (behind the connection's earlier
    /// requests): that wait counts against the bus's `queue_timeout_ms`
    /// ([`super::live::queue_wait`]).
    pub received: Option<Instant>,
}

impl ControlRequest {
    /// A write with no lease, override or confirmation.
    pub fn new(write: Write) -> Self {
        ControlRequest {
            write,
            lease: None,
            lease_action: None,
            force: false,
            single_drive: false,
            unchecked: false,
            still: None,
            received: None,
        }
    }

    /// Received by its face at `at`: its wait for the bus counts from
    /// then.
    pub fn received(mut self, at: Instant) -> Self {
        self.received = Some(at);
        self
    }

    /// What the write means, with the caller's own need for standstill.
    pub fn meaning(&self) -> Meaning {
        let mut meaning = self.write.meaning();
        meaning.still = meaning.still.or(self.still);
        meaning
    }

    /// Refused while the motor turns, for `reason`, whatever it writes.
    pub fn at_standstill(mut self, reason: StillReason) -> Self {
        self.still = Some(reason);
        self
    }

    /// One of the manual's messages.
    pub fn drive(request: DriveRequest) -> Self {
        Self::new(Write::Drive(request))
    }

    /// With a lease of `length` (if any).
    pub fn with_lease(mut self, length: Option<Duration>) -> Self {
        self.lease = length;
        self
    }

    /// With a stop of its own for the lease.
    pub fn with_lease_action(mut self, action: Option<StopAction>) -> Self {
        self.lease_action = action;
        self
    }

    /// With the still-check overridden (or not).
    pub fn forced(mut self, force: bool) -> Self {
        self.force = force;
        self
    }

    /// With the face's leave (or not) to send a function code the core
    /// cannot decode, unchecked, for an admin.
    pub fn unchecked(mut self, allowed: bool) -> Self {
        self.unchecked = allowed;
        self
    }

    /// With the single-drive confirmation of an address broadcast.
    pub fn single_drive(mut self, confirmed: bool) -> Self {
        self.single_drive = confirmed;
        self
    }
}
