//! Reading back what a drive holds: its setpoints and the settings of
//! sections 1.8 to 1.12, from the registers the appendix marks RW.
//!
//! The manual has no single block covering them (the save flags between
//! them are write-only), so they are read in [`BLOCKS`]: six reads with
//! function 0x03, addresses in the drive's byte counting (see
//! [`super::registers`]).

use super::message::ReplyError;
use super::registers::Register;
use crate::modbus::ExceptionCode;
use crate::modbus::function::{EXCEPTION_BIT, READ_HOLDING_REGISTERS};

/// The readable blocks: first register and number of registers.
pub(crate) const BLOCKS: [(Register, u16); 6] = [
    (Register::SpeedRef, 3),        // SPEED_REF, POSITION_REF, IQ_REF
    (Register::StalledCurr, 2),     // STALLED_CURR, STALLED_DURATION_MS
    (Register::SpeedTdRHigh, 2),    // speed ramp alpha, high and low
    (Register::PositionTdRHigh, 2), // position ramp alpha, high and low
    (Register::InertiaRatio, 1),    // INERTIA_RATIO
    (Register::Use485Control, 1),   // USE_485_CONTROL
];

/// Registers read in all.
pub(crate) const REGISTERS: usize = 11;

/// What a drive holds, in its own units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DriveSettings {
    /// SPEED_REF, rpm at the output.
    pub speed_rpm: i16,
    /// POSITION_REF, 0.01 degree at the output.
    pub position_centideg: i16,
    /// IQ_REF, counts (1 A = 128).
    pub torque_counts: i16,
    /// STALLED_CURR, counts.
    pub limit_counts: u16,
    /// STALLED_DURATION_MS.
    pub stall_ms: u16,
    /// Speed ramp alpha (0: ramp off).
    pub speed_alpha: u32,
    /// Position ramp alpha (0: ramp off).
    pub position_alpha: u32,
    /// INERTIA_RATIO, times the rotor's.
    pub inertia_ratio: u16,
    /// USE_485_CONTROL: true when RS-485 controls the motor.
    pub rs485_control: bool,
}

/// The request PDU reading one block.
pub(crate) fn read_pdu(start: Register, count: u16) -> Vec<u8> {
    let mut pdu = vec![READ_HOLDING_REGISTERS];
    pdu.extend_from_slice(&start.address().to_be_bytes());
    pdu.extend_from_slice(&count.to_be_bytes());
    pdu
}

/// The register values of a read reply of `count` registers.
pub(crate) fn parse_read_reply(reply: &[u8], count: u16) -> Result<Vec<u16>, ReplyError> {
    match reply.first() {
        Some(&f) if f == READ_HOLDING_REGISTERS | EXCEPTION_BIT => {
            let code = reply.get(1).copied().unwrap_or(0);
            return Err(ReplyError::Exception(ExceptionCode(code)));
        }
        Some(&READ_HOLDING_REGISTERS) => {}
        _ => return Err(ReplyError::Mismatch("wrong function code")),
    }
    let bytes = usize::from(count) * 2;
    if reply.get(1).map(|&n| usize::from(n)) != Some(bytes) || reply.len() != 2 + bytes {
        return Err(ReplyError::Mismatch("read reply of the wrong length"));
    }
    Ok(reply[2..]
        .chunks_exact(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]))
        .collect())
}

impl DriveSettings {
    /// Decodes the values of [`BLOCKS`], in order.
    pub fn from_registers(v: &[u16; REGISTERS]) -> Self {
        let alpha = |high: u16, low: u16| (u32::from(high) << 16) | u32::from(low);
        DriveSettings {
            speed_rpm: v[0] as i16,
            position_centideg: v[1] as i16,
            torque_counts: v[2] as i16,
            limit_counts: v[3],
            stall_ms: v[4],
            speed_alpha: alpha(v[5], v[6]),
            position_alpha: alpha(v[7], v[8]),
            inertia_ratio: v[9],
            rs485_control: v[10] == 1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_are_readable_and_add_up() {
        let total: u16 = BLOCKS.iter().map(|(_, n)| n).sum();
        assert_eq!(usize::from(total), REGISTERS);
        for (start, count) in BLOCKS {
            let block = Register::block(start.address(), count).unwrap();
            assert!(block.iter().all(|r| r.access().readable()), "{block:?}");
        }
    }

    #[test]
    fn read_pdus_use_byte_addresses() {
        // 0x03, STALLED_CURR at 0x000C, 2 registers (covers 0x000C and 0x000E).
        assert_eq!(
            read_pdu(Register::StalledCurr, 2),
            [0x03, 0x00, 0x0C, 0x00, 0x02]
        );
        assert_eq!(
            read_pdu(Register::Use485Control, 1),
            [0x03, 0x00, 0xBE, 0x00, 0x01]
        );
    }

    #[test]
    fn replies_decode_or_are_refused() {
        // Byte count 4, then 0x0600 (1536 counts) and 0x0BB8 (3000 ms).
        let values = parse_read_reply(&[0x03, 0x04, 0x06, 0x00, 0x0B, 0xB8], 2).unwrap();
        assert_eq!(values, [1536, 3000]);
        assert_eq!(
            parse_read_reply(&[0x83, 0x02], 2),
            Err(ReplyError::Exception(ExceptionCode(2)))
        );
        assert!(parse_read_reply(&[0x03, 0x02, 0x06, 0x00], 2).is_err());
        assert!(parse_read_reply(&[0x06, 0x04, 0, 0, 0, 0], 2).is_err());
        assert!(parse_read_reply(&[], 1).is_err());
    }

    #[test]
    fn values_decode_in_the_drive_units() {
        // alpha 500000 = 0x0007_A120.
        let s = DriveSettings::from_registers(&[
            0xFF9C, 9000, 128, 1536, 3000, 0x0007, 0xA120, 0, 200, 5, 1,
        ]);
        assert_eq!(s.speed_rpm, -100);
        assert_eq!(s.position_centideg, 9000);
        assert_eq!(s.torque_counts, 128);
        assert_eq!((s.limit_counts, s.stall_ms), (1536, 3000));
        assert_eq!((s.speed_alpha, s.position_alpha), (500_000, 200));
        assert_eq!(s.inertia_ratio, 5);
        assert!(s.rs485_control);
    }
}
