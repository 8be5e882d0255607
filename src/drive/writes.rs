//! What a raw Modbus write PDU does to a drive, read with the register
//! table: one of the manual's messages, writes to registers of the table
//! that make up no whole message (a single half of a ramp alpha, a save
//! flag on its own), a mask write whose result depends on a value nobody
//! read, a write the table cannot explain, or a function code whose effect
//! no register table describes. Faces that pass PDUs through (Modbus TCP)
//! use it so the control core sees what the drive will do, whatever the
//! framing.
//!
//! The drives have 0x03, 0x06 and 0x10 only (manual, appendix). A mask
//! write (0x16) and a read/write multiple (0x17) are carried out with
//! those ([`carried`], [`read_after`]), as the Modbus application protocol
//! defines them (V1.1b3, 6.16 and 6.17): a mask write with an AND mask of
//! 0 writes its OR mask whatever the register held, so it is a 0x06 of that
//! value; read/write multiple does its write first, then its read.

use super::message::DriveRequest;
use super::registers::Register;
use crate::modbus::function::{
    MASK_WRITE_REGISTER, READ_HOLDING_REGISTERS, READ_WRITE_MULTIPLE_REGISTERS,
    WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16,
};

/// A write PDU, as the drive reads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PduMeaning {
    /// Exactly one of the manual's messages.
    Message(DriveRequest),
    /// Values written to registers of the table, in order, that are not
    /// one whole message.
    Registers(Vec<(Register, u16)>),
    /// A mask write (0x16) whose AND mask keeps bits of the register's
    /// current value: what it writes depends on a value nobody read (the
    /// command and save-flag registers cannot even be read).
    Masked {
        /// The register.
        register: Register,
        /// Its AND mask (not 0).
        and: u16,
        /// Its OR mask.
        or: u16,
    },
    /// A write of holding registers the table cannot explain (an address
    /// outside the table, a malformed layout, a device that is not a
    /// drive).
    Unknown,
    /// A function code whose effect no register table describes (coils,
    /// file records, diagnostics that restart or clear, vendor codes):
    /// it may change anything.
    NotDecoded {
        /// The function code.
        function: u8,
    },
}

/// Decodes a write PDU to a drive: 0x06 and 0x10 as they are, 0x16 and
/// 0x17 as the writes they make; any other function code is not decoded.
pub(crate) fn decode(pdu: &[u8]) -> PduMeaning {
    match pdu.first() {
        Some(&WRITE_SINGLE_REGISTER | &WRITE_MULTIPLE_REGISTERS) => registers(pdu),
        Some(&MASK_WRITE_REGISTER) => masked(pdu),
        Some(&READ_WRITE_MULTIPLE_REGISTERS) => match carried(pdu) {
            Some(write) => registers(&write),
            None => PduMeaning::Unknown,
        },
        _ => not_decoded(pdu),
    }
}

fn not_decoded(pdu: &[u8]) -> PduMeaning {
    PduMeaning::NotDecoded {
        function: pdu.first().copied().unwrap_or(0),
    }
}

/// What a write PDU to a device that is not a configured drive means: its
/// holding registers are written (the table does not say to what effect),
/// or, for any other function code, nobody can tell.
pub(crate) fn decode_for_device(pdu: &[u8]) -> PduMeaning {
    match pdu.first() {
        Some(
            &WRITE_SINGLE_REGISTER
            | &WRITE_MULTIPLE_REGISTERS
            | &MASK_WRITE_REGISTER
            | &READ_WRITE_MULTIPLE_REGISTERS,
        ) => PduMeaning::Unknown,
        _ => not_decoded(pdu),
    }
}

/// The PDU a drive is sent to carry out a client's write, when the drive
/// has not the client's function: a mask write with an AND mask of 0 as a
/// 0x06 of its OR mask, a read/write multiple's write as a 0x10. `None`:
/// sent as it came (or, for a mask write keeping bits of the current
/// value, not at all).
pub(crate) fn carried(pdu: &[u8]) -> Option<Vec<u8>> {
    match *pdu.first()? {
        MASK_WRITE_REGISTER if pdu.len() == 7 && be_u16(pdu, 3)? == 0 => {
            let mut out = vec![WRITE_SINGLE_REGISTER];
            out.extend_from_slice(&pdu[1..3]);
            out.extend_from_slice(&pdu[5..7]);
            Some(out)
        }
        // function, read address, read quantity, then the write as a 0x10
        // lays it out: address, quantity, byte count, values
        READ_WRITE_MULTIPLE_REGISTERS if pdu.len() > 10 => {
            let mut out = vec![WRITE_MULTIPLE_REGISTERS];
            out.extend_from_slice(&pdu[5..]);
            Some(out)
        }
        _ => None,
    }
}

/// The read a read/write multiple (0x17) makes after its write, as a 0x03.
pub(crate) fn read_after(pdu: &[u8]) -> Option<Vec<u8>> {
    if pdu.first() != Some(&READ_WRITE_MULTIPLE_REGISTERS) || pdu.len() < 5 {
        return None;
    }
    let mut out = vec![READ_HOLDING_REGISTERS];
    out.extend_from_slice(&pdu[1..5]);
    Some(out)
}

/// A mask write: with an AND mask of 0, the write of its OR mask.
fn masked(pdu: &[u8]) -> PduMeaning {
    let (Some(address), Some(and), Some(or), 7) =
        (be_u16(pdu, 1), be_u16(pdu, 3), be_u16(pdu, 5), pdu.len())
    else {
        return PduMeaning::Unknown;
    };
    if and == 0 {
        return match carried(pdu) {
            Some(single) => registers(&single),
            None => PduMeaning::Unknown,
        };
    }
    match Register::at(address) {
        Some(register) => PduMeaning::Masked { register, and, or },
        None => PduMeaning::Unknown,
    }
}

/// A 0x06 or 0x10 PDU on the drive's registers.
fn registers(pdu: &[u8]) -> PduMeaning {
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
        // a mask write to the hole
        assert_eq!(decode(&[0x16, 0, 4, 0, 0xF2, 0, 0x25]), PduMeaning::Unknown);
        // byte count that does not match
        assert_eq!(
            decode(&[0x10, 0x00, 0x06, 0x00, 0x01, 0x04, 0x00, 0x64]),
            PduMeaning::Unknown
        );
        assert_eq!(decode(&[]), PduMeaning::NotDecoded { function: 0 });
    }

    #[test]
    fn function_codes_the_table_cannot_describe_are_not_decoded() {
        // coils, file records, a diagnostics restart, a vendor's code
        for pdu in [
            vec![0x05, 0x00, 0x01, 0xFF, 0x00],
            vec![0x0F, 0, 0, 0, 10, 2, 0xFF, 0x03],
            vec![0x15, 0x09, 0x06, 0, 1, 0, 0, 0, 1, 0, 5],
            vec![0x08, 0x00, 0x01, 0x00, 0x00],
            vec![0x41, 0x01],
        ] {
            let function = pdu[0];
            assert_eq!(
                decode(&pdu),
                PduMeaning::NotDecoded { function },
                "{pdu:02X?}"
            );
            assert_eq!(decode_for_device(&pdu), PduMeaning::NotDecoded { function });
            assert_eq!(carried(&pdu), None);
        }
        // A device's registers are written, to no effect the table knows.
        assert_eq!(
            decode_for_device(&[0x06, 0x00, 0x02, 0x00, 0x06]),
            PduMeaning::Unknown
        );
        assert_eq!(
            decode_for_device(&[0x16, 0, 2, 0, 0, 0, 6]),
            PduMeaning::Unknown
        );
    }

    #[test]
    fn a_mask_write_with_and_zero_is_the_write_of_its_or_mask() {
        // CONFIG: AND 0x0000, OR 0x0006: a factory reset, sent as 0x06
        let reset = [0x16, 0x00, 0x02, 0x00, 0x00, 0x00, 0x06];
        assert_eq!(
            decode(&reset),
            PduMeaning::Message(DriveRequest::Config(ConfigCommand::FactoryReset))
        );
        assert_eq!(carried(&reset), Some(vec![0x06, 0x00, 0x02, 0x00, 0x06]));
        // SLAVE_ADDR = 9, as a mask write
        assert_eq!(
            decode(&[0x16, 0x00, 0x00, 0x00, 0x00, 0x00, 0x09]),
            PduMeaning::Message(DriveRequest::SetAddress { address: 9 })
        );
        // A save flag on its own
        assert_eq!(
            decode(&[0x16, 0x00, 0x1C, 0x00, 0x00, 0x00, 0x01]),
            PduMeaning::Registers(vec![(Register::SpeedTdRSaveFlag, 1)])
        );
    }

    #[test]
    fn a_mask_write_keeping_bits_depends_on_the_current_value() {
        // CONFIG: AND 0xFFF0, OR 0x0006: 6 only if CONFIG held less than 16
        assert_eq!(
            decode(&[0x16, 0x00, 0x02, 0xFF, 0xF0, 0x00, 0x06]),
            PduMeaning::Masked {
                register: Register::Config,
                and: 0xFFF0,
                or: 0x0006
            }
        );
        // All bits kept: still not known what it writes.
        assert!(matches!(
            decode(&[0x16, 0x00, 0x06, 0xFF, 0xFF, 0x00, 0x00]),
            PduMeaning::Masked { and: 0xFFFF, .. }
        ));
        assert_eq!(carried(&[0x16, 0x00, 0x02, 0xFF, 0xF0, 0x00, 0x06]), None);
        // A mask write of the wrong length
        assert_eq!(decode(&[0x16, 0x00, 0x02, 0x00]), PduMeaning::Unknown);
    }

    #[test]
    fn read_write_multiple_is_its_write_then_its_read() {
        // read 7 at 0x00C0; write inertia 5, saved (2 registers at 0x0024)
        let pdu = [
            0x17, 0x00, 0xC0, 0x00, 0x07, 0x00, 0x24, 0x00, 0x02, 0x04, 0, 5, 0, 1,
        ];
        assert_eq!(
            decode(&pdu),
            PduMeaning::Message(DriveRequest::LoadInertia {
                ratio: 5,
                save: true
            })
        );
        assert_eq!(
            carried(&pdu),
            Some(vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04, 0, 5, 0, 1])
        );
        assert_eq!(read_after(&pdu), Some(vec![0x03, 0x00, 0xC0, 0x00, 0x07]));
        // CONFIG = 6 in a block of one: a factory reset, by registers
        let reset = [
            0x17, 0x00, 0xC0, 0x00, 0x07, 0x00, 0x02, 0x00, 0x01, 0x02, 0, 6,
        ];
        assert_eq!(
            decode(&reset),
            PduMeaning::Registers(vec![(Register::Config, 6)])
        );
        assert_eq!(read_after(&[0x06, 0, 0, 0, 0]), None);
    }
}
