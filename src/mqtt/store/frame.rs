//! The store's file format, pure: no I/O here.
//!
//! ```text
//! segment header:  "DRVGMQST" (8 bytes)  version: u32 LE (1)
//! frame:           length: u32 LE  crc32(body): u32 LE  body (`length` bytes)
//! body:            at_ms: u64 LE  topic length: u16 LE  topic (UTF-8)  payload
//! ```
//!
//! The same shape as the safety journal's (`control::journal::format`): a
//! segment is only appended to, and a power cut can leave its last frame
//! half written, so each frame says how long it is and carries a CRC-32.
//! Unlike the journal, nothing here is a promise about a motor: a damaged
//! frame is skipped and counted, never a reason to refuse the rest, and a
//! length that cannot be true ends the segment's reading there.

use crate::control::journal::format::crc32;

/// The first 8 bytes of a segment.
pub const MAGIC: &[u8; 8] = b"DRVGMQST";
/// The format this drivegate writes and reads.
pub const VERSION: u32 = 1;
/// Segment header length: the magic and the version.
pub const HEADER_LEN: usize = 12;
/// A frame's head: its length and its CRC.
pub const FRAME_LEN: usize = 8;
/// The fixed part of a body: the time and the topic's length.
const BODY_HEAD: usize = 10;
/// No frame is longer (an MQTT message of the face is far shorter): a
/// longer length field is garbage.
pub const MAX_BODY: usize = 1024 * 1024;

/// One outgoing message kept while it could not be sent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoredMessage {
    /// The MQTT topic it goes to.
    pub topic: String,
    /// Its payload, as it would have been published.
    pub payload: Vec<u8>,
    /// When it was produced, Unix time in ms.
    pub at_ms: u64,
}

/// Why a message cannot be framed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TooLarge {
    /// The topic is longer than a u16 can say (MQTT's own limit).
    #[error("its topic is {0} bytes; MQTT topics are at most 65535")]
    Topic(usize),
    /// The body is longer than [`MAX_BODY`].
    #[error("it is {0} bytes; a stored message is at most {MAX_BODY}")]
    Body(usize),
}

/// A segment's header.
pub fn header() -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_LEN);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out
}

/// One message, framed.
pub fn encode(m: &StoredMessage) -> Result<Vec<u8>, TooLarge> {
    let topic_len = u16::try_from(m.topic.len()).map_err(|_| TooLarge::Topic(m.topic.len()))?;
    let body_len = BODY_HEAD + m.topic.len() + m.payload.len();
    if body_len > MAX_BODY {
        return Err(TooLarge::Body(body_len));
    }
    let mut body = Vec::with_capacity(body_len);
    body.extend_from_slice(&m.at_ms.to_le_bytes());
    body.extend_from_slice(&topic_len.to_le_bytes());
    body.extend_from_slice(m.topic.as_bytes());
    body.extend_from_slice(&m.payload);
    let mut out = Vec::with_capacity(FRAME_LEN + body_len);
    // body_len <= MAX_BODY fits a u32.
    out.extend_from_slice(&(body_len as u32).to_le_bytes());
    out.extend_from_slice(&crc32(&body).to_le_bytes());
    out.extend_from_slice(&body);
    Ok(out)
}

/// A message read back, with where its frame ends in the segment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Framed {
    /// The message.
    pub message: StoredMessage,
    /// Byte offset just past its frame: where a reader that has sent it
    /// resumes.
    pub end: usize,
    /// Its frame's length in bytes.
    pub len: usize,
}

/// A segment read back.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Decoded {
    /// Its good messages at or after the offset asked for, in order.
    pub messages: Vec<Framed>,
    /// Bytes of good frames, header included: where the next append goes.
    pub good_len: usize,
    /// Frames skipped because their CRC or content was wrong.
    pub damaged: u64,
    /// Bytes after `good_len` left out: a torn last frame, or everything
    /// after a length that cannot be true.
    pub torn: usize,
}

/// Why a file is not a segment at all.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NotASegment {
    /// The file does not start with the magic.
    #[error("it is not a drivegate MQTT store segment (its first bytes are not \"DRVGMQST\")")]
    Magic,
    /// Another version of the format.
    #[error("it is in format version {0}; this drivegate reads version {VERSION}")]
    Version(u32),
}

/// Checks a segment's first bytes (its header, or all of it if shorter):
/// true for a whole header, false for an empty file or a header torn
/// while the file was created (an empty segment).
pub fn check_header(head: &[u8]) -> Result<bool, NotASegment> {
    if head.len() < HEADER_LEN {
        let n = head.len().min(MAGIC.len());
        if head[..n] == MAGIC[..n] {
            return Ok(false);
        }
        return Err(NotASegment::Magic);
    }
    if &head[..8] != MAGIC {
        return Err(NotASegment::Magic);
    }
    let version = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if version != VERSION {
        return Err(NotASegment::Version(version));
    }
    Ok(true)
}

/// The body length and CRC a frame's head says, if the length can be
/// true.
pub fn frame_head(head: &[u8; FRAME_LEN]) -> Option<(usize, u32)> {
    let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
    let crc = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
    (BODY_HEAD..=MAX_BODY).contains(&len).then_some((len, crc))
}

/// Where the first whole frame of `bytes` (some part of a segment, not
/// from its start) begins: a length that can be true and a body whose
/// CRC-32 matches, which bytes of another frame pass only by a one in
/// four billion chance. `None` within its first `FRAME_LEN + MAX_BODY`
/// bytes: there is none.
pub fn first_frame(bytes: &[u8]) -> Option<usize> {
    (0..(FRAME_LEN + MAX_BODY).min(bytes.len())).find(|&p| {
        let Some(head) = bytes.get(p..p + FRAME_LEN) else {
            return false;
        };
        let head: [u8; FRAME_LEN] = head.try_into().unwrap_or([0; FRAME_LEN]);
        let Some((len, crc)) = frame_head(&head) else {
            return false;
        };
        bytes
            .get(p + FRAME_LEN..p + FRAME_LEN + len)
            .is_some_and(|body| crc32(body) == crc)
    })
}

/// Reads a segment's bytes, keeping the messages whose frames start at or
/// after `from` (a reader's cursor). An empty file or a torn header is an
/// empty segment (a crash while creating it).
pub fn decode(bytes: &[u8], from: usize) -> Result<Decoded, NotASegment> {
    if !check_header(&bytes[..bytes.len().min(HEADER_LEN)])? {
        return Ok(Decoded {
            torn: bytes.len(),
            ..Decoded::default()
        });
    }
    let mut out = Decoded::default();
    let mut at = HEADER_LEN;
    while at < bytes.len() {
        let rest = &bytes[at..];
        if rest.len() < FRAME_LEN {
            break; // a torn frame head
        }
        let head: [u8; FRAME_LEN] = rest[..FRAME_LEN].try_into().unwrap_or([0; FRAME_LEN]);
        let Some((len, crc)) = frame_head(&head) else {
            break; // garbage where a length should be: nothing after it can be found
        };
        let Some(body) = rest.get(FRAME_LEN..FRAME_LEN + len) else {
            break; // a torn body
        };
        let end = at + FRAME_LEN + len;
        let message = if crc32(body) == crc {
            parse_body(body)
        } else {
            None
        };
        match message {
            Some(message) if at >= from => out.messages.push(Framed {
                message,
                end,
                len: FRAME_LEN + len,
            }),
            Some(_) => {}
            // The last frame with a bad CRC is torn (its sectors reached
            // the disk out of order); one in the middle is damaged.
            None if end == bytes.len() => break,
            None => out.damaged += 1,
        }
        at = end;
    }
    out.good_len = at;
    out.torn = bytes.len() - at;
    Ok(out)
}

fn parse_body(body: &[u8]) -> Option<StoredMessage> {
    let at_ms = u64::from_le_bytes(body.get(..8)?.try_into().ok()?);
    let topic_len = u16::from_le_bytes(body.get(8..10)?.try_into().ok()?) as usize;
    let topic = std::str::from_utf8(body.get(BODY_HEAD..BODY_HEAD + topic_len)?).ok()?;
    Some(StoredMessage {
        topic: topic.to_string(),
        payload: body[BODY_HEAD + topic_len..].to_vec(),
        at_ms,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn msg(topic: &str, payload: &[u8], at_ms: u64) -> StoredMessage {
        StoredMessage {
            topic: topic.into(),
            payload: payload.to_vec(),
            at_ms,
        }
    }

    fn segment(messages: &[StoredMessage]) -> Vec<u8> {
        let mut bytes = header();
        for m in messages {
            bytes.extend(encode(m).unwrap());
        }
        bytes
    }

    fn plain(d: &Decoded) -> Vec<StoredMessage> {
        d.messages.iter().map(|f| f.message.clone()).collect()
    }

    #[test]
    fn a_frame_is_its_length_crc_time_topic_and_payload() {
        let bytes = encode(&msg("a/b", &[0xAA], 0x0102)).unwrap();
        assert_eq!(
            bytes,
            [
                14, 0, 0, 0, // body length: 8 + 2 + 3 + 1
                0x29, 0xC4, 0x94, 0xBA, // crc32 of the body
                0x02, 0x01, 0, 0, 0, 0, 0, 0, // at_ms 0x0102
                3, 0, // topic length
                b'a', b'/', b'b', // topic
                0xAA, // payload
            ]
        );
        assert_eq!(
            u32::from_le_bytes(bytes[4..8].try_into().unwrap()),
            crc32(&bytes[8..])
        );
    }

    #[test]
    fn messages_read_back_in_order_with_their_ends() {
        let ms = [
            msg("t/1", b"one", 1),
            msg("t/2", b"", 2),
            msg("t/3", b"three", 3),
        ];
        let bytes = segment(&ms);
        let d = decode(&bytes, 0).unwrap();
        assert_eq!(plain(&d), ms);
        assert_eq!((d.good_len, d.torn, d.damaged), (bytes.len(), 0, 0));
        assert_eq!(d.messages[2].end, bytes.len());
        // From the first message's end on: the other two.
        let from = d.messages[0].end;
        assert_eq!(plain(&decode(&bytes, from).unwrap()), ms[1..]);
    }

    #[test]
    fn a_torn_last_frame_is_ignored_at_every_cut() {
        let first = msg("t", b"first", 1);
        let whole = segment(&[first.clone(), msg("t", b"second", 2)]);
        let first_end = segment(std::slice::from_ref(&first)).len();
        for cut in first_end + 1..whole.len() {
            let d = decode(&whole[..cut], 0).unwrap();
            assert_eq!(plain(&d), std::slice::from_ref(&first), "cut at {cut}");
            assert_eq!((d.good_len, d.torn), (first_end, cut - first_end));
        }
        let mut garbled = whole.clone();
        let last = garbled.len() - 1;
        garbled[last] ^= 0x55;
        let d = decode(&garbled, 0).unwrap();
        assert_eq!((plain(&d), d.damaged), (vec![first], 0));
    }

    #[test]
    fn a_damaged_frame_in_the_middle_is_skipped_and_counted() {
        let ms = [msg("t", b"a", 1), msg("t", b"b", 2), msg("t", b"c", 3)];
        let mut bytes = segment(&ms);
        let second_payload = segment(&ms[..2]).len() - 1;
        bytes[second_payload] ^= 0xFF;
        let d = decode(&bytes, 0).unwrap();
        assert_eq!(plain(&d), [ms[0].clone(), ms[2].clone()]);
        assert_eq!((d.damaged, d.torn), (1, 0));
    }

    #[test]
    fn an_impossible_length_ends_the_reading_without_failing() {
        let mut bytes = segment(&[msg("t", b"a", 1)]);
        let good = bytes.len();
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&[0; 40]);
        let d = decode(&bytes, 0).unwrap();
        assert_eq!(d.messages.len(), 1);
        assert_eq!((d.good_len, d.torn), (good, 44));
    }

    #[test]
    fn other_files_and_versions_are_not_segments() {
        assert_eq!(decode(b"hello, not a segment", 0), Err(NotASegment::Magic));
        let mut v2 = header();
        v2[8] = 2;
        assert_eq!(decode(&v2, 0), Err(NotASegment::Version(2)));
        assert_eq!(decode(b"DRVG", 0).unwrap().torn, 4);
        assert!(decode(b"", 0).unwrap().messages.is_empty());
    }

    #[test]
    fn the_first_whole_frame_is_found_inside_a_segment() {
        let ms: Vec<_> = (0..50).map(|i| msg("t/x", &[i as u8; 30], i)).collect();
        let bytes = segment(&ms);
        let ends: Vec<usize> = decode(&bytes, 0)
            .unwrap()
            .messages
            .iter()
            .map(|f| f.end)
            .collect();
        for cut in HEADER_LEN..bytes.len() - 100 {
            let p = first_frame(&bytes[cut..]).unwrap();
            let next = std::iter::once(HEADER_LEN)
                .chain(ends.iter().copied())
                .find(|&e| e >= cut)
                .unwrap();
            assert_eq!(cut + p, next, "from {cut}");
        }
    }

    #[test]
    fn oversized_messages_are_refused_in_words() {
        let long_topic = "t".repeat(70_000);
        assert_eq!(
            encode(&msg(&long_topic, b"", 0)),
            Err(TooLarge::Topic(70_000))
        );
        let e = encode(&msg("t", &vec![0; MAX_BODY], 0)).unwrap_err();
        assert!(e.to_string().contains("at most 1048576"), "{e}");
    }
}
