//! One frame seen on the wire, as the bus thread hands it to the monitor:
//! a short frame's bytes inline (a status poll's request and reply, a
//! write of a few registers), a longer one's in a buffer of the slot that
//! stays when the slot is overwritten, so the ring allocates at most once
//! per slot, for its first long frame, and a record takes about 160 bytes,
//! not the 350 a whole 256-byte frame inline took.

use crate::bus::Origin;
use crate::modbus::rtu_frame::MAX_FRAME;

/// Bytes of a request kept with each reply, so a reply can be decoded
/// (and filtered) without its request: unit, function, address, count.
/// The bus's tap keeps as many.
pub use crate::bus::tap::REQUEST_HEAD;
use crate::listed::listed_enum;

/// Which way a frame went.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Direction {
    /// drivegate to the drives.
    #[default]
    Request,
    /// A drive to drivegate, or the absence of a reply (a timeout).
    Reply,
    /// Bytes that belonged to no reply: noise, late replies, echoes.
    Noise,
}

impl Direction {
    /// Stable name: `request`, `reply`, `noise`.
    pub fn name(self) -> &'static str {
        match self {
            Direction::Request => "request",
            Direction::Reply => "reply",
            Direction::Noise => "noise",
        }
    }
}

listed_enum! {
    /// What became of a frame.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub enum FrameOutcome {
        /// A request put on the wire (its reply says how it went).
        #[default]
        Sent,
        /// A broadcast put on the wire: nobody answers those.
        Broadcast,
        /// A valid reply.
        Ok,
        /// A valid exception reply.
        Exception,
        /// No reply within the response timeout (the record has no bytes).
        Timeout,
        /// A reply with a wrong CRC.
        CrcError,
        /// A reply that does not answer the request (wrong unit, function,
        /// content or length).
        BadReply,
        /// Stray bytes.
        Stray,
    }
}

impl FrameOutcome {
    /// Stable name for the API, CSV and filters.
    pub fn name(self) -> &'static str {
        match self {
            FrameOutcome::Sent => "sent",
            FrameOutcome::Broadcast => "broadcast",
            FrameOutcome::Ok => "ok",
            FrameOutcome::Exception => "exception",
            FrameOutcome::Timeout => "timeout",
            FrameOutcome::CrcError => "crc_error",
            FrameOutcome::BadReply => "bad_reply",
            FrameOutcome::Stray => "stray",
        }
    }

    /// The outcome named `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|o| o.name() == name)
    }

    /// True for replies that failed an attempt (the master tries again,
    /// or gives up).
    pub fn is_fault(self) -> bool {
        matches!(
            self,
            FrameOutcome::Timeout | FrameOutcome::CrcError | FrameOutcome::BadReply
        )
    }
}

/// Bytes of a frame kept in its record itself; a longer frame's go to the
/// record's buffer.
pub const INLINE: usize = 32;

/// One frame.
#[derive(Debug, Clone)]
pub struct FrameRecord {
    /// Position in the bus's sequence of frames, from 0.
    pub seq: u64,
    /// When, in ns since the monitor started: a request's first byte, a
    /// reply's last byte (or the moment its timeout ran out), when stray
    /// bytes were read.
    pub at_ns: u64,
    /// Which way.
    pub direction: Direction,
    /// The unit the transaction addressed (a reply from another unit still
    /// carries the unit asked; its bytes tell who answered).
    pub unit: u8,
    /// Attempt of the transaction, 1 for the first (2 = first retry).
    pub attempt: u8,
    /// What became of it.
    pub outcome: FrameOutcome,
    /// Why a reply was refused (`BadReply`), else empty.
    pub detail: &'static str,
    /// Replies: from the end of the request on the wire to the start of the
    /// reply, in µs (estimated from the reply's end and length).
    pub turnaround_us: Option<u32>,
    /// The silence on the line before the frame, in µs, as the master
    /// measured it: before a request, from the end of the last frame to
    /// its first byte; before a reply, its turnaround.
    pub silence_us: Option<u32>,
    /// Who caused the transaction.
    pub origin: Origin,
    /// Replies: the first bytes of their request (see [`REQUEST_HEAD`]).
    pub request: [u8; REQUEST_HEAD],
    /// How many of `request` are valid.
    pub request_len: u8,
    /// True when `request` holds the whole request frame (CRC included).
    pub request_whole: bool,
    /// Bytes seen (may exceed what `bytes` keeps, for long noise).
    pub len: u16,
    /// A frame of at most [`INLINE`] bytes.
    pub(super) inline: [u8; INLINE],
    /// A longer frame's first bytes, up to [`MAX_FRAME`]; empty (its room
    /// kept) when the frame is inline.
    pub(super) long: Vec<u8>,
}

impl Default for FrameRecord {
    fn default() -> Self {
        Self {
            seq: 0,
            at_ns: 0,
            direction: Direction::Request,
            unit: 0,
            attempt: 0,
            outcome: FrameOutcome::Sent,
            detail: "",
            turnaround_us: None,
            silence_us: None,
            origin: Origin::Internal,
            request: [0; REQUEST_HEAD],
            request_len: 0,
            request_whole: false,
            len: 0,
            inline: [0; INLINE],
            long: Vec::new(),
        }
    }
}

impl FrameRecord {
    /// The bytes kept.
    pub fn bytes(&self) -> &[u8] {
        if self.long.is_empty() {
            &self.inline[..usize::from(self.len).min(INLINE)]
        } else {
            &self.long
        }
    }

    /// The request head kept with a reply (empty for others).
    pub fn request(&self) -> &[u8] {
        &self.request[..usize::from(self.request_len).min(REQUEST_HEAD)]
    }

    /// Sets the frame's bytes (the first [`MAX_FRAME`] are kept). A long
    /// frame's buffer is made room for a whole frame the first time, so
    /// the slot never allocates again.
    pub fn set_bytes(&mut self, bytes: &[u8]) {
        let kept = &bytes[..bytes.len().min(MAX_FRAME)];
        self.long.clear();
        if kept.len() <= INLINE {
            self.inline[..kept.len()].copy_from_slice(kept);
        } else {
            self.long.reserve_exact(MAX_FRAME);
            self.long.extend_from_slice(kept);
        }
        self.len = u16::try_from(bytes.len()).unwrap_or(u16::MAX);
    }

    /// Sets the request head of a reply: the first bytes of the request
    /// frame, `whole` when they are all of it.
    pub fn set_request(&mut self, request: &[u8], whole: bool) {
        let kept = request.len().min(REQUEST_HEAD);
        self.request[..kept].copy_from_slice(&request[..kept]);
        self.request_len = kept as u8;
        self.request_whole = whole && kept == request.len();
    }

    /// The PDU of a reply's request: whole (unit and CRC stripped) when the
    /// request was short enough to keep, else its first bytes.
    pub fn request_pdu(&self) -> &[u8] {
        let head = self.request();
        if self.request_whole && head.len() >= 4 {
            &head[1..head.len() - 2]
        } else {
            head.get(1..).unwrap_or(&[])
        }
    }

    /// The Modbus function of the transaction (without the exception bit):
    /// a request's own, a reply's request's.
    pub fn function(&self) -> Option<u8> {
        match self.direction {
            Direction::Request => self.bytes().get(1).copied(),
            Direction::Reply => self
                .request()
                .get(1)
                .or_else(|| self.bytes().get(1))
                .map(|f| f & 0x7F),
            Direction::Noise => None,
        }
    }

    /// Memory one record takes in the ring, in bytes.
    pub const SIZE: usize = std::mem::size_of::<FrameRecord>();
}

// A record stays small: the ring's slots are most of its memory.
const _: () = assert!(FrameRecord::SIZE <= 160);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_bytes_and_request_head() {
        let mut r = FrameRecord::default();
        r.set_bytes(&[1, 3, 0, 0xC0, 0, 7, 0x04, 0x34]);
        assert_eq!(r.bytes(), &[1, 3, 0, 0xC0, 0, 7, 0x04, 0x34]);
        assert_eq!(r.function(), Some(3));
        r.direction = Direction::Reply;
        r.set_bytes(&[1, 0x83, 2, 0xC0, 0xF1]);
        r.set_request(&[1, 3, 0, 0xC0, 0, 7, 0x04, 0x34], true);
        assert_eq!(r.request().len(), REQUEST_HEAD);
        assert_eq!(r.request_pdu(), &[3, 0, 0xC0, 0, 7]);
        assert_eq!(r.function(), Some(3));
        r.set_request(
            &[1, 0x10, 0, 0x0C, 0, 3, 6, 0, 1, 2, 3, 4, 5, 6, 7, 8],
            true,
        );
        assert!(!r.request_whole);
        assert_eq!(r.request_pdu(), &[0x10, 0, 0x0C, 0, 3, 6, 0]);
        // Long noise keeps the first 256 bytes and says how many there were.
        r.set_bytes(&[0x55; 300]);
        assert_eq!((r.len, r.bytes().len()), (300, 256));
        // A short frame after it in the same slot is its own, and the
        // buffer's room stays for the next long one.
        r.set_bytes(&[1, 3, 14]);
        assert_eq!(r.bytes(), &[1, 3, 14]);
        let room = r.long.capacity();
        assert!(room >= MAX_FRAME);
        let long: Vec<u8> = (0..=40).collect();
        r.set_bytes(&long);
        assert_eq!(r.bytes(), &long[..]);
        assert_eq!(r.long.capacity(), room);
        // A frame of exactly INLINE bytes stays inline.
        r.set_bytes(&[7; INLINE]);
        assert_eq!(r.bytes(), &[7; INLINE]);
        assert!(r.long.is_empty());
    }

    #[test]
    fn outcome_names_round_trip() {
        for o in FrameOutcome::ALL {
            assert_eq!(FrameOutcome::from_name(o.name()), Some(o));
        }
        assert!(FrameOutcome::CrcError.is_fault() && !FrameOutcome::Exception.is_fault());
    }
}
