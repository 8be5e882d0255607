//! Reading a framed file from its end, within bounds: the newest records
//! first, a chunk at a time ([`super::chunk`]), until the reader has what
//! it keeps (the alarms of `alarms_kept`, the safety journal back to its
//! last clean stop), the file's start, or a budget of bytes. What lies
//! before is skipped unread: counted in bytes, never held in memory, so a
//! file of any size neither stalls a start nor fills the memory.

use std::fs::File;
use std::io;
use std::os::unix::fs::FileExt;
use std::path::Path;

use super::chunk;
use super::format::{self, HEADER_LEN, Header, Kind, Unreadable};

/// Bytes read at a time.
pub const CHUNK: u64 = 256 * 1024;

/// What the reader says after each chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wanted {
    /// Older records, please.
    More,
    /// It has what it keeps: the rest is skipped.
    Enough,
}

/// How a file was read.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Read {
    /// The file's length.
    pub len: u64,
    /// Bytes before the records read, skipped unread.
    pub skipped: u64,
    /// Bytes of a torn last record left out.
    pub torn: u64,
    /// The budget ran out before the reader had what it keeps.
    pub cut: bool,
}

/// Reads the file of `kind` at `path` from its end, handing `take` the
/// records of each chunk (in file order; older chunks later) until it
/// says [`Wanted::Enough`], the file's start, or `budget` bytes read (at
/// least one chunk). `Ok(None)`: there is no file.
pub fn read_from_end<T: serde::de::DeserializeOwned>(
    path: &Path,
    kind: Kind,
    budget: u64,
    mut take: impl FnMut(Vec<T>) -> Wanted,
) -> Result<Option<Read>, Unreadable> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Unreadable::Io(e.to_string())),
    };
    let io_error = |e: io::Error| Unreadable::Io(e.to_string());
    let len = file.metadata().map_err(io_error)?.len();
    if len > budget {
        tracing::info!(
            "the {} {} is {}: reading it from its end",
            kind.what,
            path.display(),
            size(len)
        );
    }
    let mut head = vec![0u8; usize::try_from(len.min(HEADER_LEN as u64)).unwrap_or(0)];
    file.read_exact_at(&mut head, 0).map_err(io_error)?;
    let mut read = Read {
        len,
        ..Read::default()
    };
    if format::check_header(kind, &head)? == Header::Torn {
        read.torn = len;
        return Ok(Some(read));
    }
    let first = HEADER_LEN as u64;
    let mut end = len;
    let mut done = 0u64;
    while end > first {
        let start = end.saturating_sub(CHUNK).max(first);
        if done > 0 && done + (end - start) > budget {
            read.cut = true;
            break;
        }
        let mut bytes = vec![0u8; usize::try_from(end - start).unwrap_or(0)];
        file.read_exact_at(&mut bytes, start).map_err(io_error)?;
        let c = chunk::decode::<T>(&bytes, start, start == first, end == len)?;
        if end == len {
            read.torn = c.torn as u64;
        }
        done += end - start;
        end = start + c.start as u64;
        if take(c.records) == Wanted::Enough {
            break;
        }
    }
    read.skipped = end.saturating_sub(first);
    Ok(Some(read))
}

/// `bytes` in words: "812 bytes", "3.4 MB".
pub fn size(bytes: u64) -> String {
    if bytes < 1_000_000 {
        format!("{bytes} bytes")
    } else {
        format!("{:.1} MB", bytes as f64 / 1e6)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::super::format::{SAFETY_JOURNAL, encode, header};
    use super::*;
    use crate::control::journal::format::Record;

    fn stop_ended(i: u64) -> Record {
        Record::StopEnded {
            drive: format!("drive-{i:05}"),
        }
    }

    #[test]
    fn newest_first_until_enough_and_the_rest_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("j");
        let mut bytes = header();
        for i in 0..40_000 {
            bytes.extend(encode(&stop_ended(i)));
        }
        std::fs::write(&path, &bytes).unwrap();
        // Everything, chunk by chunk.
        let mut all: Vec<Vec<Record>> = Vec::new();
        let read = read_from_end(&path, SAFETY_JOURNAL, u64::MAX, |r| {
            all.push(r);
            Wanted::More
        })
        .unwrap()
        .unwrap();
        assert_eq!((read.skipped, read.torn, read.cut), (0, 0, false));
        let records: Vec<Record> = all.into_iter().rev().flatten().collect();
        assert_eq!(records, (0..40_000).map(stop_ended).collect::<Vec<_>>());
        // The newest chunk only.
        let mut newest = Vec::new();
        let read = read_from_end(&path, SAFETY_JOURNAL, u64::MAX, |r: Vec<Record>| {
            newest = r;
            Wanted::Enough
        })
        .unwrap()
        .unwrap();
        assert_eq!(newest.last(), Some(&stop_ended(39_999)));
        let first = newest.first().cloned().unwrap();
        let Record::StopEnded { drive } = first else {
            unreachable!()
        };
        let n: u64 = drive.trim_start_matches("drive-").parse().unwrap();
        assert_eq!(
            read.skipped,
            n * encode(&stop_ended(0)).len() as u64,
            "the bytes of the records before it"
        );
        // A budget: one chunk and no more.
        let read = read_from_end(&path, SAFETY_JOURNAL, CHUNK, |_: Vec<Record>| Wanted::More)
            .unwrap()
            .unwrap();
        assert!(read.cut && read.skipped > 0, "{read:?}");
        // No file: none.
        assert!(
            read_from_end(
                &dir.path().join("none"),
                SAFETY_JOURNAL,
                1,
                |_: Vec<Record>| { Wanted::More }
            )
            .unwrap()
            .is_none()
        );
    }
}
