//! How a Modbus TCP request ended, for the metrics; the gateway exception
//! a bus failure is answered with (Modbus application protocol, section 7:
//! 0x0A and 0x0B are the gateway codes); and the exception each rule of the
//! control core is answered with:
//!
//! | refused because | exception |
//! |---|---|
//! | the network's role does not allow the write | 0x01 illegal function |
//! | an address broadcast to a bus of several drives | 0x01 illegal function |
//! | a save, factory reset, address setting or calibration while the motor turns | 0x06 server device busy |
//! | a setpoint to a drive that is not active | 0x04 server device failure, as the drive answers it |
//! | a function code the core cannot decode (not in `raw_functions`, or to unit 0), a mask write keeping bits of the current value | 0x01 illegal function |

use crate::bus::BusError;
use crate::control::{Failure, Role, Rule};
use crate::listed::listed_enum;
use crate::modbus::ExceptionCode;

listed_enum! {
    /// The outcome label of one request.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Outcome {
        /// The drive answered normally.
        Ok,
        /// The drive answered with its own exception (passed through).
        Exception,
        /// Answered from the polled copy, without the bus.
        Cached,
        /// Sent as a broadcast (nobody answers those).
        Broadcast,
        /// 0x0B: no valid reply after the retries.
        GatewayTimeout,
        /// 0x0A: no bus for this unit, or the bus is down or stopping.
        PathUnavailable,
        /// 0x06: the bus queue was full or the request waited too long.
        Busy,
        /// 0x01: a write from a viewer (a read-only listener, or a viewer
        /// network).
        ReadOnly,
        /// 0x01: a write the client's role does not allow.
        Forbidden,
        /// 0x06: a write that needs standstill while the motor turns.
        Moving,
        /// 0x01: a broadcast the gateway will not send (a read, or an address
        /// setting on a bus of several drives).
        Refused,
        /// 0x03: the request's shape is not what its function code requires.
        Invalid,
        /// 0x01: a write the control core cannot decode (a function code
        /// not listed in `raw_functions`, or sent to unit 0; a mask write
        /// keeping bits of the register's current value).
        NotDecoded,
        /// The client disconnected before the reply.
        Cancelled,
    }
}

impl Outcome {
    /// Stable label for `drivegate_modbus_tcp_requests_total`.
    pub fn label(self) -> &'static str {
        match self {
            Outcome::Ok => "ok",
            Outcome::Exception => "exception",
            Outcome::Cached => "cached",
            Outcome::Broadcast => "broadcast",
            Outcome::GatewayTimeout => "gateway_timeout",
            Outcome::PathUnavailable => "path_unavailable",
            Outcome::Busy => "busy",
            Outcome::ReadOnly => "read_only",
            Outcome::Forbidden => "forbidden",
            Outcome::Moving => "moving",
            Outcome::Refused => "refused",
            Outcome::Invalid => "invalid",
            Outcome::NotDecoded => "not_decoded",
            Outcome::Cancelled => "cancelled",
        }
    }
}

/// The exception a client gets for a request the bus could not carry out.
pub fn gateway_exception(error: &BusError) -> (ExceptionCode, Outcome) {
    match error {
        // Sent, and every attempt went unanswered or garbled; or sent, and
        // the port failed before the reply: either way the drive may have
        // carried it out, which 0x0A (never routed) would deny.
        BusError::Timeout { .. }
        | BusError::BadReply { .. }
        | BusError::BusDownAfterSend { .. } => (
            ExceptionCode::GATEWAY_TARGET_FAILED,
            Outcome::GatewayTimeout,
        ),
        // No way to the drive now.
        BusError::BusDown { .. } | BusError::ShuttingDown => (
            ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
            Outcome::PathUnavailable,
        ),
        // Never sent: the queue was full or the bus too busy to get to it.
        BusError::Busy { .. } | BusError::Expired { .. } => {
            (ExceptionCode::SERVER_DEVICE_BUSY, Outcome::Busy)
        }
        // Passthrough returns the drive's exception as a reply; these come
        // only from typed requests, never from this face.
        BusError::Exception { code, .. } => (*code, Outcome::Exception),
        BusError::Unconfirmed { .. } => (
            ExceptionCode::GATEWAY_TARGET_FAILED,
            Outcome::GatewayTimeout,
        ),
        BusError::Invalid(_) => (ExceptionCode::ILLEGAL_DATA_VALUE, Outcome::Invalid),
    }
}

/// The reply to a write the control core did not carry out: the drive's
/// own reply when it answered, else the exception for the rule or the bus
/// failure.
pub fn failure_reply(function: u8, failure: &Failure) -> (Vec<u8>, Outcome) {
    match failure {
        Failure::Refused(refusal) => {
            let (code, outcome) = match &refusal.rule {
                Rule::Role {
                    has: Role::Viewer, ..
                } => (ExceptionCode::ILLEGAL_FUNCTION, Outcome::ReadOnly),
                Rule::Role { .. } => (ExceptionCode::ILLEGAL_FUNCTION, Outcome::Forbidden),
                Rule::SharedBusAddress => (ExceptionCode::ILLEGAL_FUNCTION, Outcome::Refused),
                // A Modbus TCP client asks for no lease length (its
                // network's comm_loss_ms is checked with the config).
                Rule::LeaseLength { .. } => (ExceptionCode::ILLEGAL_DATA_VALUE, Outcome::Refused),
                Rule::Moving { .. } => (ExceptionCode::SERVER_DEVICE_BUSY, Outcome::Moving),
                // What the drive itself answers.
                Rule::NotActive => (ExceptionCode::SERVER_DEVICE_FAILURE, Outcome::Exception),
                Rule::NotDecoded => (ExceptionCode::ILLEGAL_FUNCTION, Outcome::NotDecoded),
                // A request on a connection is live (its lateness is the
                // bus's queue timeout, 0x06).
                Rule::NotLive => (ExceptionCode::SERVER_DEVICE_BUSY, Outcome::Refused),
            };
            (exception_pdu(function, code), outcome)
        }
        // The drive's own code, under the client's function (a mask write
        // went to the drive as a 0x06, a read/write multiple as a 0x10).
        Failure::DriveRefused { code, .. } => (exception_pdu(function, *code), Outcome::Exception),
        Failure::Unknown {
            reply: Some(reply), ..
        } => (reply.clone(), Outcome::Ok),
        Failure::CheckFailed(e) | Failure::NotSent(e) | Failure::Unknown { error: e, .. } => {
            let (code, outcome) = gateway_exception(e);
            (exception_pdu(function, code), outcome)
        }
    }
}

/// An exception reply PDU for `function`.
pub fn exception_pdu(function: u8, code: ExceptionCode) -> Vec<u8> {
    vec![function | crate::modbus::function::EXCEPTION_BIT, code.0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::Priority;
    use std::time::Duration;

    #[test]
    fn every_outcome_is_listed_once_with_its_own_label() {
        let mut labels: Vec<_> = Outcome::ALL.iter().map(|o| o.label()).collect();
        labels.sort_unstable();
        labels.dedup();
        assert_eq!(labels.len(), Outcome::ALL.len());
        assert!(Outcome::ALL.contains(&Outcome::Forbidden));
        assert!(Outcome::ALL.contains(&Outcome::Moving));
    }

    #[test]
    fn bus_failures_map_to_the_gateway_codes() {
        let timeout = BusError::Timeout {
            unit: 3,
            attempts: 2,
            timeout_ms: 50,
        };
        assert_eq!(gateway_exception(&timeout).0, ExceptionCode(0x0B));
        let garbled = BusError::BadReply {
            unit: 3,
            attempts: 2,
            fault: crate::bus::master::Fault::Crc,
        };
        assert_eq!(gateway_exception(&garbled).0, ExceptionCode(0x0B));
        let down = BusError::BusDown {
            bus: "line1".into(),
            reason: crate::bus::error::PortCause::other("unplugged"),
        };
        assert_eq!(
            gateway_exception(&down),
            (ExceptionCode(0x0A), Outcome::PathUnavailable)
        );
        let full = BusError::Busy {
            bus: "line1".into(),
            priority: Priority::Command,
            capacity: 256,
        };
        assert_eq!(
            gateway_exception(&full),
            (ExceptionCode(0x06), Outcome::Busy)
        );
        let cut = BusError::BusDownAfterSend {
            bus: "line1".into(),
            unit: 3,
            reason: crate::bus::error::PortCause::io(
                &std::io::Error::from(std::io::ErrorKind::UnexpectedEof),
                "unplugged",
            ),
        };
        assert_eq!(
            gateway_exception(&cut),
            (ExceptionCode(0x0B), Outcome::GatewayTimeout)
        );
        let waited = BusError::Expired {
            waited: Duration::from_secs(5),
        };
        assert_eq!(gateway_exception(&waited).0, ExceptionCode(0x06));
        assert_eq!(exception_pdu(0x03, ExceptionCode(0x0B)), [0x83, 0x0B]);
    }
}
