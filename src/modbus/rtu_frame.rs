//! RTU framing: an ADU is `unit, PDU, CRC(lo, hi)`.
//!
//! RTU frames carry no length field; a receiver either knows the length from
//! the function code (and, for some, a byte count) or waits for 3.5 character
//! times of silence. [`response_length`] and [`request_length`] say which,
//! from the bytes seen so far; both are pure and never panic on any input.

use super::crc::{crc_bytes, frame_crc_ok};
use super::function::{EXCEPTION_BIT, be_u16};

/// Smallest possible RTU frame: unit, function, CRC.
pub const MIN_FRAME: usize = 4;
/// Largest RTU frame the Modbus specification allows.
pub const MAX_FRAME: usize = 256;

/// What the bytes received so far say about the frame's total length.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameLength {
    /// Not enough bytes yet to tell.
    NeedMore,
    /// The frame is exactly this many bytes, CRC included.
    Known(usize),
    /// The function code does not tell: frame by the 3.5-character silence.
    BySilence,
}

/// Builds an ADU: unit, PDU, CRC.
pub fn encode(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(pdu.len() + 3);
    frame.push(unit);
    frame.extend_from_slice(pdu);
    let crc = crc_bytes(&frame);
    frame.extend_from_slice(&crc);
    frame
}

/// Why a received frame was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Shorter than unit + function + CRC.
    #[error("frame of {0} bytes is too short to be an RTU frame")]
    TooShort(usize),
    /// Longer than the 256 bytes Modbus allows.
    #[error("frame of {0} bytes is longer than the 256 bytes Modbus allows")]
    TooLong(usize),
    /// The CRC does not match: a corrupted or partial frame.
    #[error("CRC mismatch: the frame was corrupted on the wire")]
    Crc,
}

/// Checks the CRC and splits a whole frame into (unit, PDU).
pub fn decode(frame: &[u8]) -> Result<(u8, &[u8]), FrameError> {
    if frame.len() < MIN_FRAME {
        return Err(FrameError::TooShort(frame.len()));
    }
    if frame.len() > MAX_FRAME {
        return Err(FrameError::TooLong(frame.len()));
    }
    if !frame_crc_ok(frame) {
        return Err(FrameError::Crc);
    }
    Ok((frame[0], &frame[1..frame.len() - 2]))
}

/// Length of a reply frame (server to master) from its first bytes.
pub fn response_length(buf: &[u8]) -> FrameLength {
    let Some(&function) = buf.get(1) else {
        return FrameLength::NeedMore;
    };
    if function & EXCEPTION_BIT != 0 {
        // unit, function|0x80, code, CRC
        return FrameLength::Known(5);
    }
    match function {
        // unit, fc, byte count, data, CRC
        0x01 | 0x02 | 0x03 | 0x04 | 0x0C | 0x11 | 0x17 => byte_counted(buf, 2, 3),
        0x08 => diagnostics(buf),
        // unit, fc, address, value/quantity, CRC
        0x05 | 0x06 | 0x0B | 0x0F | 0x10 => FrameLength::Known(8),
        // unit, fc, status byte, CRC
        0x07 => FrameLength::Known(5),
        // unit, fc, address, and-mask, or-mask, CRC
        0x16 => FrameLength::Known(10),
        _ => FrameLength::BySilence,
    }
}

/// Length of a request frame (master to server) from its first bytes.
pub fn request_length(buf: &[u8]) -> FrameLength {
    let Some(&function) = buf.get(1) else {
        return FrameLength::NeedMore;
    };
    match function {
        0x01..=0x06 => FrameLength::Known(8),
        0x08 => diagnostics(buf),
        0x07 | 0x0B | 0x0C | 0x11 => FrameLength::Known(4),
        // unit, fc, address, quantity, byte count, data, CRC
        0x0F | 0x10 => byte_counted(buf, 6, 7),
        0x16 => FrameLength::Known(10),
        // unit, fc, read addr, read qty, write addr, write qty, byte count, data, CRC
        0x17 => byte_counted(buf, 10, 11),
        _ => FrameLength::BySilence,
    }
}

/// Length of the (normal) reply frame that answers the request `pdu`
/// (function code onward), when its function code tells; `None` for codes
/// whose reply length only the reply says. An exception reply (5 bytes) is
/// never longer.
pub fn expected_response_length(pdu: &[u8]) -> Option<usize> {
    let function = *pdu.first()?;
    let quantity = be_u16(pdu, 3).map(usize::from);
    match function {
        // unit, fc, byte count, data, CRC
        0x01 | 0x02 => Some(5 + quantity?.div_ceil(8)),
        0x03 | 0x04 => Some(5 + 2 * quantity?),
        0x17 => Some(5 + 2 * quantity?),
        0x05 | 0x06 | 0x0B | 0x0F | 0x10 => Some(8),
        0x07 => Some(5),
        0x16 => Some(10),
        // Diagnostics: "return query data" echoes the request, the other
        // sub-functions answer one word.
        0x08 => match be_u16(pdu, 1)? {
            0 => Some(pdu.len() + 3),
            _ => Some(8),
        },
        _ => None,
    }
    .map(|n| n.min(MAX_FRAME))
}

/// A diagnostics frame (0x08), request or reply alike: unit, fc,
/// sub-function, data, CRC. Sub-function 0000 ("return query data") echoes
/// any number of data words, so only the silence ends it; every other
/// sub-function carries one word.
fn diagnostics(buf: &[u8]) -> FrameLength {
    match (buf.get(2), buf.get(3)) {
        (Some(0), Some(0)) => FrameLength::BySilence,
        (Some(_), Some(_)) => FrameLength::Known(8),
        _ => FrameLength::NeedMore,
    }
}

/// A frame whose byte count sits at `at`, followed by that many bytes after a
/// `header`-byte header, then the CRC.
fn byte_counted(buf: &[u8], at: usize, header: usize) -> FrameLength {
    match buf.get(at) {
        Some(&n) => FrameLength::Known(header + usize::from(n) + 2),
        None => FrameLength::NeedMore,
    }
}

/// The register address and value (or quantity) of a 0x05/0x06/0x10 style PDU.
pub fn address_and_value(pdu: &[u8]) -> Option<(u16, u16)> {
    Some((be_u16(pdu, 1)?, be_u16(pdu, 3)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encode_adds_crc_low_byte_first() {
        // status read of unit 1 (frames.tsv: status_read)
        assert_eq!(
            encode(1, &[0x03, 0x00, 0xC0, 0x00, 0x07]),
            [0x01, 0x03, 0x00, 0xC0, 0x00, 0x07, 0x04, 0x34]
        );
    }

    #[test]
    fn decode_checks_crc_and_length() {
        let frame = [0x01, 0x83, 0x02, 0xC0, 0xF1]; // exception 02 from unit 1
        assert_eq!(decode(&frame), Ok((1, &frame[1..3])));
        assert_eq!(
            decode(&[0x01, 0x83, 0x02, 0xC0, 0xF2]),
            Err(FrameError::Crc)
        );
        assert_eq!(decode(&[0x01, 0x83]), Err(FrameError::TooShort(2)));
        assert_eq!(decode(&[0u8; 300]), Err(FrameError::TooLong(300)));
    }

    #[test]
    fn response_lengths() {
        assert_eq!(response_length(&[1]), FrameLength::NeedMore);
        assert_eq!(response_length(&[1, 0x03]), FrameLength::NeedMore);
        // status reply: 3 + 14 data + 2 CRC
        assert_eq!(response_length(&[1, 0x03, 0x0E]), FrameLength::Known(19));
        assert_eq!(response_length(&[1, 0x06]), FrameLength::Known(8));
        assert_eq!(response_length(&[1, 0x10]), FrameLength::Known(8));
        assert_eq!(response_length(&[1, 0x83]), FrameLength::Known(5));
        assert_eq!(response_length(&[1, 0x41]), FrameLength::BySilence);
        // diagnostics: return query data echoes any length; the others one word
        assert_eq!(response_length(&[1, 0x08, 0x00]), FrameLength::NeedMore);
        assert_eq!(
            response_length(&[1, 0x08, 0x00, 0x00]),
            FrameLength::BySilence
        );
        assert_eq!(
            response_length(&[1, 0x08, 0x00, 0x0B]),
            FrameLength::Known(8)
        );
        assert_eq!(response_length(&[1, 0x88]), FrameLength::Known(5));
    }

    #[test]
    fn expected_response_lengths() {
        // status read, 7 registers: 3 + 14 + 2
        assert_eq!(
            expected_response_length(&[0x03, 0x00, 0xC0, 0x00, 0x07]),
            Some(19)
        );
        // 125 registers: the longest frame, 255 bytes
        assert_eq!(
            expected_response_length(&[0x03, 0x00, 0x00, 0x00, 125]),
            Some(255)
        );
        // 9 coils: two data bytes
        assert_eq!(
            expected_response_length(&[0x01, 0x00, 0x00, 0x00, 9]),
            Some(7)
        );
        assert_eq!(
            expected_response_length(&[0x06, 0x00, 0x02, 0x00, 0x05]),
            Some(8)
        );
        assert_eq!(
            expected_response_length(&[0x10, 0x00, 0x0C, 0x00, 3, 6, 0, 1, 0, 2, 0, 0]),
            Some(8)
        );
        assert_eq!(
            expected_response_length(&[0x08, 0x00, 0x00, 0x12, 0x34]),
            Some(8)
        );
        assert_eq!(expected_response_length(&[0x2B, 0x0E, 0x01, 0x00]), None);
        // Too short to say.
        assert_eq!(expected_response_length(&[0x03, 0x00]), None);
        assert_eq!(expected_response_length(&[]), None);
    }

    #[test]
    fn request_lengths() {
        assert_eq!(request_length(&[1, 0x03]), FrameLength::Known(8));
        // protection write: 7 header + 6 data + 2 CRC
        assert_eq!(
            request_length(&[1, 0x10, 0, 0x0C, 0, 3, 6]),
            FrameLength::Known(15)
        );
        assert_eq!(
            request_length(&[1, 0x10, 0, 0x0C, 0, 3]),
            FrameLength::NeedMore
        );
        assert_eq!(request_length(&[1, 0x2B]), FrameLength::BySilence);
        assert_eq!(request_length(&[1, 0x08, 0x00]), FrameLength::NeedMore);
        assert_eq!(
            request_length(&[1, 0x08, 0x00, 0x00]),
            FrameLength::BySilence
        );
        assert_eq!(
            request_length(&[1, 0x08, 0x00, 0x01]),
            FrameLength::Known(8)
        );
    }
}
