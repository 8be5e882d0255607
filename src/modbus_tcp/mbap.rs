//! The Modbus TCP frame: a 7-byte MBAP header (transaction id, protocol id 0,
//! length, unit id) and the PDU. Pure code on byte slices, no I/O.
//!
//! [`check`] says whether a whole frame is in the buffer and how long it is,
//! refusing a bad header as soon as its six bytes are there, so a stream of
//! garbage is caught before the daemon waits for a body that never ends;
//! [`parse`] then decodes it.

/// Bytes of the MBAP header, unit id included.
pub const HEADER_LEN: usize = 7;
/// Largest PDU Modbus allows (253: an RTU frame is at most 256 bytes).
pub const MAX_PDU: usize = 253;
/// Largest whole frame.
pub const MAX_FRAME: usize = HEADER_LEN + MAX_PDU;

/// One request as it came off the socket.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// The client's transaction id, echoed in the reply.
    pub transaction: u16,
    /// The unit id: which drive (0 = broadcast).
    pub unit: u8,
    /// Function code and data.
    pub pdu: Vec<u8>,
}

/// Why the bytes on a connection are not Modbus TCP. The stream cannot be
/// resynchronised after any of these (MBAP has no frame marker), so the
/// connection is closed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum MbapError {
    /// The protocol id must be 0 (Modbus).
    #[error("protocol id {0} is not Modbus (0): not a Modbus TCP client?")]
    ProtocolId(u16),
    /// The length field counts the unit id and the PDU: 2 to 254.
    #[error("length field {0} is out of range: valid 2 to 254 (unit id + PDU of 1 to 253 bytes)")]
    Length(u16),
    /// Function codes are 1 to 127; 0 and 128 and up (exception replies)
    /// cannot start a request.
    #[error("function code 0x{0:02X} cannot start a request: valid 0x01 to 0x7F")]
    Function(u8),
}

/// Length of the whole frame at the start of `buf`, `None` until it is all
/// there; an error as soon as the header is bad.
pub fn check(buf: &[u8]) -> Result<Option<usize>, MbapError> {
    if buf.len() < 6 {
        return Ok(None);
    }
    let protocol = u16::from_be_bytes([buf[2], buf[3]]);
    if protocol != 0 {
        return Err(MbapError::ProtocolId(protocol));
    }
    let length = u16::from_be_bytes([buf[4], buf[5]]);
    if !(2..=(MAX_PDU as u16 + 1)).contains(&length) {
        return Err(MbapError::Length(length));
    }
    if let Some(&function) = buf.get(HEADER_LEN)
        && !(0x01..=0x7F).contains(&function)
    {
        return Err(MbapError::Function(function));
    }
    let total = 6 + usize::from(length);
    Ok((buf.len() >= total).then_some(total))
}

/// Decodes the frame at the start of `buf`: the frame and the bytes it used.
pub fn parse(buf: &[u8]) -> Result<Option<(Frame, usize)>, MbapError> {
    let Some(total) = check(buf)? else {
        return Ok(None);
    };
    let frame = Frame {
        transaction: u16::from_be_bytes([buf[0], buf[1]]),
        unit: buf[6],
        pdu: buf[HEADER_LEN..total].to_vec(),
    };
    Ok(Some((frame, total)))
}

/// Appends the reply frame for `transaction` and `unit` carrying `pdu`.
pub fn encode(transaction: u16, unit: u8, pdu: &[u8], out: &mut Vec<u8>) {
    // A reply PDU comes from the drive through the RTU master (at most 253
    // bytes) or from the gateway itself (a few bytes).
    let pdu = &pdu[..pdu.len().min(MAX_PDU)];
    out.extend_from_slice(&transaction.to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
    out.push(unit);
    out.extend_from_slice(pdu);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Transaction 0x1234, protocol 0, length 6, unit 1, read 7 registers at
    /// 0x00C0 (the status block).
    const STATUS_READ: [u8; 12] = [
        0x12, 0x34, 0x00, 0x00, 0x00, 0x06, 0x01, 0x03, 0x00, 0xC0, 0x00, 0x07,
    ];

    #[test]
    fn a_whole_frame_is_parsed() {
        let (frame, used) = parse(&STATUS_READ).unwrap().unwrap();
        assert_eq!(used, 12);
        assert_eq!(
            frame,
            Frame {
                transaction: 0x1234,
                unit: 1,
                pdu: vec![0x03, 0x00, 0xC0, 0x00, 0x07]
            }
        );
    }

    #[test]
    fn partial_frames_wait_for_more() {
        for n in 0..STATUS_READ.len() {
            assert_eq!(check(&STATUS_READ[..n]), Ok(None), "{n} bytes");
        }
        // Two frames back to back (pipelining): the first is taken alone.
        let mut two = STATUS_READ.to_vec();
        two.extend_from_slice(&STATUS_READ);
        assert_eq!(check(&two), Ok(Some(12)));
    }

    #[test]
    fn bad_headers_are_refused_before_the_body_arrives() {
        // protocol id 1
        assert_eq!(check(&[0, 1, 0, 1, 0, 6]), Err(MbapError::ProtocolId(1)));
        // length 1: a unit id and no function code
        assert_eq!(check(&[0, 1, 0, 0, 0, 1]), Err(MbapError::Length(1)));
        // length 0
        assert_eq!(check(&[0, 1, 0, 0, 0, 0]), Err(MbapError::Length(0)));
        // length 255: a PDU of 254 bytes, one too many
        assert_eq!(check(&[0, 1, 0, 0, 0, 255]), Err(MbapError::Length(255)));
        // An HTTP request sent to the Modbus port.
        assert!(check(b"GET / HTTP/1.1\r\n").is_err());
        // Function code 0x83 (an exception reply, not a request) and 0x00.
        assert_eq!(
            check(&[0, 1, 0, 0, 0, 3, 1, 0x83]),
            Err(MbapError::Function(0x83))
        );
        assert_eq!(
            check(&[0, 1, 0, 0, 0, 3, 1, 0x00]),
            Err(MbapError::Function(0x00))
        );
    }

    #[test]
    fn the_longest_frame_is_accepted() {
        let mut frame = vec![0, 9, 0, 0, 0, 254, 1, 0x10];
        frame.resize(MAX_FRAME, 0);
        assert_eq!(check(&frame), Ok(Some(MAX_FRAME)));
        assert_eq!(parse(&frame).unwrap().unwrap().0.pdu.len(), MAX_PDU);
    }

    #[test]
    fn replies_echo_transaction_and_unit() {
        let mut out = Vec::new();
        // Exception 0x0B for a read of unit 9, transaction 0xBEEF.
        encode(0xBEEF, 9, &[0x83, 0x0B], &mut out);
        assert_eq!(out, [0xBE, 0xEF, 0x00, 0x00, 0x00, 0x03, 0x09, 0x83, 0x0B]);
    }

    proptest::proptest! {
        #[test]
        fn no_input_panics(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..300)) {
            let _ = parse(&bytes);
        }

        #[test]
        fn a_request_survives_encode_then_parse(
            transaction in proptest::prelude::any::<u16>(),
            unit in proptest::prelude::any::<u8>(),
            function in 1u8..=0x7F,
            data in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..MAX_PDU),
        ) {
            let mut pdu = vec![function];
            pdu.extend_from_slice(&data);
            let mut out = Vec::new();
            encode(transaction, unit, &pdu, &mut out);
            let (frame, used) = parse(&out).unwrap().unwrap();
            proptest::prop_assert_eq!(used, out.len());
            proptest::prop_assert_eq!(frame, Frame { transaction, unit, pdu });
        }
    }
}
