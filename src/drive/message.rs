//! Typed requests to the drive and the replies they expect (manual 1.2 to 1.12).

use super::command::ConfigCommand;
use super::range::RangeError;
use super::registers::{Register, STATUS_BLOCK_LEN, STATUS_BLOCK_START};
use super::status::Status;
use super::units;
use crate::modbus::ExceptionCode;
use crate::modbus::function::{
    EXCEPTION_BIT, READ_HOLDING_REGISTERS, WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16,
};

/// One message of the manual, with values in the drive's own units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DriveRequest {
    /// 1.2: broadcast (unit 0) the new address of the only drive on the bus.
    SetAddress {
        /// New address, 1..=255.
        address: u8,
    },
    /// 1.3: one of the twelve config commands.
    Config(ConfigCommand),
    /// 1.4: speed setpoint, rpm at the gearbox output, -2048..=2047.
    Speed {
        /// Setpoint in rpm.
        rpm: i16,
    },
    /// 1.5: position setpoint, 0.01 degree at the gearbox output, -18000..=18000.
    Position {
        /// Setpoint in 0.01 degree.
        centideg: i16,
    },
    /// 1.6: torque (current) setpoint at the motor shaft, counts (1 A = 128), -2048..=2047.
    Torque {
        /// Setpoint in counts.
        counts: i16,
    },
    /// 1.7: read the seven status registers.
    ReadStatus,
    /// 1.8: over-current (stall) protection.
    OverCurrent {
        /// Current limit in counts, 0..=2047.
        limit_counts: u16,
        /// How long the limit may be exceeded before the drive stalls, 0..=60000 ms.
        stall_ms: u16,
        /// Write to flash (motor must stand still).
        save: bool,
    },
    /// 1.9: speed ramp.
    SpeedRamp {
        /// Ramp alpha; 0 turns the ramp off.
        alpha: u32,
        /// Write to flash (motor must stand still).
        save: bool,
    },
    /// 1.10: position ramp.
    PositionRamp {
        /// Ramp alpha; 0 turns the ramp off.
        alpha: u32,
        /// Write to flash (motor must stand still).
        save: bool,
    },
    /// 1.11: load inertia as a multiple of the rotor's.
    LoadInertia {
        /// Ratio, 1..=65535.
        ratio: u16,
        /// Write to flash (motor must stand still).
        save: bool,
    },
    /// 1.12: which interface controls the motor.
    Rs485Control {
        /// True: RS-485 controls and CAN is ignored; false: CAN controls.
        enabled: bool,
    },
}

/// What the drive answers when a request succeeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DriveReply {
    /// A broadcast: no reply is sent.
    None,
    /// The drive echoed the write (0x06) or acknowledged the block (0x10).
    Confirmed,
    /// The status block.
    Status(Status),
}

/// Why a reply does not confirm the request.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReplyError {
    /// The drive refused the request with a Modbus exception.
    #[error("the drive refused the request: {0}")]
    Exception(ExceptionCode),
    /// The reply is well-framed but does not answer this request.
    #[error("the drive's reply does not match the request: {0}")]
    Mismatch(&'static str),
}

impl DriveRequest {
    /// Unit a request must go to: address setting is always a broadcast.
    pub fn is_broadcast(&self) -> bool {
        matches!(self, DriveRequest::SetAddress { .. })
    }

    /// True for writes that need the motor standing still (save to flash).
    pub fn saves_to_flash(&self) -> bool {
        match self {
            DriveRequest::OverCurrent { save, .. }
            | DriveRequest::SpeedRamp { save, .. }
            | DriveRequest::PositionRamp { save, .. }
            | DriveRequest::LoadInertia { save, .. } => *save,
            _ => false,
        }
    }

    /// True when the request changes the drive (everything but the status read).
    pub fn is_write(&self) -> bool {
        !matches!(self, DriveRequest::ReadStatus)
    }

    /// Checks every value against the manual's ranges.
    pub fn validate(&self) -> Result<(), RangeError> {
        match *self {
            DriveRequest::SetAddress { address } => {
                RangeError::check_int("drive address", i64::from(address), 1, 255, "")?;
            }
            DriveRequest::Position { centideg } => {
                let (min, max) = units::POSITION_CENTIDEG;
                RangeError::check_int(
                    "position setpoint",
                    i64::from(centideg),
                    min,
                    max,
                    "x 0.01 deg",
                )?;
            }
            DriveRequest::Speed { rpm } => {
                let (min, max) = units::SPEED_RPM;
                RangeError::check_int("speed setpoint", i64::from(rpm), min, max, "rpm")?;
            }
            DriveRequest::Torque { counts } => {
                units::torque_setpoint_counts(i64::from(counts))?;
            }
            DriveRequest::OverCurrent {
                limit_counts,
                stall_ms,
                ..
            } => {
                units::current_limit_counts(i64::from(limit_counts))?;
                units::stall_time_ms(i64::from(stall_ms))?;
            }
            DriveRequest::LoadInertia { ratio, .. } => {
                units::inertia_ratio(i64::from(ratio))?;
            }
            DriveRequest::Config(_)
            | DriveRequest::ReadStatus
            | DriveRequest::SpeedRamp { .. }
            | DriveRequest::PositionRamp { .. }
            | DriveRequest::Rs485Control { .. } => {}
        }
        Ok(())
    }

    /// The Modbus PDU (function code and data) of this request.
    pub fn pdu(&self) -> Result<Vec<u8>, RangeError> {
        self.validate()?;
        Ok(match *self {
            DriveRequest::SetAddress { address } => {
                write_single(Register::SlaveAddr, u16::from(address))
            }
            DriveRequest::Config(command) => write_single(Register::Config, command.code()),
            DriveRequest::Speed { rpm } => write_single(Register::SpeedRef, rpm as u16),
            DriveRequest::Position { centideg } => {
                write_single(Register::PositionRef, centideg as u16)
            }
            DriveRequest::Torque { counts } => write_single(Register::IqRef, counts as u16),
            DriveRequest::Rs485Control { enabled } => {
                write_single(Register::Use485Control, u16::from(enabled))
            }
            DriveRequest::ReadStatus => {
                let mut pdu = vec![READ_HOLDING_REGISTERS];
                pdu.extend_from_slice(&STATUS_BLOCK_START.to_be_bytes());
                pdu.extend_from_slice(&STATUS_BLOCK_LEN.to_be_bytes());
                pdu
            }
            DriveRequest::OverCurrent {
                limit_counts,
                stall_ms,
                save,
            } => write_block(
                Register::StalledCurr,
                &[limit_counts, stall_ms, u16::from(save)],
            ),
            DriveRequest::SpeedRamp { alpha, save } => write_block(
                Register::SpeedTdRHigh,
                &[(alpha >> 16) as u16, alpha as u16, u16::from(save)],
            ),
            DriveRequest::PositionRamp { alpha, save } => write_block(
                Register::PositionTdRHigh,
                &[(alpha >> 16) as u16, alpha as u16, u16::from(save)],
            ),
            DriveRequest::LoadInertia { ratio, save } => {
                write_block(Register::InertiaRatio, &[ratio, u16::from(save)])
            }
        })
    }

    /// The whole RTU frame for `unit` (unit 0 for the address broadcast).
    pub fn frame(&self, unit: u8) -> Result<Vec<u8>, RangeError> {
        let unit = if self.is_broadcast() { 0 } else { unit };
        Ok(crate::modbus::rtu_frame::encode(unit, &self.pdu()?))
    }

    /// Length in bytes of the whole reply frame, `None` for a broadcast.
    pub fn reply_len(&self) -> Option<usize> {
        match self {
            DriveRequest::SetAddress { .. } => None,
            DriveRequest::ReadStatus => Some(3 + Status::BYTES + 2),
            _ => Some(8),
        }
    }

    /// Checks a reply PDU (function code onward, CRC already checked) against
    /// this request: an echo must repeat the write, an ack its address and count.
    pub fn parse_reply(&self, reply: &[u8]) -> Result<DriveReply, ReplyError> {
        if self.is_broadcast() {
            return Ok(DriveReply::None);
        }
        let request = self
            .pdu()
            .map_err(|_| ReplyError::Mismatch("the request itself was out of range"))?;
        let function = request[0];
        match reply.first() {
            Some(&f) if f == function | EXCEPTION_BIT => {
                let code = reply.get(1).copied().unwrap_or(0);
                return Err(ReplyError::Exception(ExceptionCode(code)));
            }
            Some(&f) if f == function => {}
            _ => return Err(ReplyError::Mismatch("wrong function code")),
        }
        match function {
            WRITE_SINGLE_REGISTER => {
                if reply == request.as_slice() {
                    Ok(DriveReply::Confirmed)
                } else {
                    Err(ReplyError::Mismatch("the echo differs from the write"))
                }
            }
            WRITE_MULTIPLE_REGISTERS => {
                if reply.len() == 5 && reply[1..5] == request[1..5] {
                    Ok(DriveReply::Confirmed)
                } else {
                    Err(ReplyError::Mismatch(
                        "the acknowledgement names other registers",
                    ))
                }
            }
            _ => {
                if reply.get(1).copied() != Some(Status::BYTES as u8) {
                    return Err(ReplyError::Mismatch("status reply of the wrong length"));
                }
                Status::from_bytes(&reply[2..])
                    .map(DriveReply::Status)
                    .ok_or(ReplyError::Mismatch("status reply of the wrong length"))
            }
        }
    }

    /// Short name for logs and metrics.
    pub fn name(&self) -> &'static str {
        match self {
            DriveRequest::SetAddress { .. } => "set-address",
            DriveRequest::Config(c) => c.name(),
            DriveRequest::Speed { .. } => "speed-setpoint",
            DriveRequest::Position { .. } => "position-setpoint",
            DriveRequest::Torque { .. } => "torque-setpoint",
            DriveRequest::ReadStatus => "read-status",
            DriveRequest::OverCurrent { .. } => "over-current-protection",
            DriveRequest::SpeedRamp { .. } => "speed-ramp",
            DriveRequest::PositionRamp { .. } => "position-ramp",
            DriveRequest::LoadInertia { .. } => "load-inertia",
            DriveRequest::Rs485Control { .. } => "rs485-control",
        }
    }

    /// Decodes a request PDU back into a typed request, if it is one of the
    /// manual's messages (used to recognise passthrough writes).
    pub fn from_pdu(pdu: &[u8]) -> Option<DriveRequest> {
        let function = *pdu.first()?;
        let address = be_u16(pdu, 1)?;
        match function {
            WRITE_SINGLE_REGISTER if pdu.len() == 5 => {
                let value = be_u16(pdu, 3)?;
                let request = match Register::at(address)? {
                    Register::SlaveAddr => DriveRequest::SetAddress {
                        address: u8::try_from(value).ok()?,
                    },
                    Register::Config => DriveRequest::Config(ConfigCommand::from_code(value)?),
                    Register::SpeedRef => DriveRequest::Speed { rpm: value as i16 },
                    Register::PositionRef => DriveRequest::Position {
                        centideg: value as i16,
                    },
                    Register::IqRef => DriveRequest::Torque {
                        counts: value as i16,
                    },
                    Register::Use485Control if value <= 1 => DriveRequest::Rs485Control {
                        enabled: value == 1,
                    },
                    _ => return None,
                };
                request.validate().ok().map(|()| request)
            }
            READ_HOLDING_REGISTERS
                if pdu.len() == 5
                    && address == STATUS_BLOCK_START
                    && be_u16(pdu, 3)? == STATUS_BLOCK_LEN =>
            {
                Some(DriveRequest::ReadStatus)
            }
            WRITE_MULTIPLE_REGISTERS => {
                let count = be_u16(pdu, 3)?;
                let bytes = usize::from(*pdu.get(5)?);
                if bytes != usize::from(count) * 2 || pdu.len() != 6 + bytes {
                    return None;
                }
                let v = |i: usize| be_u16(pdu, 6 + 2 * i);
                let flag = |i: usize| match v(i) {
                    Some(0) => Some(false),
                    Some(1) => Some(true),
                    _ => None,
                };
                let request = match (Register::at(address)?, count) {
                    (Register::StalledCurr, 3) => DriveRequest::OverCurrent {
                        limit_counts: v(0)?,
                        stall_ms: v(1)?,
                        save: flag(2)?,
                    },
                    (Register::SpeedTdRHigh, 3) => DriveRequest::SpeedRamp {
                        alpha: (u32::from(v(0)?) << 16) | u32::from(v(1)?),
                        save: flag(2)?,
                    },
                    (Register::PositionTdRHigh, 3) => DriveRequest::PositionRamp {
                        alpha: (u32::from(v(0)?) << 16) | u32::from(v(1)?),
                        save: flag(2)?,
                    },
                    (Register::InertiaRatio, 2) => DriveRequest::LoadInertia {
                        ratio: v(0)?,
                        save: flag(1)?,
                    },
                    _ => return None,
                };
                request.validate().ok().map(|()| request)
            }
            _ => None,
        }
    }
}

fn write_single(register: Register, value: u16) -> Vec<u8> {
    let mut pdu = vec![WRITE_SINGLE_REGISTER];
    pdu.extend_from_slice(&register.address().to_be_bytes());
    pdu.extend_from_slice(&value.to_be_bytes());
    pdu
}

fn write_block(first: Register, values: &[u16]) -> Vec<u8> {
    let mut pdu = vec![WRITE_MULTIPLE_REGISTERS];
    pdu.extend_from_slice(&first.address().to_be_bytes());
    pdu.extend_from_slice(&(values.len() as u16).to_be_bytes());
    pdu.push((values.len() * 2) as u8);
    for v in values {
        pdu.extend_from_slice(&v.to_be_bytes());
    }
    pdu
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn echo_must_repeat_the_write() {
        let req = DriveRequest::Speed { rpm: 100 };
        let pdu = req.pdu().unwrap();
        assert_eq!(req.parse_reply(&pdu), Ok(DriveReply::Confirmed));
        let other = DriveRequest::Speed { rpm: 101 }.pdu().unwrap();
        assert!(matches!(
            req.parse_reply(&other),
            Err(ReplyError::Mismatch(_))
        ));
        assert_eq!(
            req.parse_reply(&[0x86, 0x03]),
            Err(ReplyError::Exception(ExceptionCode::ILLEGAL_DATA_VALUE))
        );
        assert!(matches!(
            req.parse_reply(&[0x03, 0x0E]),
            Err(ReplyError::Mismatch(_))
        ));
        assert!(matches!(req.parse_reply(&[]), Err(ReplyError::Mismatch(_))));
    }

    #[test]
    fn out_of_range_requests_are_refused_before_encoding() {
        assert!(DriveRequest::Speed { rpm: 2048 }.pdu().is_err());
        assert!(DriveRequest::Position { centideg: -18001 }.pdu().is_err());
        assert!(DriveRequest::SetAddress { address: 0 }.pdu().is_err());
        let err = DriveRequest::OverCurrent {
            limit_counts: 2048,
            stall_ms: 10,
            save: false,
        }
        .pdu()
        .unwrap_err();
        assert_eq!(err.quantity, "over-current limit");
        assert!(
            DriveRequest::LoadInertia {
                ratio: 0,
                save: false
            }
            .pdu()
            .is_err()
        );
    }

    #[test]
    fn broadcast_goes_to_unit_zero_and_expects_nothing() {
        let req = DriveRequest::SetAddress { address: 5 };
        assert_eq!(req.frame(9).unwrap()[0], 0);
        assert_eq!(req.reply_len(), None);
        assert_eq!(req.parse_reply(&[]), Ok(DriveReply::None));
    }
}
