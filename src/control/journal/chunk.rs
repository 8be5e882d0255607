//! One chunk of a framed file ([`super::format`]) read on its own, pure:
//! the part of a file between some byte and where the records read
//! before it begin, so that a file can be read from its end, the newest
//! records first, without reading what lies before.
//!
//! A chunk that does not begin right after the header begins inside some
//! record: its first whole record is found where the frames from there on
//! follow one another, each with its length and a matching CRC-32,
//! exactly to the chunk's end. A frame is at most `FRAME_LEN +
//! MAX_RECORD` bytes, so that place is within as much of the chunk's
//! start; bytes of JSON never read as a length a record can have, and a
//! CRC-32 that matches by chance, followed by a chain that ends exactly
//! where the next chunk begins, is a one in four billion coincidence
//! repeated. A chunk in which no such place is found holds a damaged
//! record: the file is not trusted, as a damaged record followed by good
//! ones never is.

use super::format::{self, FRAME_LEN, MAX_RECORD, Unreadable};

/// What one chunk holds.
#[derive(Debug, Clone, PartialEq)]
pub struct Chunk<T> {
    /// Its whole records, in order.
    pub records: Vec<T>,
    /// Where its first whole record begins, in the chunk: the end of the
    /// chunk before it.
    pub start: usize,
    /// Bytes of a torn last record left out (only at the file's end).
    pub torn: usize,
}

/// Decodes `bytes`, the part of a framed file from byte `base` on:
/// right after the header (`at_start`), or somewhere before the records
/// read so far, whose first byte it ends at; at the file's end (`at_end`)
/// a torn last record is left out.
pub fn decode<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
    base: u64,
    at_start: bool,
    at_end: bool,
) -> Result<Chunk<T>, Unreadable> {
    let start = if at_start {
        0
    } else {
        first_record(bytes, at_end).ok_or(Unreadable::Damaged {
            offset: base,
            why: "no run of whole records reaches the records after it",
        })?
    };
    let chain = format::frames(bytes, start, at_end).map_err(|(at, why)| Unreadable::Damaged {
        offset: base + at as u64,
        why,
    })?;
    let records = format::parse(bytes, &chain.payloads, base)?;
    Ok(Chunk {
        records,
        start,
        torn: bytes.len() - chain.good_len,
    })
}

/// Where the first whole record of `bytes` begins: the first place with
/// a whole frame from which the frames run to the end.
fn first_record(bytes: &[u8], at_end: bool) -> Option<usize> {
    let last = (FRAME_LEN + MAX_RECORD).min(bytes.len());
    (0..last).find(|&p| {
        matches!(format::frame_at(bytes, p), format::FrameAt::Whole(_))
            && format::frames(bytes, p, at_end).is_ok()
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::super::format::{Action, HEADER_LEN, HolderKind, ModeName, Record, encode, header};
    use super::*;

    fn lease(i: u64) -> Record {
        Record::Lease {
            drive: format!("drive-{i}"),
            owner: "scada".into(),
            holder: HolderKind::Http,
            deadline_ms: 1_700_000_000_000 + i,
            length_ms: 1000,
            action: Action::ZeroSpeed,
            mode: ModeName::Speed,
        }
    }

    fn journal(n: u64) -> Vec<u8> {
        let mut bytes = header();
        for i in 0..n {
            bytes.extend(encode(&lease(i)));
        }
        bytes
    }

    #[test]
    fn chunks_read_from_the_end_give_back_every_record_at_every_cut() {
        let whole = journal(300);
        let records = format::decode(&whole).unwrap().records;
        for size in [300, 1000, 4096, 9999] {
            // Chunks of `size` bytes, newest first, each ending where the
            // one after it began.
            let mut end = whole.len();
            let mut newest_first: Vec<Record> = Vec::new();
            loop {
                let start = end.saturating_sub(size).max(HEADER_LEN);
                let c: Chunk<Record> = decode(
                    &whole[start..end],
                    start as u64,
                    start == HEADER_LEN,
                    end == whole.len(),
                )
                .unwrap_or_else(|e| panic!("chunk {start}..{end}: {e}"));
                newest_first.extend(c.records.into_iter().rev());
                end = start + c.start;
                if start == HEADER_LEN {
                    break;
                }
            }
            newest_first.reverse();
            assert_eq!(newest_first, records, "chunks of {size}");
        }
    }

    #[test]
    fn a_torn_tail_is_left_out_at_the_end_only() {
        let mut bytes = journal(40);
        let whole = bytes.len();
        bytes.extend(encode(&lease(99)));
        bytes.truncate(whole + 30);
        let start = bytes.len() - 2000;
        let c: Chunk<Record> = decode(&bytes[start..], start as u64, false, true).unwrap();
        assert_eq!(c.torn, 30);
        assert_eq!(c.records.last(), Some(&lease(39)));
        // Not at the end, a chunk must end on a record's end.
        assert!(decode::<Record>(&bytes[start..], start as u64, false, false).is_err());
    }

    #[test]
    fn a_damaged_record_in_a_chunk_is_not_trusted() {
        // Further into the chunk than a record can be long: not taken for
        // the part of a record that began before the chunk.
        let mut bytes = journal(2000);
        let start = bytes.len() - 200_000;
        bytes[start + 150_000] ^= 0x55;
        let e = decode::<Record>(&bytes[start..], start as u64, false, true).unwrap_err();
        assert!(matches!(e, Unreadable::Damaged { .. }), "{e}");
    }
}
