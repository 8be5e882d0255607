//! What the gateway knows about a request PDU without asking a drive: whether
//! its shape is what the Modbus application protocol specifies for its
//! function code, whether it only reads, whether it may be broadcast.
//!
//! The shape check protects the bus: an RTU slave frames a request by the
//! length its function code implies, so a request of the wrong length would
//! be misframed by every drive, cost a timeout and its retries, and be
//! answered 0x0B. The specification has the server answer such a request
//! with exception 0x03 instead, which the gateway does at once. Function
//! codes it does not know pass unchecked: the drive answers those itself.

use crate::modbus::ExceptionCode;
use crate::modbus::function::be_u16;

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

/// True when the request only reads: the function codes the specification
/// defines as reads (and the device identification read of 0x2B). Anything
/// else, unknown codes included, may change a drive: it is refused on a
/// read-only listener and written to the audit log.
pub fn reads_only(pdu: &[u8]) -> bool {
    match pdu.first() {
        Some(0x01 | 0x02 | 0x03 | 0x04 | 0x07 | 0x0B | 0x0C | 0x11 | 0x14 | 0x18) => true,
        // Encapsulated interface transport, MEI 0x0E: read device identification.
        Some(0x2B) => pdu.get(1) == Some(&0x0E),
        _ => false,
    }
}

/// True for the write function codes the specification allows as a
/// broadcast (unit 0); a read broadcast has nobody to answer it.
pub fn broadcastable(pdu: &[u8]) -> bool {
    matches!(pdu.first(), Some(0x05 | 0x06 | 0x0F | 0x10 | 0x16))
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
            assert!(!reads_only(&[write, 0, 0, 0, 0]), "0x{write:02X}");
        }
        assert!(broadcastable(&[0x06, 0, 2, 0, 0]));
        assert!(!broadcastable(&[0x03, 0, 0xC0, 0, 7]));
    }

    #[test]
    fn broadcast_confirmations() {
        let single = [0x06, 0x00, 0x06, 0x00, 0x64];
        assert_eq!(write_confirmation(&single), single);
        let block = [0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0, 100, 0x03, 0xE8, 0, 0];
        assert_eq!(write_confirmation(&block), [0x10, 0x00, 0x0C, 0x00, 0x03]);
    }
}
