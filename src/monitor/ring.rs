//! The ring of the last N frames of one bus.
//!
//! The bus thread is its only writer and must never wait for a reader: each
//! slot has its own lock, and a reader holds a slot's lock only while it
//! copies that one record. So the writer can at worst find the one slot it
//! writes being copied, for the time of a ~160-byte copy, and a reader
//! that is slow, stuck or gone costs the writer nothing: it simply finds,
//! when it reads again, that the frames it had not read yet were
//! overwritten, and counts them lost.
//!
//! The slots come in chunks of [`CHUNK`], each allocated when the writer
//! first reaches it: a ring of 10,000 frames (1.6 MB) takes the memory of
//! the frames a bus has carried so far, not all of it at start (a quiet
//! bus, or a daemon restarted, never fills most of it). The writer
//! allocates during its first lap only, once every [`CHUNK`] frames; after
//! that, never.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};

use super::record::FrameRecord;

/// Slots allocated at a time.
pub const CHUNK: usize = 128;

type Chunk = Box<[Mutex<FrameRecord>]>;

/// A fixed ring of frame records with a running sequence number.
pub struct Ring {
    chunks: Box<[OnceLock<Chunk>]>,
    capacity: usize,
    /// Sequence number of the next frame written (= frames written so far).
    head: AtomicU64,
}

/// What one read brought.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct ReadReport {
    /// Frames copied.
    pub read: usize,
    /// Frames the reader had not read yet that were overwritten.
    pub lost: u64,
}

impl Ring {
    /// A ring of `capacity` frames (at least 1), its slots allocated as
    /// the writer reaches them.
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(1);
        Self {
            chunks: (0..capacity.div_ceil(CHUNK))
                .map(|_| OnceLock::new())
                .collect(),
            capacity,
            head: AtomicU64::new(0),
        }
    }

    /// Frames it holds when full.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Frames written since it started; the next frame's sequence number.
    pub fn head(&self) -> u64 {
        self.head.load(Ordering::Acquire)
    }

    /// The oldest sequence number still in the ring.
    pub fn oldest(&self) -> u64 {
        self.head().saturating_sub(self.capacity() as u64)
    }

    /// Memory the ring takes when full, in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.capacity() * std::mem::size_of::<Mutex<FrameRecord>>()
    }

    /// Memory the ring takes now (its chunks allocated so far), in bytes.
    pub fn allocated_bytes(&self) -> usize {
        let slots: usize = self
            .chunks
            .iter()
            .filter_map(OnceLock::get)
            .map(|c| c.len())
            .sum();
        slots * std::mem::size_of::<Mutex<FrameRecord>>()
    }

    /// The slot of `seq`, its chunk allocated first if it was not yet
    /// (only the writer reaches a slot whose chunk is not there: a reader
    /// reads below the head).
    fn slot(&self, seq: u64) -> std::sync::MutexGuard<'_, FrameRecord> {
        let index = (seq % self.capacity as u64) as usize;
        let (chunk, at) = (index / CHUNK, index % CHUNK);
        let len = CHUNK.min(self.capacity - chunk * CHUNK);
        let slots = self.chunks[chunk].get_or_init(|| {
            (0..len)
                .map(|_| Mutex::new(FrameRecord::default()))
                .collect()
        });
        // A panic while a slot was held cannot leave a record half valid in
        // a way that matters (it is display data): go on with it.
        slots[at].lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Writes the next frame: `fill` sets its fields in place (the slot's
    /// previous content is overwritten; `seq` is set here). Only the bus
    /// thread writes: the sequence is not reserved atomically.
    pub fn push(&self, fill: impl FnOnce(&mut FrameRecord)) -> u64 {
        let seq = self.head.load(Ordering::Relaxed);
        {
            let mut slot = self.slot(seq);
            fill(&mut slot);
            slot.seq = seq;
        }
        self.head.store(seq + 1, Ordering::Release);
        seq
    }

    /// Copies up to `max` frames from `*cursor` on into `out`, and moves the
    /// cursor past them. Frames overwritten before they were read are
    /// skipped and counted as lost.
    pub fn read(&self, cursor: &mut u64, max: usize, out: &mut Vec<FrameRecord>) -> ReadReport {
        let head = self.head();
        let mut report = ReadReport::default();
        let oldest = head.saturating_sub(self.capacity() as u64);
        if *cursor < oldest {
            report.lost += oldest - *cursor;
            *cursor = oldest;
        }
        while *cursor < head && report.read < max {
            let seq = *cursor;
            *cursor += 1;
            let slot = self.slot(seq);
            if slot.seq == seq {
                out.push(slot.clone());
                report.read += 1;
            } else {
                // The writer lapped us while we read.
                report.lost += 1;
            }
        }
        report
    }

    /// The last `n` frames (fewer if the ring holds fewer).
    pub fn last(&self, n: usize) -> Vec<FrameRecord> {
        let mut cursor = self.head().saturating_sub(n as u64);
        let mut out = Vec::with_capacity(n.min(self.capacity()));
        self.read(&mut cursor, n, &mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn push_unit(ring: &Ring, unit: u8) {
        ring.push(|r| r.unit = unit);
    }

    #[test]
    fn reads_in_order_and_counts_what_was_overwritten() {
        let ring = Ring::new(4);
        let mut cursor = 0;
        let mut out = vec![];
        for u in 0..3 {
            push_unit(&ring, u);
        }
        assert_eq!(
            ring.read(&mut cursor, 10, &mut out),
            ReadReport { read: 3, lost: 0 }
        );
        assert_eq!(out.iter().map(|r| r.unit).collect::<Vec<_>>(), [0, 1, 2]);
        // A reader that falls more than the ring behind loses the oldest.
        for u in 3..10 {
            push_unit(&ring, u);
        }
        out.clear();
        assert_eq!(
            ring.read(&mut cursor, 10, &mut out),
            ReadReport { read: 4, lost: 3 }
        );
        assert_eq!(out.iter().map(|r| r.seq).collect::<Vec<_>>(), [6, 7, 8, 9]);
        assert_eq!(cursor, 10);
        // Nothing new: nothing read, nothing lost.
        out.clear();
        assert_eq!(ring.read(&mut cursor, 10, &mut out), ReadReport::default());
    }

    #[test]
    fn its_memory_is_taken_as_it_fills() {
        let ring = Ring::new(CHUNK * 3 + 5);
        assert_eq!(ring.allocated_bytes(), 0);
        let slot = std::mem::size_of::<Mutex<FrameRecord>>();
        push_unit(&ring, 1);
        assert_eq!(ring.allocated_bytes(), CHUNK * slot);
        for u in 0..CHUNK * 3 {
            push_unit(&ring, u as u8);
        }
        // The last chunk, reached by the last frame, holds the five left
        // over.
        assert_eq!(ring.allocated_bytes(), ring.memory_bytes());
        assert_eq!(ring.memory_bytes(), (CHUNK * 3 + 5) * slot);
        for u in 0..10 {
            push_unit(&ring, u);
        }
        // The writer wrapped over the short chunk; reading never allocates.
        let last = ring.last(CHUNK * 4);
        assert_eq!(last.len(), CHUNK * 3 + 5);
        assert_eq!(last.last().map(|r| r.unit), Some(9));
        assert_eq!(last.first().map(|r| r.seq), Some(6));
    }

    #[test]
    fn reads_in_batches() {
        let ring = Ring::new(8);
        for u in 0..6 {
            push_unit(&ring, u);
        }
        let (mut cursor, mut out) = (0, vec![]);
        assert_eq!(ring.read(&mut cursor, 4, &mut out).read, 4);
        assert_eq!(ring.read(&mut cursor, 4, &mut out).read, 2);
        assert_eq!(out.len(), 6);
        assert_eq!(
            ring.last(3).iter().map(|r| r.unit).collect::<Vec<_>>(),
            [3, 4, 5]
        );
        assert_eq!(ring.oldest(), 0);
    }

    #[test]
    fn a_reader_on_another_thread_never_sees_a_torn_sequence() {
        let ring = std::sync::Arc::new(Ring::new(16));
        let writer = {
            let ring = ring.clone();
            std::thread::spawn(move || {
                for i in 0..20_000u32 {
                    ring.push(|r| {
                        r.unit = (i % 251) as u8;
                        r.set_bytes(&i.to_le_bytes());
                    });
                }
            })
        };
        let (mut cursor, mut seen, mut lost) = (0u64, 0u64, 0u64);
        let mut out = vec![];
        while cursor < 20_000 {
            out.clear();
            let report = ring.read(&mut cursor, 8, &mut out);
            for r in &out {
                // Each record is whole: its bytes are its own sequence number.
                let i = u32::from_le_bytes(r.bytes().try_into().unwrap());
                assert_eq!(u64::from(i), r.seq);
                assert_eq!(r.unit, (i % 251) as u8);
            }
            seen += report.read as u64;
            lost += report.lost;
        }
        writer.join().unwrap();
        assert_eq!(seen + lost, 20_000);
    }
}
