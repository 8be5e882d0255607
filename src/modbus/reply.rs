//! Does a reply frame answer the request it follows? The checks an RTU master
//! makes, since RTU frames carry no transaction id: CRC, unit, function, and
//! the content a standard reply must repeat (an echo repeats the write, an
//! acknowledgement its address and count, a read the byte count asked for).

use super::function::{EXCEPTION_BIT, be_u16};
use super::rtu_frame::{self, FrameError};

/// Why a frame does not answer the request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mismatch {
    /// The CRC is wrong: corrupted on the wire.
    Crc,
    /// Too short or too long to be a frame.
    Malformed,
    /// From another unit than the one asked.
    OtherUnit,
    /// For another function than the one asked.
    OtherFunction,
    /// Right unit and function, but not the answer to this request.
    OtherRequest,
}

impl Mismatch {
    /// Text for error messages.
    pub fn describe(self) -> &'static str {
        match self {
            Mismatch::Crc => "CRC error",
            Mismatch::Malformed => "malformed frame",
            Mismatch::OtherUnit => "reply from another unit",
            Mismatch::OtherFunction => "reply to another function",
            Mismatch::OtherRequest => "reply does not answer the request",
        }
    }
}

/// Checks `frame` (a whole RTU frame) against the request PDU `request`
/// sent to `unit`; returns the reply PDU (an exception reply included).
pub fn check(unit: u8, request: &[u8], frame: &[u8]) -> Result<Vec<u8>, Mismatch> {
    let (from, reply) = rtu_frame::decode(frame).map_err(|e| match e {
        FrameError::Crc => Mismatch::Crc,
        FrameError::TooShort(_) | FrameError::TooLong(_) => Mismatch::Malformed,
    })?;
    if from != unit {
        return Err(Mismatch::OtherUnit);
    }
    let Some(&function) = request.first() else {
        return Err(Mismatch::OtherRequest);
    };
    match reply.first() {
        Some(&f) if f == function | EXCEPTION_BIT && reply.len() == 2 => return Ok(reply.to_vec()),
        Some(&f) if f == function => {}
        _ => return Err(Mismatch::OtherFunction),
    }
    let answers = match function {
        // Echo of the request (diagnostics: "return query data" only;
        // the counters answer with their value).
        0x05 | 0x06 => reply == request,
        0x08 if be_u16(request, 1) == Some(0) => reply == request,
        // Address and quantity of the request.
        0x0F | 0x10 => reply.len() == 5 && request.len() >= 5 && reply[1..5] == request[1..5],
        // Byte count of the quantity asked for.
        0x03 | 0x04 => be_u16(request, 3).is_some_and(|q| {
            reply.len() == 2 + 2 * usize::from(q) && usize::from(reply[1]) == 2 * usize::from(q)
        }),
        0x01 | 0x02 => be_u16(request, 3).is_some_and(|q| {
            let bytes = usize::from(q).div_ceil(8);
            reply.len() == 2 + bytes && usize::from(reply[1]) == bytes
        }),
        _ => true,
    };
    if answers {
        Ok(reply.to_vec())
    } else {
        Err(Mismatch::OtherRequest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_must_answer_their_request() {
        // unit 1, read 7 registers from 0x00C0, answered with 14 bytes
        let read = [0x03, 0x00, 0xC0, 0x00, 0x07];
        let mut reply = vec![0x03, 0x0E];
        reply.extend_from_slice(&[0; 14]);
        let frame = rtu_frame::encode(1, &reply);
        assert_eq!(check(1, &read, &frame), Ok(reply.clone()));
        assert_eq!(check(2, &read, &frame), Err(Mismatch::OtherUnit));
        // A one-register read answered with 14 bytes is not its answer.
        let read_one = [0x03, 0x00, 0xC2, 0x00, 0x01];
        assert_eq!(check(1, &read_one, &frame), Err(Mismatch::OtherRequest));

        // SPEED_REF = 100: the echo must repeat it, a stale echo of 101 does not.
        let write = [0x06, 0x00, 0x06, 0x00, 0x64];
        assert_eq!(
            check(1, &write, &rtu_frame::encode(1, &write)),
            Ok(write.to_vec())
        );
        let stale = [0x06, 0x00, 0x06, 0x00, 0x65];
        assert_eq!(
            check(1, &write, &rtu_frame::encode(1, &stale)),
            Err(Mismatch::OtherRequest)
        );
        // exception 03 to the write: a valid reply.
        let exception = [0x86, 0x03];
        assert_eq!(
            check(1, &write, &rtu_frame::encode(1, &exception)),
            Ok(exception.to_vec())
        );
        assert_eq!(
            check(1, &read, &rtu_frame::encode(1, &exception)),
            Err(Mismatch::OtherFunction)
        );
        let mut corrupted = rtu_frame::encode(1, &write);
        corrupted[7] ^= 0xFF;
        assert_eq!(check(1, &write, &corrupted), Err(Mismatch::Crc));
        assert_eq!(check(1, &write, &[1, 6]), Err(Mismatch::Malformed));

        // protection block at 0x000C, count 3: ack must name 0x000C, 3.
        let block = [
            0x10, 0x00, 0x0C, 0x00, 0x03, 0x06, 0, 0x80, 0x0B, 0xB8, 0, 0,
        ];
        let ack = [0x10, 0x00, 0x0C, 0x00, 0x03];
        assert_eq!(
            check(1, &block, &rtu_frame::encode(1, &ack)),
            Ok(ack.to_vec())
        );
        let other_ack = [0x10, 0x00, 0x24, 0x00, 0x02];
        assert_eq!(
            check(1, &block, &rtu_frame::encode(1, &other_ack)),
            Err(Mismatch::OtherRequest)
        );
        // Return query data: the echo must repeat every data word.
        let query = [0x08, 0x00, 0x00, 0x12, 0x34, 0x56, 0x78];
        assert_eq!(
            check(1, &query, &rtu_frame::encode(1, &query)),
            Ok(query.to_vec())
        );
        assert_eq!(
            check(1, &query, &rtu_frame::encode(1, &query[..5])),
            Err(Mismatch::OtherRequest)
        );
        // An empty request never matches anything.
        assert_eq!(
            check(1, &[], &rtu_frame::encode(1, &ack)),
            Err(Mismatch::OtherRequest)
        );
    }
}
