//! What the gateway knows about a request PDU without asking a drive: whether
//! its shape is what the Modbus application protocol specifies for its
//! function code, whether it only reads, whether it may be broadcast, and
//! the reply a client gets when the drive was sent another function.
//!
//! The shape check protects the bus: an RTU slave frames a request by the
//! length its function code implies, so a request of the wrong length would
//! be misframed by every drive, cost a timeout and its retries, and be
//! answered 0x0B. The specification has the server answer such a request
//! with exception 0x03 instead, which the gateway does at once. Function
//! codes it does not know are not checked here: they are not reads, so
//! the control core refuses them unless `raw_functions` lists them.

use crate::modbus::ExceptionCode;
use crate::modbus::function::{
    EXCEPTION_BIT, Effect, MASK_WRITE_REGISTER, READ_DEVICE_IDENTIFICATION,
    READ_WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER, be_u16, effect,
};

/// Checks the request's length and quantities against the Modbus
/// application protocol (V1.1b3, section 6) for the function codes it
/// defines with a fixed layout.
pub fn check_shape(pdu: &[u8]) -> Result<(), ExceptionCode> {
    let Some(&function) = pdu.first() else {
        return Err(ExceptionCode::ILLEGAL_FUNCTION);
    };
    let bad = Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    let word = |at: usize| be_u16(pdu, at).unwrap_or(0);
    let counted = |header: usize| {
        // header bytes, then a byte count and that many bytes
        pdu.get(header)
            .is_some_and(|&n| pdu.len() == header + 1 + usize::from(n))
    };
    match function {
        // read coils / discrete inputs: address, quantity 1..=2000
        0x01 | 0x02 if pdu.len() != 5 || !(1..=2000).contains(&word(3)) => bad,
        // read holding / input registers: address, quantity 1..=125
        0x03 | 0x04 if pdu.len() != 5 || !(1..=125).contains(&word(3)) => bad,
        // write single coil: address, 0x0000 or 0xFF00
        0x05 if pdu.len() != 5 || !matches!(word(3), 0x0000 | 0xFF00) => bad,
        // write single register: address, value
        0x06 if pdu.len() != 5 => bad,
        // diagnostics: sub-function, then data in whole words; "return
        // query data" (0000) echoes any number of them, every other
        // sub-function takes one (section 6.8)
        0x08 => {
            let ok = match word(1) {
                _ if pdu.len() < 5 => false,
                0x0000 => pdu.len() % 2 == 1,
                _ => pdu.len() == 5,
            };
            if ok { Ok(()) } else { bad }
        }
        // read exception status, comm event counter and log, report server id
        0x07 | 0x0B | 0x0C | 0x11 if pdu.len() != 1 => bad,
        // write multiple coils: quantity 1..=1968, byte count ceil(q / 8)
        0x0F => {
            let q = word(3);
            let ok = counted(5)
                && (1..=0x07B0).contains(&q)
                && usize::from(pdu[5]) == usize::from(q).div_ceil(8);
            if ok { Ok(()) } else { bad }
        }
        // write multiple registers: quantity 1..=123, byte count 2 q
        0x10 => {
            let q = word(3);
            let ok =
                counted(5) && (1..=123).contains(&q) && usize::from(pdu[5]) == usize::from(q) * 2;
            if ok { Ok(()) } else { bad }
        }
        // mask write register: address, and-mask, or-mask
        0x16 if pdu.len() != 7 => bad,
        // read file record: byte count 7..=245, sub-requests of 7 bytes
        0x14 => file_records(pdu, false),
        // write file record: byte count 9..=251, each sub-request with its data
        0x15 => file_records(pdu, true),
        // read FIFO queue: its pointer address
        0x18 if pdu.len() != 3 => bad,
        // read device identification: MEI type, read code 1..=4, object id
        0x2B if pdu.get(1) == Some(&READ_DEVICE_IDENTIFICATION)
            && (pdu.len() != 4 || !(1..=4).contains(&pdu[2])) =>
        {
            bad
        }
        // read/write multiple registers: read 1..=125, write 1..=121
        0x17 => {
            let (rq, wq) = (word(3), word(7));
            let ok = counted(9)
                && (1..=125).contains(&rq)
                && (1..=121).contains(&wq)
                && usize::from(pdu[9]) == usize::from(wq) * 2;
            if ok { Ok(()) } else { bad }
        }
        _ => Ok(()),
    }
}

/// A file record request (0x14 read, 0x15 write): a byte count, then
/// sub-requests of reference type 6, file, record and length (and, for a
/// write, the record's data), which must fill the byte count exactly.
fn file_records(pdu: &[u8], write: bool) -> Result<(), ExceptionCode> {
    let bad = Err(ExceptionCode::ILLEGAL_DATA_VALUE);
    let Some(&count) = pdu.get(1) else {
        return bad;
    };
    let (min, max) = if write { (9, 0xFB) } else { (7, 0xF5) };
    if !(min..=max).contains(&count) || pdu.len() != 2 + usize::from(count) {
        return bad;
    }
    let mut at = 2;
    while at < pdu.len() {
        let (Some(6), Some(length)) = (pdu.get(at), be_u16(pdu, at + 5)) else {
            return bad;
        };
        at += 7 + if write { 2 * usize::from(length) } else { 0 };
    }
    if at == pdu.len() { Ok(()) } else { bad }
}

/// True when the request only reads: the function codes the specification
/// defines as reads, diagnostics' sub-functions that return data, and the
/// device identification read of 0x2B. Anything else, unknown codes
/// included, may change a drive: it goes to the control core, which
/// decides on it (and audits it).
pub fn reads_only(pdu: &[u8]) -> bool {
    effect(pdu) == Effect::Read
}

/// True for a request that may be broadcast (unit 0): anything that is
/// not a read, whose reply nobody would send (read/write multiple reads
/// too). Whether it goes is the control core's to decide.
pub fn broadcastable(pdu: &[u8]) -> bool {
    !reads_only(pdu) && pdu.first() != Some(&READ_WRITE_MULTIPLE_REGISTERS)
}

/// The reply a client gets for its write `pdu` when the drive confirmed
/// it with `reply`: as it came, except for a mask write, which went to the
/// drive as a 0x06 and is answered, as the specification says, with the
/// request echoed. An exception reply goes back under the client's
/// function code.
pub fn reply_to(pdu: &[u8], mut reply: Vec<u8>) -> Vec<u8> {
    let function = pdu.first().copied().unwrap_or(0);
    match reply.first().copied() {
        Some(f) if f & EXCEPTION_BIT != 0 => {
            reply[0] = function | EXCEPTION_BIT;
            reply
        }
        Some(WRITE_SINGLE_REGISTER) if function == MASK_WRITE_REGISTER => pdu.to_vec(),
        _ => reply,
    }
}

/// The reply a device gives to a write it carried out, built from the
/// request: what a broadcast is answered with when replies are configured.
pub fn write_confirmation(pdu: &[u8]) -> Vec<u8> {
    match pdu.first() {
        // 0x0F, 0x10: function, address, quantity
        Some(0x0F | 0x10) => pdu[..pdu.len().min(5)].to_vec(),
        // 0x05, 0x06, 0x16: the request echoed
        _ => pdu.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const VALUE: Result<(), ExceptionCode> = Err(ExceptionCode::ILLEGAL_DATA_VALUE);

    #[test]
    fn well_formed_requests_pass() {
        // status read: 7 registers at 0x00C0
        assert_eq!(check_shape(&[0x03, 0x00, 0xC0, 0x00, 0x07]), Ok(()));
        // speed setpoint 100 rpm
        assert_eq!(check_shape(&[0x06, 0x00, 0x06, 0x00, 0x64]), Ok(()));
        // protection: 3 registers at 0x000C, 6 bytes
        assert_eq!(
            check_shape(&[0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0, 100, 0x03, 0xE8, 0, 0]),
            Ok(())
        );
        // write 10 coils: 2 bytes
        assert_eq!(check_shape(&[0x0F, 0, 0, 0, 10, 2, 0xFF, 0x03]), Ok(()));
        // report server id, mask write, read/write multiple
        assert_eq!(check_shape(&[0x11]), Ok(()));
        assert_eq!(check_shape(&[0x16, 0, 4, 0, 0xF2, 0, 0x25]), Ok(()));
        assert_eq!(
            check_shape(&[0x17, 0, 3, 0, 6, 0, 0x0E, 0, 1, 2, 0, 0xFF]),
            Ok(())
        );
        // diagnostics: return query data with one word, and with three;
        // clear counters (000A) with its one word
        assert_eq!(check_shape(&[0x08, 0x00, 0x00, 0xA5, 0x37]), Ok(()));
        assert_eq!(
            check_shape(&[0x08, 0x00, 0x00, 0x12, 0x34, 0x56, 0x78, 0x9A, 0xBC]),
            Ok(())
        );
        assert_eq!(check_shape(&[0x08, 0x00, 0x0A, 0x00, 0x00]), Ok(()));
        // codes the specification leaves open pass unchecked
        assert_eq!(check_shape(&[0x41, 1, 2, 3]), Ok(()));
        assert_eq!(check_shape(&[0x2B, 0x0E, 0x01, 0x00]), Ok(()));
        assert_eq!(check_shape(&[0x2B, 0x0D, 0x00, 0x01]), Ok(()));
        // read file record: file 4, record 1, 2 registers; FIFO at 0x04DE
        assert_eq!(check_shape(&[0x14, 7, 6, 0, 4, 0, 1, 0, 2]), Ok(()));
        assert_eq!(check_shape(&[0x18, 0x04, 0xDE]), Ok(()));
        // write file record: file 4, record 7, one register 0x06AF
        assert_eq!(
            check_shape(&[0x15, 9, 6, 0, 4, 0, 7, 0, 1, 0x06, 0xAF]),
            Ok(())
        );
    }

    #[test]
    fn file_fifo_and_identification_requests_must_fit_their_layout() {
        // byte count that does not match, reference type other than 6
        assert_eq!(check_shape(&[0x14, 8, 6, 0, 4, 0, 1, 0, 2]), VALUE);
        assert_eq!(check_shape(&[0x14, 7, 5, 0, 4, 0, 1, 0, 2]), VALUE);
        assert_eq!(check_shape(&[0x14]), VALUE);
        // write file record whose length says 2 registers but carries 1
        assert_eq!(
            check_shape(&[0x15, 9, 6, 0, 4, 0, 7, 0, 2, 0x06, 0xAF]),
            VALUE
        );
        assert_eq!(check_shape(&[0x18, 0x04]), VALUE);
        assert_eq!(check_shape(&[0x2B, 0x0E, 0x05, 0x00]), VALUE);
        assert_eq!(check_shape(&[0x2B, 0x0E, 0x01]), VALUE);
    }

    #[test]
    fn a_mask_write_sent_as_0x06_is_answered_with_its_echo() {
        let mask = [0x16, 0x00, 0x06, 0x00, 0x00, 0x00, 0x64];
        assert_eq!(reply_to(&mask, vec![0x06, 0x00, 0x06, 0x00, 0x64]), mask);
        assert_eq!(reply_to(&mask, vec![0x86, 0x03]), [0x96, 0x03]);
        let single = [0x06, 0x00, 0x06, 0x00, 0x64];
        assert_eq!(reply_to(&single, single.to_vec()), single);
        assert_eq!(reply_to(&single, vec![0x86, 0x04]), [0x86, 0x04]);
    }

    #[test]
    fn quantities_out_of_range_are_refused() {
        // read quantity 0 and 126
        assert_eq!(check_shape(&[0x03, 0x00, 0xC0, 0x00, 0x00]), VALUE);
        assert_eq!(check_shape(&[0x03, 0x00, 0xC0, 0x00, 126]), VALUE);
        assert_eq!(check_shape(&[0x01, 0x00, 0x00, 0x07, 0xD1]), VALUE);
        // coil value other than ON/OFF
        assert_eq!(check_shape(&[0x05, 0x00, 0x01, 0x12, 0x34]), VALUE);
        // block write of 124 registers
        let mut big = vec![0x10, 0, 0, 0, 124, 248];
        big.resize(6 + 248, 0);
        assert_eq!(check_shape(&big), VALUE);
    }

    #[test]
    fn lengths_that_do_not_match_are_refused() {
        // read with a trailing byte, a truncated read
        assert_eq!(check_shape(&[0x03, 0x00, 0xC0, 0x00, 0x07, 0x00]), VALUE);
        assert_eq!(check_shape(&[0x03, 0x00, 0xC0]), VALUE);
        // block write: byte count 6 but 4 data bytes
        assert_eq!(check_shape(&[0x10, 0, 0x0C, 0, 3, 6, 0, 1, 0, 2]), VALUE);
        // block write: byte count 4 for 3 registers
        assert_eq!(check_shape(&[0x10, 0, 0x0C, 0, 3, 4, 0, 1, 0, 2]), VALUE);
        // coils: 10 coils need 2 bytes, not 1
        assert_eq!(check_shape(&[0x0F, 0, 0, 0, 10, 1, 0xFF]), VALUE);
        assert_eq!(check_shape(&[0x11, 0x00]), VALUE);
        assert_eq!(check_shape(&[0x16, 0, 4, 0, 0xF2]), VALUE);
        assert_eq!(check_shape(&[0x06, 0x00, 0x06]), VALUE);
        // diagnostics: half a word of query data, none at all, a second
        // word for a sub-function that takes one, no sub-function
        assert_eq!(check_shape(&[0x08, 0x00, 0x00, 0x12, 0x34, 0x56]), VALUE);
        assert_eq!(check_shape(&[0x08, 0x00, 0x00]), VALUE);
        assert_eq!(check_shape(&[0x08, 0x00, 0x0A, 0, 0, 0, 0]), VALUE);
        assert_eq!(check_shape(&[0x08, 0x00]), VALUE);
    }

    #[test]
    fn reads_and_writes_are_told_apart() {
        assert!(reads_only(&[0x03, 0x00, 0xC0, 0x00, 0x07]));
        assert!(reads_only(&[0x2B, 0x0E, 0x01, 0x00]));
        assert!(!reads_only(&[0x2B, 0x0D, 0x00]));
        for write in [0x05, 0x06, 0x0F, 0x10, 0x15, 0x16, 0x17, 0x08, 0x41] {
            assert!(!reads_only(&[write, 0, 1, 0, 0]), "0x{write:02X}");
        }
        // Diagnostics that only return data are reads; a restart is not.
        assert!(reads_only(&[0x08, 0x00, 0x0B, 0x00, 0x00]));
        assert!(!reads_only(&[0x08, 0x00, 0x01, 0x00, 0x00]));
        assert!(broadcastable(&[0x06, 0, 2, 0, 0]));
        assert!(broadcastable(&[0x41, 0, 2]));
        assert!(!broadcastable(&[0x03, 0, 0xC0, 0, 7]));
        assert!(!broadcastable(&[0x17, 0, 0xC0, 0, 7, 0, 6, 0, 1, 2, 0, 0]));
    }

    #[test]
    fn broadcast_confirmations() {
        let single = [0x06, 0x00, 0x06, 0x00, 0x64];
        assert_eq!(write_confirmation(&single), single);
        let block = [0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0, 100, 0x03, 0xE8, 0, 0];
        assert_eq!(write_confirmation(&block), [0x10, 0x00, 0x0C, 0x00, 0x03]);
    }
}
