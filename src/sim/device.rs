//! A plain Modbus device sharing the bus with the drives: an energy meter
//! or an I/O module as the gateway sees it, 65536 holding registers behind
//! 0x03, 0x06 and 0x10. Pure code.
//!
//! The drives' own table is a few registers; this is what long replies come
//! from (a 125-register read is the longest Modbus frame, 255 bytes, 265 ms
//! at 9600 baud), and what a Modbus TCP client reaches through the unit map
//! next to the drives. Register `a` holds `a` until written.

use crate::modbus::ExceptionCode;
use crate::modbus::function::{
    EXCEPTION_BIT, READ_HOLDING_REGISTERS, WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16,
};

/// Most registers one read may ask for (Modbus application protocol).
const MAX_READ: u16 = 125;
/// Most registers one block write may carry.
const MAX_WRITE: u16 = 123;

/// A device of 65536 holding registers.
#[derive(Debug, Clone)]
pub struct RegisterDevice {
    unit: u8,
    registers: Vec<u16>,
}

impl RegisterDevice {
    /// A device at `unit` whose register `a` holds `a`.
    pub fn new(unit: u8) -> Self {
        Self {
            unit,
            registers: (0..=u16::MAX).collect(),
        }
    }

    /// Its address.
    pub fn unit(&self) -> u8 {
        self.unit
    }

    /// The value of register `address`.
    pub fn register(&self, address: u16) -> u16 {
        self.registers[usize::from(address)]
    }

    /// Answers `pdu` into `reply`; returns the exception if it is one.
    pub fn answer(&mut self, pdu: &[u8], reply: &mut Vec<u8>) -> Option<ExceptionCode> {
        reply.clear();
        let function = pdu.first().copied().unwrap_or(0);
        let result = match function {
            READ_HOLDING_REGISTERS => self.read(pdu, reply),
            WRITE_SINGLE_REGISTER => self.write_single(pdu, reply),
            WRITE_MULTIPLE_REGISTERS => self.write_block(pdu, reply),
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

    /// The registers `start..start + count`, if they all exist.
    fn range(start: u16, count: u16) -> Result<std::ops::Range<usize>, ExceptionCode> {
        let (start, count) = (usize::from(start), usize::from(count));
        if start + count > 1 << 16 {
            return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS);
        }
        Ok(start..start + count)
    }

    fn read(&self, pdu: &[u8], reply: &mut Vec<u8>) -> Result<(), ExceptionCode> {
        let (Some(start), Some(count), 5) = (be_u16(pdu, 1), be_u16(pdu, 3), pdu.len()) else {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        };
        if count == 0 || count > MAX_READ {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let range = Self::range(start, count)?;
        reply.push(READ_HOLDING_REGISTERS);
        reply.push((count * 2) as u8);
        for value in &self.registers[range] {
            reply.extend_from_slice(&value.to_be_bytes());
        }
        Ok(())
    }

    fn write_single(&mut self, pdu: &[u8], reply: &mut Vec<u8>) -> Result<(), ExceptionCode> {
        let (Some(address), Some(value), 5) = (be_u16(pdu, 1), be_u16(pdu, 3), pdu.len()) else {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        };
        self.registers[usize::from(address)] = value;
        reply.extend_from_slice(pdu);
        Ok(())
    }

    fn write_block(&mut self, pdu: &[u8], reply: &mut Vec<u8>) -> Result<(), ExceptionCode> {
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
        let range = Self::range(start, count)?;
        for (i, register) in range.enumerate() {
            self.registers[register] = be_u16(pdu, 6 + 2 * i).unwrap_or(0);
        }
        reply.extend_from_slice(&pdu[..5]);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_of_up_to_125_registers() {
        let mut d = RegisterDevice::new(100);
        let mut reply = Vec::new();
        // 125 registers from 0x1000: byte count 250, then 0x1000, 0x1001...
        assert_eq!(d.answer(&[0x03, 0x10, 0x00, 0x00, 125], &mut reply), None);
        assert_eq!(reply.len(), 2 + 250);
        assert_eq!(reply[1], 250);
        assert_eq!(&reply[2..6], &[0x10, 0x00, 0x10, 0x01]);
        assert_eq!(&reply[250..], &[0x10, 0x7C]);
        // 126 is one too many; past the last register does not exist.
        assert_eq!(
            d.answer(&[0x03, 0x00, 0x00, 0x00, 126], &mut reply),
            Some(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(reply, [0x83, 0x03]);
        assert_eq!(
            d.answer(&[0x03, 0xFF, 0xFF, 0x00, 2], &mut reply),
            Some(ExceptionCode::ILLEGAL_DATA_ADDRESS)
        );
        assert_eq!(
            d.answer(&[0x04, 0x00, 0x00, 0x00, 1], &mut reply),
            Some(ExceptionCode::ILLEGAL_FUNCTION)
        );
    }

    #[test]
    fn writes_are_kept() {
        let mut d = RegisterDevice::new(100);
        let mut reply = Vec::new();
        let write = [0x06, 0x00, 0x05, 0xAB, 0xCD];
        assert_eq!(d.answer(&write, &mut reply), None);
        assert_eq!(reply, write);
        let block = [0x10, 0x00, 0x07, 0x00, 0x02, 0x04, 0x00, 0x01, 0x00, 0x02];
        assert_eq!(d.answer(&block, &mut reply), None);
        assert_eq!(reply, &block[..5]);
        assert_eq!(
            (d.register(5), d.register(7), d.register(8), d.register(9)),
            (0xABCD, 1, 2, 9)
        );
        // A byte count that does not match.
        assert_eq!(
            d.answer(
                &[0x10, 0x00, 0x07, 0x00, 0x02, 0x02, 0x00, 0x01],
                &mut reply
            ),
            Some(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
    }
}
