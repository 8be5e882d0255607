//! The drive's Modbus slave: a request PDU in, a reply PDU out. Pure code.
//!
//! Addressing as the manual shows it: registers at even byte addresses,
//! quantities in 16-bit words ([`Register::block`]); a one-register read at
//! 0x00C2 is ANGLE.
//!
//! Exceptions, in the order a Modbus device checks (function, quantity,
//! address, value, execution):
//! - 0x01 illegal function: everything but 0x03, 0x06 and 0x10 (0x04 too: the
//!   drive has no input registers).
//! - 0x03 illegal data value: a read quantity outside 1..=125, a block write
//!   whose quantity (1..=123) or byte count does not match its data, or a
//!   value outside the manual's range ([`Register::accepts`]).
//! - 0x02 illegal data address: any address of the block missing from the
//!   table (holes, odd addresses), reads of write-only registers, writes of
//!   read-only ones.
//! - 0x04 server device failure: a setpoint to a drive that is not active,
//!   fine-tuning before calibration.
//! - 0x06 server device busy: setpoints and mode commands while the drive
//!   calibrates or fine-tunes.
//!
//! The manual does not say how the real drive refuses the last two kinds; a
//! drive may as well echo and ignore them. The gateway therefore checks the
//! active flag itself before sending setpoints and does not rely on these.

use super::model::{DriveModel, Refusal};
use crate::drive::Register;
use crate::modbus::ExceptionCode;
use crate::modbus::function::{
    EXCEPTION_BIT, READ_HOLDING_REGISTERS, WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16,
};

/// Most registers one read may ask for (Modbus application protocol).
const MAX_READ: u16 = 125;
/// Most registers one block write may carry.
const MAX_WRITE: u16 = 123;

impl From<Refusal> for ExceptionCode {
    fn from(refusal: Refusal) -> Self {
        match refusal {
            Refusal::NotActive | Refusal::NotCalibrated => ExceptionCode::SERVER_DEVICE_FAILURE,
            Refusal::Busy(_) => ExceptionCode::SERVER_DEVICE_BUSY,
        }
    }
}

/// Answers one request `pdu` (function code onward) addressed to `drive`,
/// writing the reply PDU into `reply`; returns the exception if it is one.
pub(crate) fn answer(
    drive: &mut DriveModel,
    pdu: &[u8],
    reply: &mut Vec<u8>,
) -> Option<ExceptionCode> {
    reply.clear();
    let function = pdu.first().copied().unwrap_or(0);
    let result = match function {
        READ_HOLDING_REGISTERS => read(drive, pdu, reply),
        WRITE_SINGLE_REGISTER => write_single(drive, pdu, reply),
        WRITE_MULTIPLE_REGISTERS => write_block(drive, pdu, reply),
        _ => Err(ExceptionCode::ILLEGAL_FUNCTION),
    };
    match result {
        Ok(()) => None,
        Err(code) => {
            reply.clear();
            reply.push(function | EXCEPTION_BIT);
            reply.push(code.0);
            Some(code)
        }
    }
}

/// Carries out a broadcast (unit 0) `pdu`: writes take effect, nothing is
/// answered, reads and refusals are ignored. `scratch` is a reusable buffer.
pub(crate) fn broadcast(drive: &mut DriveModel, pdu: &[u8], scratch: &mut Vec<u8>) {
    if matches!(
        pdu.first(),
        Some(&WRITE_SINGLE_REGISTER | &WRITE_MULTIPLE_REGISTERS)
    ) {
        let _ = answer(drive, pdu, scratch);
    }
    scratch.clear();
}

/// 0x03: byte count, then the registers big-endian.
fn read(drive: &DriveModel, pdu: &[u8], reply: &mut Vec<u8>) -> Result<(), ExceptionCode> {
    let (Some(start), Some(count), 5) = (be_u16(pdu, 1), be_u16(pdu, 3), pdu.len()) else {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    };
    if count == 0 || count > MAX_READ {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    }
    let registers = Register::block(start, count).ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
    if !registers.iter().all(|r| r.access().readable()) {
        return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS);
    }
    reply.push(READ_HOLDING_REGISTERS);
    reply.push((count * 2) as u8);
    drive.read_into(&registers, reply);
    Ok(())
}

/// 0x06: the drive echoes the request.
fn write_single(
    drive: &mut DriveModel,
    pdu: &[u8],
    reply: &mut Vec<u8>,
) -> Result<(), ExceptionCode> {
    let (Some(address), Some(value), 5) = (be_u16(pdu, 1), be_u16(pdu, 3), pdu.len()) else {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    };
    let register = Register::at(address)
        .filter(|r| r.access().writable())
        .ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
    if !register.accepts(value) {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    }
    drive.write(register, value)?;
    reply.extend_from_slice(pdu);
    Ok(())
}

/// 0x10: all or nothing; the drive answers the address and the count.
fn write_block(
    drive: &mut DriveModel,
    pdu: &[u8],
    reply: &mut Vec<u8>,
) -> Result<(), ExceptionCode> {
    let (Some(start), Some(count), Some(&bytes)) = (be_u16(pdu, 1), be_u16(pdu, 3), pdu.get(5))
    else {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    };
    if count == 0
        || count > MAX_WRITE
        || usize::from(bytes) != usize::from(count) * 2
        || pdu.len() != 6 + usize::from(bytes)
    {
        return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    }
    let registers = Register::block(start, count).ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
    if !registers.iter().all(|r| r.access().writable()) {
        return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS);
    }
    let value = |i: usize| be_u16(pdu, 6 + 2 * i).unwrap_or(0);
    for (i, register) in registers.iter().enumerate() {
        if !register.accepts(value(i)) {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
    }
    for (i, register) in registers.iter().enumerate() {
        drive.check_write(*register, value(i))?;
    }
    let writes: Vec<(Register, u16)> = registers
        .iter()
        .enumerate()
        .map(|(i, register)| (*register, value(i)))
        .collect();
    drive.write_block(&writes)?;
    reply.extend_from_slice(&pdu[..5]);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::{ConfigCommand, DriveReply, DriveRequest};

    fn drive() -> DriveModel {
        DriveModel::new(1, 3.75, true, 0.3)
    }

    fn ask(d: &mut DriveModel, pdu: &[u8]) -> Result<Vec<u8>, u8> {
        let mut reply = Vec::new();
        match answer(d, pdu, &mut reply) {
            None => Ok(reply),
            Some(code) => {
                assert_eq!(reply, [pdu[0] | 0x80, code.0]);
                Err(code.0)
            }
        }
    }

    fn request(d: &mut DriveModel, req: DriveRequest) -> Result<DriveReply, u8> {
        let pdu = req.pdu().unwrap();
        let reply = ask(d, &pdu)?;
        Ok(req.parse_reply(&reply).unwrap())
    }

    #[test]
    fn status_read_decodes_as_the_master_does() {
        let mut d = drive();
        let Ok(DriveReply::Status(s)) = request(&mut d, DriveRequest::ReadStatus) else {
            panic!("no status");
        };
        assert_eq!(s, d.status());
        assert_eq!((s.voltage_v, s.temperature_c), (24, 25));
    }

    #[test]
    fn byte_addressing_one_register_at_0x00c2_is_angle() {
        let mut d = drive();
        d.write(Register::Config, ConfigCommand::Activate.code())
            .unwrap();
        d.write(Register::Config, ConfigCommand::PositionMode.code())
            .unwrap();
        d.write(Register::PositionRef, 4500).unwrap();
        d.advance(0.5);
        // 03, address 0x00C2, 1 register -> 03, 2 bytes, ANGLE.
        let reply = ask(&mut d, &[0x03, 0x00, 0xC2, 0x00, 0x01]).unwrap();
        assert_eq!(&reply[..2], &[0x03, 0x02]);
        let angle = i16::from_be_bytes([reply[2], reply[3]]);
        assert_eq!(angle, d.status().angle_centideg);
        assert!((angle - 4500).abs() <= 2, "{angle}");
        // Three RW registers from 0x0006: SPEED_REF, POSITION_REF, IQ_REF.
        let reply = ask(&mut d, &[0x03, 0x00, 0x06, 0x00, 0x03]).unwrap();
        assert_eq!(reply, [0x03, 0x06, 0, 0, 0x11, 0x94, 0, 0]);
    }

    #[test]
    fn illegal_function_for_everything_but_03_06_10() {
        let mut d = drive();
        for function in [0x01, 0x02, 0x04, 0x05, 0x0F, 0x11, 0x17, 0x2B, 0x41] {
            assert_eq!(
                ask(&mut d, &[function, 0x00, 0xC0, 0x00, 0x07]),
                Err(0x01),
                "{function:#04x}"
            );
        }
    }

    #[test]
    fn illegal_address_for_holes_odd_addresses_and_wrong_access() {
        let mut d = drive();
        for pdu in [
            [0x03, 0x00, 0x04, 0x00, 0x01], // hole in the table
            [0x03, 0x00, 0xC1, 0x00, 0x01], // odd address
            [0x03, 0x00, 0xC0, 0x00, 0x08], // one past the status block
            [0x03, 0x00, 0x02, 0x00, 0x01], // CONFIG is write-only
            [0x03, 0x00, 0x0C, 0x00, 0x03], // block ending in a save flag
            [0x06, 0x00, 0xC4, 0x00, 0x01], // SPEED is read-only
            [0x06, 0x00, 0x04, 0x00, 0x01], // hole
        ] {
            assert_eq!(ask(&mut d, &pdu), Err(0x02), "{pdu:02X?}");
        }
        // A block write over the hole at 0x0004.
        let pdu = [0x10, 0x00, 0x02, 0x00, 0x02, 0x04, 0x00, 0x00, 0x00, 0x00];
        assert_eq!(ask(&mut d, &pdu), Err(0x02));
    }

    #[test]
    fn illegal_value_for_ranges_and_malformed_counts() {
        let mut d = drive();
        d.write(Register::Config, 0).unwrap();
        for pdu in [
            vec![0x03, 0x00, 0xC0, 0x00, 0x00],       // quantity 0
            vec![0x03, 0x00, 0xC0, 0x00, 0x7E],       // quantity 126
            vec![0x06, 0x00, 0x06, 0x08, 0x00],       // speed 2048 rpm
            vec![0x06, 0x00, 0x08, 0x46, 0x51],       // position 180.01 deg
            vec![0x06, 0x00, 0x02, 0x00, 0x09],       // CONFIG 0x9 is no command
            vec![0x06, 0x00, 0x00, 0x00, 0x00],       // address 0
            vec![0x06, 0x00, 0x24, 0x00, 0x00],       // inertia 0
            vec![0x06, 0x00, 0xBE, 0x00, 0x02],       // USE_485_CONTROL 2
            vec![0x10, 0x00, 0x0C, 0x00, 0x03, 0x04], // byte count does not match
            vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04, 0x00, 0x01, 0x00], // data short
            vec![0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0x08, 0x00, 0, 0, 0, 0], // limit 2048
            vec![0x06, 0x00, 0x06, 0x00],             // truncated PDU
        ] {
            assert_eq!(ask(&mut d, &pdu), Err(0x03), "{pdu:02X?}");
        }
    }

    #[test]
    fn device_failure_and_busy_for_state_refusals() {
        let mut d = DriveModel::new(1, 3.75, false, 0.3);
        // Not active: setpoints refused with 0x04.
        assert_eq!(request(&mut d, DriveRequest::Speed { rpm: 10 }), Err(0x04));
        assert_eq!(
            request(&mut d, DriveRequest::Torque { counts: 10 }),
            Err(0x04)
        );
        // Fine-tune before calibrate: 0x04.
        let fine_tune = DriveRequest::Config(ConfigCommand::FineTuneCalibration);
        assert_eq!(request(&mut d, fine_tune), Err(0x04));
        // While calibrating: setpoints and mode changes are busy (0x06).
        request(&mut d, DriveRequest::Config(ConfigCommand::Activate)).unwrap();
        request(&mut d, DriveRequest::Config(ConfigCommand::Calibrate)).unwrap();
        assert_eq!(
            request(&mut d, DriveRequest::Position { centideg: 10 }),
            Err(0x06)
        );
        assert_eq!(
            request(&mut d, DriveRequest::Config(ConfigCommand::SpeedMode)),
            Err(0x06)
        );
        // Reads still work.
        assert!(request(&mut d, DriveRequest::ReadStatus).is_ok());
        d.advance(4.1);
        assert_eq!(
            request(&mut d, DriveRequest::Position { centideg: 10 }),
            Ok(DriveReply::Confirmed)
        );
        assert_eq!(request(&mut d, fine_tune), Ok(DriveReply::Confirmed));
    }

    #[test]
    fn block_writes_are_all_or_nothing() {
        let mut d = drive();
        // SPEED_REF, POSITION_REF, IQ_REF to an inactive drive: nothing is written.
        let pdu = [0x10, 0x00, 0x06, 0x00, 0x03, 0x06, 0, 5, 0, 5, 0, 5];
        assert_eq!(ask(&mut d, &pdu), Err(0x04));
        d.write(Register::Config, 0).unwrap();
        assert_eq!(ask(&mut d, &pdu), Ok(pdu[..5].to_vec()));
        assert_eq!(d.read(Register::IqRef), 5);
    }

    #[test]
    fn manual_blocks_are_acknowledged_and_applied() {
        let mut d = drive();
        let cases = [
            DriveRequest::OverCurrent {
                limit_counts: 128,
                stall_ms: 3000,
                save: false,
            },
            DriveRequest::SpeedRamp {
                alpha: 500_000,
                save: true,
            },
            DriveRequest::PositionRamp {
                alpha: 200,
                save: false,
            },
            DriveRequest::LoadInertia {
                ratio: 10,
                save: true,
            },
            DriveRequest::Rs485Control { enabled: true },
        ];
        for req in cases {
            assert_eq!(request(&mut d, req), Ok(DriveReply::Confirmed), "{req:?}");
        }
        let v = d.view();
        assert_eq!(
            (v.settings.stall_current, v.settings.stall_duration_ms),
            (128, 3000)
        );
        assert_eq!(v.settings.position_alpha, 200);
        assert_eq!(v.flash.settings.inertia_ratio, 10);
        assert_eq!(v.flash.settings.stall_current, 1536, "not saved");
    }

    #[test]
    fn broadcast_writes_without_replying_and_ignores_reads() {
        let mut d = drive();
        let mut scratch = Vec::new();
        broadcast(
            &mut d,
            &DriveRequest::SetAddress { address: 5 }.pdu().unwrap(),
            &mut scratch,
        );
        assert_eq!(d.address(), 5);
        broadcast(
            &mut d,
            &DriveRequest::Config(ConfigCommand::Activate).pdu().unwrap(),
            &mut scratch,
        );
        assert!(d.status().active());
        broadcast(
            &mut d,
            &DriveRequest::ReadStatus.pdu().unwrap(),
            &mut scratch,
        );
        assert!(scratch.is_empty());
    }
}
