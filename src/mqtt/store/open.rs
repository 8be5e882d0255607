//! What an earlier process left in the store, read back within bounds, so
//! that a store of any size neither stalls a start nor fills the memory:
//!
//! - segments are kept newest first while they fit `store_max_mb`; the
//!   older ones are removed unread (what the bound would have dropped);
//! - a segment longer than a segment may be (`store_max_mb / 8`: this
//!   daemon starts a new one there; a longer one was not written by it)
//!   keeps its newest part of that length, from its first whole frame on,
//!   copied to a new file a buffer at a time;
//! - each kept segment's frames are counted by their heads, a buffer at a
//!   time, without reading their bodies; a torn last frame (cut short, or
//!   with a CRC that does not match) is cut off. A frame damaged in the
//!   middle is found, counted and skipped when it is replayed.
//!
//! What is skipped is counted in bytes and logged.

use std::collections::VecDeque;
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufReader, Read, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use super::Segment;
use super::frame::{self, FRAME_LEN, HEADER_LEN, MAX_BODY};
use crate::control::journal::format::crc32;
use crate::control::journal::tail::size;

/// What was found.
#[derive(Debug, Default)]
pub(super) struct Found {
    /// The segments kept, oldest first.
    pub segments: VecDeque<Segment>,
    /// Where the replay stands in the oldest (the cursor, unless its
    /// segment was cut or removed).
    pub cursor: u64,
    /// Bytes skipped unread.
    pub skipped: u64,
    /// What is worth saying, in words.
    pub news: Vec<String>,
}

/// Reads back the segments `ids` (sorted) of the store in `dir`, with the
/// cursor `(segment, offset)`, within `max_bytes` and segments of
/// `segment_bytes`.
pub(super) fn scan(
    dir: &Path,
    ids: &[u64],
    (cursor_id, cursor_at): (u64, u64),
    max_bytes: u64,
    segment_bytes: u64,
) -> io::Result<Found> {
    let path = |id: u64| super::segment_path(dir, id);
    let mut found = Found {
        cursor: HEADER_LEN as u64,
        ..Found::default()
    };
    let mut kept: Vec<(u64, u64)> = Vec::new();
    let mut total = 0u64;
    let (mut removed, mut removed_bytes) = (0, 0);
    for &id in ids.iter().rev() {
        if id < cursor_id {
            // Replayed before the cursor moved past it; its removal was
            // cut short.
            fs::remove_file(path(id))?;
            continue;
        }
        let len = fs::metadata(path(id))?.len();
        if kept.is_empty() || total + len <= max_bytes {
            total += len;
            kept.push((id, len));
        } else {
            fs::remove_file(path(id))?;
            removed += 1;
            removed_bytes += len;
        }
    }
    if removed > 0 {
        found.skipped += removed_bytes;
        found.news.push(format!(
            "MQTT store: {removed} older segments ({}) beyond [mqtt] store_max_mb were removed unread",
            size(removed_bytes)
        ));
    }
    for (id, len) in kept.into_iter().rev() {
        let at = if id == cursor_id { cursor_at } else { 0 };
        if let Some((segment, whole)) = keep(&path(id), id, len, at, segment_bytes, &mut found)? {
            if id == cursor_id && found.segments.is_empty() && whole {
                found.cursor = cursor_at.max(HEADER_LEN as u64);
            }
            found.segments.push_back(segment);
        }
    }
    Ok(found)
}

/// Reads back one segment, and whether its head was kept (not cut):
/// `None` when it holds nothing (removed) or is not a segment (set
/// aside).
fn keep(
    path: &Path,
    id: u64,
    len: u64,
    from: u64,
    segment_bytes: u64,
    found: &mut Found,
) -> io::Result<Option<(Segment, bool)>> {
    let mut head = vec![0u8; usize::try_from(len.min(HEADER_LEN as u64)).unwrap_or(0)];
    File::open(path)?.read_exact_at(&mut head, 0)?;
    match frame::check_header(&head) {
        Ok(true) => {}
        Ok(false) => {
            fs::remove_file(path)?;
            return Ok(None);
        }
        Err(why) => {
            // Not ours to read: set aside, never deleted.
            tracing::warn!("MQTT store: {} is set aside: {why}", path.display());
            fs::rename(path, path.with_extension("unreadable"))?;
            return Ok(None);
        }
    }
    let longest = segment_bytes + (FRAME_LEN + MAX_BODY) as u64;
    let whole = len <= longest;
    let (len, from) = if !whole {
        let skipped = cut(path, len, segment_bytes)?;
        found.skipped += skipped;
        found.news.push(format!(
            "MQTT store: {} is {}, longer than a segment may be ([mqtt] store_max_mb / 8): its newest {} are kept, the {} before them skipped unread",
            path.display(),
            size(len),
            size(len - skipped),
            size(skipped)
        ));
        (fs::metadata(path)?.len(), 0)
    } else {
        (len, from)
    };
    let walked = walk(path, len, from)?;
    if walked.good_len < len {
        // Appends go after the good frames.
        let f = OpenOptions::new().write(true).open(path)?;
        f.set_len(walked.good_len)?;
        f.sync_all()?;
    }
    if walked.good_len <= HEADER_LEN as u64 {
        fs::remove_file(path)?;
        return Ok(None);
    }
    Ok(Some((
        Segment {
            id,
            len: walked.good_len,
            messages: walked.messages,
            bytes: walked.bytes,
        },
        whole,
    )))
}

/// A segment's frames, counted by their heads.
#[derive(Debug, Default, PartialEq, Eq)]
struct Walked {
    /// Frames starting at or after the offset asked for.
    messages: u64,
    /// Their bytes.
    bytes: u64,
    /// Where the last whole frame ends.
    good_len: u64,
}

/// Counts the frames of the segment at `path` (`len` bytes) from `from`
/// on, reading their heads only, and checks the last one's CRC.
fn walk(path: &Path, len: u64, from: u64) -> io::Result<Walked> {
    let file = File::open(path)?;
    let mut reader = BufReader::with_capacity(64 * 1024, file.try_clone()?);
    reader.seek(SeekFrom::Start(HEADER_LEN as u64))?;
    let mut w = Walked::default();
    let mut at = HEADER_LEN as u64;
    let mut last = None;
    while len - at >= FRAME_LEN as u64 {
        let mut head = [0u8; FRAME_LEN];
        reader.read_exact(&mut head)?;
        // A length that cannot be true ends the reading there.
        let Some((body, crc)) = frame::frame_head(&head) else {
            break;
        };
        let end = at + (FRAME_LEN + body) as u64;
        if end > len {
            break; // a torn frame
        }
        reader.seek_relative(i64::try_from(body).unwrap_or(0))?;
        let counted = at >= from;
        if counted {
            w.messages += 1;
            w.bytes += end - at;
        }
        last = Some((at, body, crc, counted));
        at = end;
    }
    // A last frame whose sectors reached the disk out of order is torn.
    if let Some((start, body, crc, counted)) = last
        && at == len
    {
        let mut bytes = vec![0u8; body];
        file.read_exact_at(&mut bytes, start + FRAME_LEN as u64)?;
        if crc32(&bytes) != crc {
            at = start;
            if counted {
                w.messages -= 1;
                w.bytes -= (FRAME_LEN + body) as u64;
            }
        }
    }
    w.good_len = at;
    Ok(w)
}

/// Cuts the segment at `path` (`len` bytes) to its newest `keep` bytes,
/// from its first whole frame there on: a new segment, written a buffer
/// at a time, synced and renamed over it. Returns the bytes skipped.
fn cut(path: &Path, len: u64, keep: u64) -> io::Result<u64> {
    let from = len - keep;
    let file = File::open(path)?;
    let mut window =
        vec![0u8; usize::try_from(keep.min((2 * (FRAME_LEN + MAX_BODY)) as u64)).unwrap_or(0)];
    file.read_exact_at(&mut window, from)?;
    let Some(first) = frame::first_frame(&window) else {
        // No frame in it: nothing of it can be kept.
        let f = OpenOptions::new().write(true).open(path)?;
        f.set_len(HEADER_LEN as u64)?;
        f.sync_all()?;
        return Ok(len - HEADER_LEN as u64);
    };
    let start = from + first as u64;
    let tmp: PathBuf = path.with_extension("cut");
    let mut out = File::create(&tmp)?;
    out.write_all(&frame::header())?;
    let mut reader = BufReader::with_capacity(64 * 1024, file);
    reader.seek(SeekFrom::Start(start))?;
    io::copy(&mut reader, &mut out)?;
    out.sync_all()?;
    fs::rename(&tmp, path)?;
    Ok(start - HEADER_LEN as u64)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::super::frame::{StoredMessage, encode};
    use super::*;

    fn msg(i: u64) -> StoredMessage {
        StoredMessage {
            topic: format!("drive{}", i % 8),
            payload: vec![(i % 251) as u8; 60],
            at_ms: 1_700_000_000_000 + i,
        }
    }

    fn segment(dir: &Path, id: u64, messages: impl Iterator<Item = u64>) -> u64 {
        let mut bytes = frame::header();
        for i in messages {
            bytes.extend(encode(&msg(i)).unwrap());
        }
        fs::write(super::super::segment_path(dir, id), &bytes).unwrap();
        bytes.len() as u64
    }

    #[test]
    fn older_segments_beyond_the_bound_and_an_oversized_ones_head_are_skipped() {
        let dir = tempfile::tempdir().unwrap();
        // Four segments of 100 messages, then one far too long.
        for id in 0..4 {
            segment(dir.path(), id, id * 100..id * 100 + 100);
        }
        let big = segment(dir.path(), 4, 1000..60_000);
        let max = big / 4;
        let found = scan(dir.path(), &[0, 1, 2, 3, 4], (0, 0), max, max / 8).unwrap();
        // Only the newest is kept, cut to a segment's length.
        assert_eq!(found.segments.len(), 1, "{found:?}");
        let s = &found.segments[0];
        assert!(s.len <= max / 8 + 12 && s.len > max / 8 - 100, "{s:?}");
        assert_eq!(
            s.len,
            fs::metadata(super::super::segment_path(dir.path(), 4))
                .unwrap()
                .len()
        );
        assert!(found.skipped > big - max / 8, "{}", found.skipped);
        assert_eq!(found.news.len(), 2, "{:?}", found.news);
        // What is kept is the newest, whole, up to the last message.
        let bytes = fs::read(super::super::segment_path(dir.path(), 4)).unwrap();
        let d = frame::decode(&bytes, 0).unwrap();
        assert_eq!(d.messages.len() as u64, s.messages);
        assert_eq!(d.messages.last().unwrap().message, msg(59_999));
        assert_eq!(d.torn, 0);
    }

    #[test]
    fn an_oversized_segment_without_a_frame_is_removed() {
        let dir = tempfile::tempdir().unwrap();
        let mut bytes = frame::header();
        bytes.resize(10 << 20, 0);
        fs::write(super::super::segment_path(dir.path(), 0), &bytes).unwrap();
        let found = scan(dir.path(), &[0], (0, 0), 16 << 20, 2 << 20).unwrap();
        assert!(found.segments.is_empty(), "{found:?}");
        assert_eq!(found.skipped, (10 << 20) - HEADER_LEN as u64);
        assert!(!super::super::segment_path(dir.path(), 0).exists());
    }

    #[test]
    fn counting_by_heads_agrees_with_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let len = segment(dir.path(), 0, 0..500);
        let path = super::super::segment_path(dir.path(), 0);
        let bytes = fs::read(&path).unwrap();
        let d = frame::decode(&bytes, 0).unwrap();
        let from = d.messages[99].end as u64;
        let w = walk(&path, len, from).unwrap();
        assert_eq!(w.messages, 400);
        assert_eq!(w.good_len, len);
        // A torn, garbled last frame is cut off.
        let mut garbled = bytes.clone();
        let last = garbled.len() - 3;
        garbled[last] ^= 0x55;
        fs::write(&path, &garbled).unwrap();
        let w = walk(&path, len, 0).unwrap();
        assert_eq!(w.messages, 499);
        assert_eq!(w.good_len, d.messages[498].end as u64);
    }
}
