//! Store and forward: the outgoing messages that could not be sent (the
//! broker unreachable, or the primary host offline), kept on disk in
//! `[safety] state_dir` until they can be, oldest first.
//!
//! The store is a directory of segments (`seg-<n>.mqs`, [`frame`]'s
//! format), oldest first, and a cursor file saying how far the oldest has
//! been replayed. Why segments: the bound (`store_max_mb`) drops the
//! oldest data first, and dropping a whole file is one `unlink`, where
//! cutting the head off one file would mean rewriting it. A segment is an
//! eighth of the bound, so a drop loses an eighth at most, and each drop
//! is counted (messages never sent).
//!
//! Why it survives a crash: every message is written to its segment (the
//! kernel holds it from then on, whatever becomes of the process), the
//! file is synced when a segment is closed and on [`Store::sync`], and a
//! frame torn by a power cut is recognised by its length and CRC and
//! ignored, not read as data nor taken as a reason to refuse the rest.
//! The cursor is replaced atomically (written, renamed), after the
//! messages it passes were handed to the MQTT client: a crash in between
//! sends them again (at least once), never loses them.
//!
//! What a restart finds is read back within `store_max_mb` and without
//! reading the messages' bodies (`open`): a store left larger, or a
//! segment longer than this daemon writes, costs a start no more time or
//! memory than one at its bound; what lies beyond is skipped, counted
//! ([`Figures::skipped_bytes`]) and logged.

pub mod frame;
mod open;
pub mod outbox;
pub mod pacing;

use std::collections::VecDeque;
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use crate::control::journal::format::crc32;
pub use frame::StoredMessage;
use frame::{Framed, HEADER_LEN};

/// The store's directory in the state directory.
pub const DIR: &str = "mqtt-store";
/// The cursor's file name in it.
const CURSOR: &str = "cursor";
/// The smallest segment: a bound of a few kB still keeps whole messages.
const MIN_SEGMENT: u64 = 4096;

/// The store's figures, for the metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Figures {
    /// Bytes of messages waiting (frames, as on disk).
    pub bytes: u64,
    /// Messages waiting.
    pub messages: u64,
    /// Messages dropped unsent: the oldest, to keep the bound, or one
    /// too large for a segment.
    pub dropped: u64,
    /// Frames found damaged on disk and skipped.
    pub damaged: u64,
    /// Bytes skipped unread when the store was opened (beyond its bound).
    pub skipped_bytes: u64,
}

/// Why the store cannot be used, in words.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The directory or a file could not be created, read or written.
    #[error("the MQTT store in {dir} cannot be used: {source}")]
    Io {
        /// The store's directory.
        dir: PathBuf,
        /// What went wrong.
        source: io::Error,
    },
}

/// One segment file.
#[derive(Debug, Clone)]
struct Segment {
    id: u64,
    /// The file's length (where the next frame goes).
    len: u64,
    /// Messages in it not yet replayed.
    messages: u64,
    /// Their bytes.
    bytes: u64,
}

/// The disk-backed FIFO. Not shared: one task (the face's) owns it.
#[derive(Debug)]
pub struct Store {
    dir: PathBuf,
    max_bytes: u64,
    segment_bytes: u64,
    /// Oldest first; the last is the one written.
    segments: VecDeque<Segment>,
    writer: Option<File>,
    /// The oldest segment's messages from the cursor on, read when asked
    /// for (`None`: not read yet).
    head: Option<VecDeque<Framed>>,
    /// Where the replay stands in the oldest segment.
    cursor: u64,
    dropped: u64,
    damaged: u64,
    skipped_bytes: u64,
}

/// The file of segment `id` in `dir`.
fn segment_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("seg-{id:016}.mqs"))
}

impl Store {
    /// Opens (or creates) the store in `dir`, bounded to `max_bytes` on
    /// disk. What an earlier process left is read back within the bound:
    /// its segments, its cursor; torn tails are cut off, what lies beyond
    /// the bound skipped and counted, damaged frames counted as they are
    /// replayed.
    pub fn open(dir: &Path, max_bytes: u64) -> Result<Store, StoreError> {
        let io = |source| StoreError::Io {
            dir: dir.to_path_buf(),
            source,
        };
        fs::create_dir_all(dir).map_err(io)?;
        let mut ids = Vec::new();
        for entry in fs::read_dir(dir).map_err(io)? {
            let name = entry.map_err(io)?.file_name();
            if let Some(id) = name
                .to_str()
                .and_then(|n| n.strip_prefix("seg-"))
                .and_then(|n| n.strip_suffix(".mqs"))
                .and_then(|n| n.parse::<u64>().ok())
            {
                ids.push(id);
            }
        }
        ids.sort_unstable();
        let max_bytes = max_bytes.max(MIN_SEGMENT);
        let mut store = Store {
            dir: dir.to_path_buf(),
            max_bytes,
            segment_bytes: (max_bytes / 8).max(MIN_SEGMENT),
            segments: VecDeque::new(),
            writer: None,
            head: None,
            cursor: HEADER_LEN as u64,
            dropped: 0,
            damaged: 0,
            skipped_bytes: 0,
        };
        let cursor = store.read_cursor().unwrap_or((0, HEADER_LEN as u64));
        let found = open::scan(dir, &ids, cursor, max_bytes, store.segment_bytes).map_err(io)?;
        for news in &found.news {
            tracing::warn!("{news}");
        }
        store.segments = found.segments;
        store.cursor = found.cursor;
        store.skipped_bytes = found.skipped;
        if let Some(last) = store.segments.back() {
            let f = OpenOptions::new()
                .append(true)
                .open(store.segment_path(last.id))
                .map_err(io)?;
            store.writer = Some(f);
        }
        store.drop_empty_head().map_err(io)?;
        Ok(store)
    }

    /// The figures now.
    pub fn figures(&self) -> Figures {
        Figures {
            bytes: self.segments.iter().map(|s| s.bytes).sum(),
            messages: self.segments.iter().map(|s| s.messages).sum(),
            dropped: self.dropped,
            damaged: self.damaged,
            skipped_bytes: self.skipped_bytes,
        }
    }

    /// Nothing waits.
    pub fn is_empty(&self) -> bool {
        self.segments.iter().all(|s| s.messages == 0)
    }

    /// Appends a message; the oldest are dropped (and counted) while the
    /// store is over its bound. A message too large to store is counted
    /// as dropped.
    pub fn push(&mut self, message: &StoredMessage) -> Result<(), StoreError> {
        let Ok(bytes) = frame::encode(message) else {
            self.dropped += 1;
            return Ok(());
        };
        let n = bytes.len() as u64;
        let roll = match self.segments.back() {
            None => true,
            Some(s) => s.len > HEADER_LEN as u64 && s.len + n > self.segment_bytes,
        };
        if roll {
            self.roll().map_err(|e| self.io(e))?;
        }
        let Some(writer) = self.writer.as_mut() else {
            return Err(self.io(io::Error::other("no segment open")));
        };
        if let Err(e) = writer.write_all(&bytes) {
            return Err(self.io(e));
        }
        let single = self.segments.len() == 1;
        let Some(last) = self.segments.back_mut() else {
            return Err(self.io(io::Error::other("no segment open")));
        };
        last.len += n;
        last.messages += 1;
        last.bytes += n;
        let end = last.len as usize;
        if single {
            // The oldest segment is the one written: its messages read so
            // far grow with it.
            if let Some(head) = self.head.as_mut() {
                head.push_back(Framed {
                    message: message.clone(),
                    end,
                    len: n as usize,
                });
            }
        }
        while self.segments.len() > 1 && self.disk_bytes() > self.max_bytes {
            self.drop_oldest().map_err(|e| self.io(e))?;
        }
        Ok(())
    }

    /// Up to `max` of the oldest messages waiting, in order, left in the
    /// store until [`Store::pop`] says they were sent. A batch ends at a
    /// segment's end, so it may be shorter; an empty one means nothing
    /// waits.
    pub fn peek(&mut self, max: usize) -> Result<Vec<StoredMessage>, StoreError> {
        self.load_head().map_err(|e| self.io(e))?;
        Ok(self
            .head
            .iter()
            .flatten()
            .take(max)
            .map(|f| f.message.clone())
            .collect())
    }

    /// The `n` oldest messages were sent: they leave the store, and the
    /// cursor on disk moves past them.
    pub fn pop(&mut self, n: usize) -> Result<(), StoreError> {
        let mut left = n;
        while left > 0 {
            self.load_head().map_err(|e| self.io(e))?;
            let Some(head) = self.head.as_mut() else {
                break;
            };
            let take = left.min(head.len());
            if take == 0 {
                break;
            }
            let mut bytes = 0;
            for f in head.drain(..take) {
                self.cursor = f.end as u64;
                bytes += f.len as u64;
            }
            left -= take;
            if let Some(front) = self.segments.front_mut() {
                front.messages = front.messages.saturating_sub(take as u64);
                front.bytes = front.bytes.saturating_sub(bytes);
            }
            self.drop_empty_head().map_err(|e| self.io(e))?;
        }
        self.write_cursor().map_err(|e| self.io(e))
    }

    /// Syncs the segment being written to the disk.
    pub fn sync(&mut self) -> Result<(), StoreError> {
        if let Some(w) = self.writer.as_ref() {
            w.sync_data().map_err(|e| self.io(e))?;
        }
        Ok(())
    }

    fn io(&self, source: io::Error) -> StoreError {
        StoreError::Io {
            dir: self.dir.clone(),
            source,
        }
    }

    fn segment_path(&self, id: u64) -> PathBuf {
        segment_path(&self.dir, id)
    }

    fn disk_bytes(&self) -> u64 {
        self.segments.iter().map(|s| s.len).sum()
    }

    /// Closes the segment being written (synced) and starts the next.
    fn roll(&mut self) -> io::Result<()> {
        if let Some(w) = self.writer.take() {
            w.sync_data()?;
        }
        let id = self.segments.back().map_or(0, |s| s.id + 1);
        let path = self.segment_path(id);
        let mut f = OpenOptions::new()
            .create(true)
            .truncate(true)
            .write(true)
            .open(&path)?;
        f.write_all(&frame::header())?;
        self.segments.push_back(Segment {
            id,
            len: HEADER_LEN as u64,
            messages: 0,
            bytes: 0,
        });
        self.writer = Some(f);
        Ok(())
    }

    /// Drops the oldest segment with what it still held.
    fn drop_oldest(&mut self) -> io::Result<()> {
        if let Some(s) = self.segments.pop_front() {
            self.dropped += s.messages;
            fs::remove_file(self.segment_path(s.id))?;
        }
        self.head = None;
        self.cursor = HEADER_LEN as u64;
        self.write_cursor()
    }

    /// Removes the oldest segment once it is replayed and another follows
    /// it; an empty store removes its last segment too, so an idle store
    /// is an empty directory.
    fn drop_empty_head(&mut self) -> io::Result<()> {
        while let Some(front) = self.segments.front() {
            if front.messages > 0 {
                break;
            }
            let id = front.id;
            if self.segments.len() == 1 {
                self.writer = None;
            }
            self.segments.pop_front();
            fs::remove_file(self.segment_path(id))?;
            self.head = None;
            self.cursor = HEADER_LEN as u64;
        }
        Ok(())
    }

    /// Reads the oldest segment's messages from the cursor on, when none
    /// are left in memory. Its counts become what it really holds (a frame
    /// damaged on disk is skipped, and counted, here); one that holds
    /// nothing more is removed and the next one read.
    fn load_head(&mut self) -> io::Result<()> {
        loop {
            if self.head.as_ref().is_some_and(|h| !h.is_empty()) {
                return Ok(());
            }
            let Some(front) = self.segments.front() else {
                self.head = Some(VecDeque::new());
                return Ok(());
            };
            let bytes = fs::read(self.segment_path(front.id))?;
            let d = frame::decode(&bytes, self.cursor as usize)
                .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))?;
            self.damaged += d.damaged;
            if let Some(front) = self.segments.front_mut() {
                front.messages = d.messages.len() as u64;
                front.bytes = d.messages.iter().map(|m| m.len as u64).sum();
            }
            self.head = Some(d.messages.into());
            if self.head.as_ref().is_some_and(|h| !h.is_empty()) {
                return Ok(());
            }
            self.drop_empty_head()?;
        }
    }

    fn read_cursor(&self) -> Option<(u64, u64)> {
        let b = fs::read(self.dir.join(CURSOR)).ok()?;
        let b: [u8; 20] = b.try_into().ok()?;
        let crc = u32::from_le_bytes(b[16..20].try_into().ok()?);
        (crc32(&b[..16]) == crc).then(|| {
            (
                u64::from_le_bytes(b[..8].try_into().unwrap_or_default()),
                u64::from_le_bytes(b[8..16].try_into().unwrap_or_default()),
            )
        })
    }

    /// The cursor as (segment, offset) + CRC, replaced atomically.
    fn write_cursor(&self) -> io::Result<()> {
        let id = self.segments.front().map_or(0, |s| s.id);
        let mut b = Vec::with_capacity(20);
        b.extend_from_slice(&id.to_le_bytes());
        b.extend_from_slice(&self.cursor.to_le_bytes());
        b.extend_from_slice(&crc32(&b).to_le_bytes());
        let tmp = self.dir.join(format!("{CURSOR}.tmp"));
        fs::write(&tmp, &b)?;
        fs::rename(&tmp, self.dir.join(CURSOR))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn msg(i: u64) -> StoredMessage {
        StoredMessage {
            topic: format!("spBv1.0/plant/DDATA/gw1/drive{}", i % 8),
            payload: vec![(i % 251) as u8; 40],
            at_ms: 1_700_000_000_000 + i,
        }
    }

    fn drain(store: &mut Store) -> Vec<StoredMessage> {
        let mut out = Vec::new();
        loop {
            let batch = store.peek(7).unwrap();
            if batch.is_empty() {
                return out;
            }
            store.pop(batch.len()).unwrap();
            out.extend(batch);
        }
    }

    #[test]
    fn messages_come_out_in_the_order_they_went_in() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path(), 1 << 20).unwrap();
        for i in 0..500 {
            s.push(&msg(i)).unwrap();
        }
        let f = s.figures();
        assert_eq!((f.messages, f.dropped), (500, 0));
        assert!(f.bytes > 500 * 40, "{f:?}");
        let out = drain(&mut s);
        assert_eq!(out, (0..500).map(msg).collect::<Vec<_>>());
        assert_eq!(s.figures(), Figures::default());
        // Replayed: nothing left on disk but the cursor.
        let left: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(left, [CURSOR]);
    }

    #[test]
    fn pushing_while_replaying_keeps_the_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path(), 1 << 20).unwrap();
        let mut out = Vec::new();
        for i in 0..100 {
            s.push(&msg(i)).unwrap();
            if i % 3 == 0 {
                let b = s.peek(2).unwrap();
                s.pop(b.len()).unwrap();
                out.extend(b);
            }
        }
        out.extend(drain(&mut s));
        assert_eq!(out, (0..100).map(msg).collect::<Vec<_>>());
    }

    #[test]
    fn the_bound_drops_the_oldest_first_and_counts_them() {
        let dir = tempfile::tempdir().unwrap();
        let max = 64 * 1024;
        let mut s = Store::open(dir.path(), max).unwrap();
        let n = 5000;
        for i in 0..n {
            s.push(&msg(i)).unwrap();
            let on_disk: u64 = fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().metadata().unwrap().len())
                .sum();
            assert!(on_disk <= max, "{on_disk} bytes on disk after {i}");
        }
        let f = s.figures();
        assert!(f.dropped > 0);
        assert_eq!(f.dropped + f.messages, n, "{f:?}");
        // What is left is the newest, without a gap.
        let out = drain(&mut s);
        let first = n - out.len() as u64;
        assert_eq!(first, f.dropped);
        assert_eq!(out, (first..n).map(msg).collect::<Vec<_>>());
        // Most of the bound is used: a drop loses one segment at most.
        assert!(
            out.len() as u64 * 98 > max * 7 / 8 - 8 * 1024,
            "{}",
            out.len()
        );
    }

    #[test]
    fn a_restart_finds_what_was_not_sent() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut s = Store::open(dir.path(), 64 * 1024).unwrap();
            for i in 0..600 {
                s.push(&msg(i)).unwrap();
            }
            // Segments of 8 kB: this crosses some.
            let mut sent = 0;
            while sent < 250 {
                let batch = s.peek(250 - sent).unwrap();
                assert!(!batch.is_empty());
                s.pop(batch.len()).unwrap();
                sent += batch.len();
            }
            // Peeked but not popped: not sent, still owed.
            assert_eq!(s.peek(10).unwrap().len(), 10);
        }
        let mut s = Store::open(dir.path(), 64 * 1024).unwrap();
        let f = s.figures();
        let out = drain(&mut s);
        assert_eq!(out.len() as u64, f.messages);
        // What was sent is not sent again, and nothing else is missing.
        assert_eq!(f.dropped, 0);
        let first = 600 - out.len() as u64;
        assert_eq!(first, 250);
        assert_eq!(out, (first..600).map(msg).collect::<Vec<_>>());
        // And appends after a restart go after what was there.
        s.push(&msg(1000)).unwrap();
        assert_eq!(drain(&mut s), [msg(1000)]);
    }

    #[test]
    fn a_torn_tail_is_cut_off_and_the_rest_kept() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut s = Store::open(dir.path(), 1 << 20).unwrap();
            for i in 0..10 {
                s.push(&msg(i)).unwrap();
            }
        }
        let seg = dir.path().join("seg-0000000000000000.mqs");
        let len = fs::metadata(&seg).unwrap().len();
        // The last frame half written, as a power cut leaves it.
        let f = OpenOptions::new().write(true).open(&seg).unwrap();
        f.set_len(len - 20).unwrap();
        drop(f);
        let mut s = Store::open(dir.path(), 1 << 20).unwrap();
        assert_eq!(s.figures().messages, 9);
        s.push(&msg(10)).unwrap();
        let out = drain(&mut s);
        let mut want: Vec<_> = (0..9).map(msg).collect();
        want.push(msg(10));
        assert_eq!(out, want);
    }

    #[test]
    fn garbage_in_the_directory_is_set_aside_not_fatal() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(
            dir.path().join("seg-0000000000000007.mqs"),
            b"not a segment at all",
        )
        .unwrap();
        fs::write(dir.path().join(CURSOR), b"junk").unwrap();
        let mut s = Store::open(dir.path(), 1 << 20).unwrap();
        assert!(s.is_empty());
        s.push(&msg(1)).unwrap();
        assert_eq!(drain(&mut s), [msg(1)]);
        assert!(dir.path().join("seg-0000000000000007.unreadable").exists());
    }

    #[test]
    fn a_message_too_large_is_counted_as_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path(), 1 << 20).unwrap();
        let mut big = msg(0);
        big.payload = vec![0; frame::MAX_BODY];
        s.push(&big).unwrap();
        assert_eq!(s.figures().dropped, 1);
        assert!(s.is_empty());
    }
}
