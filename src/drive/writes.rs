//! What a raw Modbus write PDU does to a drive, read with the register
//! table: one of the manual's messages, writes to registers of the table
//! that make up no whole message (a single half of a ramp alpha, a save
//! flag on its own), or a write the table cannot explain. Faces that pass
//! PDUs through (Modbus TCP) use it so the control core sees what the
//! drive will do, whatever the framing.

use super::message::DriveRequest;
use super::registers::Register;
use crate::modbus::function::{WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16};

/// A write PDU, as the drive reads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PduMeaning {
    /// Exactly one of the manual's messages.
    Message(DriveRequest),
    /// Values written to registers of the table, in order, that are not
    /// one whole message.
    Registers(Vec<(Register, u16)>),
    /// Not a write of the register table (another function code, an
    /// address outside the table, a malformed layout).
    Unknown,
}

/// Decodes a write PDU (function 0x06 or 0x10 on the drive's registers).
pub(crate) fn decode(pdu: &[u8]) -> PduMeaning {
    if let Some(request) = DriveRequest::from_pdu(pdu)
        && request.is_write()
    {
        return PduMeaning::Message(request);
    }
    let registers = match pdu.first() {
        Some(&WRITE_SINGLE_REGISTER) if pdu.len() == 5 => {
            let (Some(address), Some(value)) = (be_u16(pdu, 1), be_u16(pdu, 3)) else {
                return PduMeaning::Unknown;
            };
            match Register::at(address) {
                Some(r) => vec![(r, value)],
                None => return PduMeaning::Unknown,
            }
        }
        Some(&WRITE_MULTIPLE_REGISTERS) => {
            let (Some(address), Some(count), Some(&bytes)) =
                (be_u16(pdu, 1), be_u16(pdu, 3), pdu.get(5))
            else {
                return PduMeaning::Unknown;
            };
            if usize::from(bytes) != usize::from(count) * 2 || pdu.len() != 6 + usize::from(bytes) {
                return PduMeaning::Unknown;
            }
            let Some(block) = Register::block(address, count) else {
                return PduMeaning::Unknown;
            };
            let mut writes = Vec::with_capacity(block.len());
            for (i, r) in block.into_iter().enumerate() {
                match be_u16(pdu, 6 + 2 * i) {
                    Some(v) => writes.push((r, v)),
                    None => return PduMeaning::Unknown,
                }
            }
            writes
        }
        _ => return PduMeaning::Unknown,
    };
    PduMeaning::Registers(registers)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::ConfigCommand;

    #[test]
    fn whole_messages_decode_to_their_request() {
        // CONFIG = 5: the emergency brake (manual 1.3)
        assert_eq!(
            decode(&[0x06, 0x00, 0x02, 0x00, 0x05]),
            PduMeaning::Message(DriveRequest::Config(ConfigCommand::EmergencyBrake))
        );
        // IQ_REF = 128: 1 A
        assert_eq!(
            decode(&[0x06, 0x00, 0x0A, 0x00, 0x80]),
            PduMeaning::Message(DriveRequest::Torque { counts: 128 })
        );
        // SLAVE_ADDR = 7
        assert_eq!(
            decode(&[0x06, 0x00, 0x00, 0x00, 0x07]),
            PduMeaning::Message(DriveRequest::SetAddress { address: 7 })
        );
        // inertia 5, saved: a block of 2 at 0x0024
        assert_eq!(
            decode(&[0x10, 0x00, 0x24, 0x00, 0x02, 0x04, 0, 5, 0, 1]),
            PduMeaning::Message(DriveRequest::LoadInertia {
                ratio: 5,
                save: true
            })
        );
    }

    #[test]
    fn parts_of_messages_decode_to_registers() {
        // SPEED_TD_R_SAVE_FLAG = 1 on its own: a save
        assert_eq!(
            decode(&[0x06, 0x00, 0x1C, 0x00, 0x01]),
            PduMeaning::Registers(vec![(Register::SpeedTdRSaveFlag, 1)])
        );
        // SPEED_REF as a block of one
        assert_eq!(
            decode(&[0x10, 0x00, 0x06, 0x00, 0x01, 0x02, 0x00, 0x64]),
            PduMeaning::Registers(vec![(Register::SpeedRef, 100)])
        );
        // the three setpoints in one block
        assert_eq!(
            decode(&[0x10, 0x00, 0x06, 0x00, 0x03, 0x06, 0, 100, 0, 0, 0, 0]),
            PduMeaning::Registers(vec![
                (Register::SpeedRef, 100),
                (Register::PositionRef, 0),
                (Register::IqRef, 0)
            ])
        );
        // CONFIG with a code the drive refuses
        assert_eq!(
            decode(&[0x06, 0x00, 0x02, 0x00, 0x09]),
            PduMeaning::Registers(vec![(Register::Config, 9)])
        );
    }

    #[test]
    fn writes_outside_the_table_are_unknown() {
        // 0x0004 is a hole in the table
        assert_eq!(decode(&[0x06, 0x00, 0x04, 0x00, 0x01]), PduMeaning::Unknown);
        // a block across the hole
        assert_eq!(
            decode(&[0x10, 0x00, 0x02, 0x00, 0x02, 0x04, 0, 5, 0, 0]),
            PduMeaning::Unknown
        );
        // coils, mask write, a read
        assert_eq!(decode(&[0x05, 0x00, 0x01, 0xFF, 0x00]), PduMeaning::Unknown);
        assert_eq!(decode(&[0x16, 0, 4, 0, 0xF2, 0, 0x25]), PduMeaning::Unknown);
        assert_eq!(decode(&[0x03, 0x00, 0xC0, 0x00, 0x07]), PduMeaning::Unknown);
        // byte count that does not match
        assert_eq!(
            decode(&[0x10, 0x00, 0x06, 0x00, 0x01, 0x04, 0x00, 0x64]),
            PduMeaning::Unknown
        );
        assert_eq!(decode(&[]), PduMeaning::Unknown);
    }
}
