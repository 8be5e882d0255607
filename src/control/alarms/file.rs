//! The alarm book's file, `alarms.journal` in `[safety] state_dir`: the
//! safety journal's framing ([`crate::control::journal::format`]: a
//! header, then records each with its length and CRC-32, a torn last
//! record left out), with its own magic so neither file is ever read as
//! the other.
//!
//! Each change of an alarm appends the alarm whole (`alarm`), a dropped
//! one its number (`dropped`): the last record of an id wins. When the file
//! has grown past twice its last snapshot (and [`COMPACT_AT`]) it is
//! rewritten as a snapshot of the alarms it holds (a temporary file,
//! synced, renamed over it, the directory synced). The book holds at most
//! `[safety] alarms_kept` alarms, so the file stays below twice their
//! snapshot plus one append.
//!
//! At start-up the file is read from its end
//! ([`crate::control::journal::tail`]), the newest records first, until it
//! has given `alarms_kept` alarms (the last record of each), its start, or
//! a budget of bytes a file of that many alarms never reaches: a file
//! that grew beyond what the daemon keeps (written with a larger
//! `alarms_kept`, or not by this daemon) costs no more time or memory than
//! one of the alarms kept. What lies before is skipped unread, counted
//! and logged, and the file is compacted to what was kept.

use std::collections::{BTreeMap, HashSet};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::book::Alarm;
use crate::control::journal::format::{self, Kind};
use crate::control::journal::tail::{self, Wanted};

/// The file's name in the state directory.
pub const FILE: &str = "alarms.journal";
/// Compacted once it is this long (and twice its last snapshot).
pub const COMPACT_AT: u64 = 64 * 1024;
/// Bytes read at start-up per alarm kept: an alarm's record is well under
/// 2 KiB, and a file this daemon wrote holds at most two of each (twice
/// its snapshot) plus [`COMPACT_AT`].
const READ_PER_ALARM: u64 = 4 * 1024;
/// The alarm file's magic and version.
pub const ALARM_FILE: Kind = Kind {
    magic: b"DRVGALRM",
    version: 1,
    oldest: 1,
    what: "alarm file",
};

/// One record of the file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "record", rename_all = "kebab-case")]
pub enum AlarmRecord {
    /// An alarm as it now stands.
    Alarm(Alarm),
    /// An alarm dropped to keep the book within its bound.
    Dropped {
        /// Its number.
        id: u64,
    },
}

/// The alarms a file's records come to, by id.
pub fn replay(records: impl IntoIterator<Item = AlarmRecord>) -> BTreeMap<u64, Alarm> {
    let mut out = BTreeMap::new();
    for r in records {
        match r {
            AlarmRecord::Alarm(a) => {
                out.insert(a.id, a);
            }
            AlarmRecord::Dropped { id } => {
                out.remove(&id);
            }
        }
    }
    out
}

/// Counts of the file's life, for the metrics.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FileState {
    /// Bytes of the file.
    pub bytes: u64,
    /// Appends or compactions that failed.
    pub write_errors: u64,
    /// What is wrong, in words (`None`: written and synced, or no state
    /// directory).
    pub failing: Option<String>,
    /// Bytes of older records skipped unread at start-up.
    pub skipped_bytes: u64,
}

/// The newest alarms of a file, read from its end.
struct Newest {
    alarms: BTreeMap<u64, Alarm>,
    last_id: u64,
    skipped: u64,
    news: Vec<String>,
}

/// Reads the file at `path` from its end until it gave `keep` alarms (the
/// last record of each id; a dropped one counts for nothing), its start,
/// or `keep` times [`READ_PER_ALARM`] bytes.
fn read_newest(path: &Path, keep: usize) -> Result<Newest, format::Unreadable> {
    let mut decided: HashSet<u64> = HashSet::new();
    let mut alarms = BTreeMap::new();
    let mut last_id = 0;
    let keep = keep.max(1);
    let budget = (keep as u64)
        .saturating_mul(READ_PER_ALARM)
        .saturating_add(COMPACT_AT);
    let read = tail::read_from_end(path, ALARM_FILE, budget, |records: Vec<AlarmRecord>| {
        for r in records.into_iter().rev() {
            let id = match &r {
                AlarmRecord::Alarm(a) => a.id,
                AlarmRecord::Dropped { id } => *id,
            };
            last_id = last_id.max(id);
            // Newest first: the first record of an id is its last word.
            if !decided.insert(id) {
                continue;
            }
            if let AlarmRecord::Alarm(a) = r {
                alarms.insert(id, a);
                if alarms.len() >= keep {
                    return Wanted::Enough;
                }
            }
        }
        Wanted::More
    })?;
    let mut news = Vec::new();
    let Some(read) = read else {
        return Ok(Newest {
            alarms,
            last_id,
            skipped: 0,
            news,
        });
    };
    if read.torn > 0 {
        news.push(format!(
            "the alarm file {} ended in a record cut short ({} bytes); it was left out",
            path.display(),
            read.torn
        ));
    }
    if read.skipped > 0 {
        news.push(format!(
            "the alarm file {} is {}, more than {} alarms ([safety] alarms_kept) need: it was read from its end, its newest {} alarms kept and the {} before them skipped unread; the file is compacted to what is kept",
            path.display(),
            tail::size(read.len),
            keep,
            alarms.len(),
            tail::size(read.skipped)
        ));
    }
    Ok(Newest {
        alarms,
        last_id,
        skipped: read.skipped,
        news,
    })
}

/// The open file, with a copy of what it holds (for its snapshots).
pub struct AlarmFile {
    dir: Option<PathBuf>,
    file: Option<File>,
    held: BTreeMap<u64, Alarm>,
    snapshot_len: u64,
    rewrite: bool,
    state: FileState,
}

/// What opening the file found.
pub struct OpenedFile {
    /// The file, ready for appends.
    pub file: AlarmFile,
    /// The alarms it held, oldest first.
    pub alarms: Vec<Alarm>,
    /// The highest alarm number its records read name (the book numbers
    /// on after it).
    pub last_id: u64,
    /// What happened, in words, for the log (empty: nothing worth saying).
    pub news: Vec<String>,
}

impl AlarmFile {
    /// Opens (or creates) the file in `dir`, reading back the newest
    /// `keep` alarms; `None`: alarms live in memory only.
    pub fn open(dir: Option<&Path>, keep: usize) -> OpenedFile {
        let mut file = AlarmFile {
            dir: dir.map(Path::to_path_buf),
            file: None,
            held: BTreeMap::new(),
            snapshot_len: 0,
            rewrite: true,
            state: FileState::default(),
        };
        let Some(dir) = dir else {
            return OpenedFile {
                file,
                alarms: Vec::new(),
                last_id: 0,
                news: vec![
                    "no state directory ([safety] state_dir): alarms are kept in memory only and lost at a restart".into(),
                ],
            };
        };
        let path = dir.join(FILE);
        let mut news = Vec::new();
        let mut last_id = 0;
        match read_newest(&path, keep) {
            Ok(read) => {
                news.extend(read.news);
                file.state.skipped_bytes = read.skipped;
                file.held = read.alarms;
                last_id = read.last_id;
            }
            Err(why) => {
                let aside = dir.join(format!(
                    "{FILE}.unreadable-{}",
                    format::unix_ms(std::time::SystemTime::now())
                ));
                let moved = match fs::rename(&path, &aside) {
                    Ok(()) => format!("it was set aside as {}", aside.display()),
                    Err(e) => format!("it could not be set aside ({e})"),
                };
                news.push(format!(
                    "the alarm file {} could not be read: {why}; {moved}; the alarm list starts empty",
                    path.display()
                ));
            }
        }
        if let Err(e) = file.compact() {
            file.fail(format!(
                "the alarm file {} cannot be written: {e}",
                path.display()
            ));
            news.extend(file.state.failing.clone());
        }
        OpenedFile {
            alarms: file.held.values().cloned().collect(),
            last_id,
            file,
            news,
        }
    }

    /// How it stands.
    pub fn state(&self) -> &FileState {
        &self.state
    }

    /// Appends `records` and syncs them (one sync for all). What it holds
    /// is kept in memory even when the disk fails, and written whole once
    /// the disk takes writes again.
    pub fn append(&mut self, records: &[AlarmRecord]) {
        for r in records {
            match r {
                AlarmRecord::Alarm(a) => {
                    self.held.insert(a.id, a.clone());
                }
                AlarmRecord::Dropped { id } => {
                    self.held.remove(id);
                }
            }
        }
        if self.dir.is_none() || records.is_empty() {
            return;
        }
        let result = if self.rewrite {
            self.compact()
        } else {
            self.write(records)
        };
        match result {
            Ok(()) => {
                if self.state.failing.take().is_some() {
                    tracing::info!("the alarm file is written again");
                }
                if self.state.bytes > COMPACT_AT.max(2 * self.snapshot_len)
                    && let Err(e) = self.compact()
                {
                    self.fail(format!("the alarm file could not be compacted: {e}"));
                }
            }
            Err(e) => self.fail(format!("the alarm file could not be written: {e}")),
        }
    }

    fn fail(&mut self, why: String) {
        if self.state.failing.is_none() {
            tracing::warn!("{why}; alarms are kept in memory until it can be written");
        }
        self.state.write_errors += 1;
        self.state.failing = Some(why);
        self.file = None;
        self.rewrite = true;
    }

    fn write(&mut self, records: &[AlarmRecord]) -> io::Result<()> {
        let Some(file) = self.file.as_mut() else {
            return Err(io::Error::other("the file is not open"));
        };
        let bytes: Vec<u8> = records.iter().flat_map(format::frame).collect();
        file.write_all(&bytes)?;
        file.sync_data()?;
        self.state.bytes += bytes.len() as u64;
        Ok(())
    }

    /// Rewrites the file as a snapshot of what it holds, so that it is at
    /// every instant either the old file or the new one.
    fn compact(&mut self) -> io::Result<()> {
        let Some(dir) = self.dir.clone() else {
            return Ok(());
        };
        fs::create_dir_all(&dir)?;
        let tmp = dir.join(format!("{FILE}.tmp"));
        let path = dir.join(FILE);
        let mut bytes = format::header_of(ALARM_FILE);
        for a in self.held.values() {
            bytes.extend(format::frame(&AlarmRecord::Alarm(a.clone())));
        }
        let written = (|| {
            let mut f = File::create(&tmp)?;
            f.write_all(&bytes)?;
            f.sync_all()?;
            fs::rename(&tmp, &path)?;
            File::open(&dir)?.sync_all()
        })();
        if let Err(e) = written {
            let _ = fs::remove_file(&tmp);
            return Err(e);
        }
        self.file = Some(OpenOptions::new().append(true).open(&path)?);
        self.state.bytes = bytes.len() as u64;
        self.snapshot_len = bytes.len() as u64;
        self.rewrite = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::super::book::AlarmKind;
    use super::*;

    fn alarm(id: u64, text: &str) -> Alarm {
        Alarm {
            id,
            kind: AlarmKind::Offline,
            bus: "line1".into(),
            drive: Some("conveyor".into()),
            code: 0,
            text: text.into(),
            help: "check the wiring".into(),
            raised_ms: 1_700_000_000_000,
            cleared_ms: None,
            ack: None,
            count: 1,
            last_ms: 1_700_000_000_000,
        }
    }

    #[test]
    fn alarms_are_read_back_by_the_next_process_last_record_winning() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = AlarmFile::open(Some(dir.path()), 500).file;
        f.append(&[
            AlarmRecord::Alarm(alarm(1, "first")),
            AlarmRecord::Alarm(alarm(2, "second")),
        ]);
        f.append(&[
            AlarmRecord::Alarm(alarm(1, "first, cleared")),
            AlarmRecord::Dropped { id: 2 },
        ]);
        drop(f);
        let opened = AlarmFile::open(Some(dir.path()), 500);
        assert_eq!(opened.alarms, vec![alarm(1, "first, cleared")]);
        assert!(opened.news.is_empty(), "{:?}", opened.news);
    }

    #[test]
    fn a_torn_tail_is_left_out_and_garbage_set_aside() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = AlarmFile::open(Some(dir.path()), 500).file;
        f.append(&[AlarmRecord::Alarm(alarm(1, "kept"))]);
        drop(f);
        let path = dir.path().join(FILE);
        let mut bytes = fs::read(&path).unwrap();
        let whole = bytes.len();
        bytes.extend(format::frame(&AlarmRecord::Alarm(alarm(2, "torn"))));
        bytes.truncate(whole + 20);
        fs::write(&path, &bytes).unwrap();
        let opened = AlarmFile::open(Some(dir.path()), 500);
        assert_eq!(opened.alarms, vec![alarm(1, "kept")]);
        assert!(opened.news[0].contains("cut short"), "{:?}", opened.news);
        drop(opened);
        // The safety journal is not an alarm file.
        fs::write(&path, format::header()).unwrap();
        let opened = AlarmFile::open(Some(dir.path()), 500);
        assert!(opened.alarms.is_empty());
        assert!(
            opened.news[0].contains("not a drivegate alarm file"),
            "{:?}",
            opened.news
        );
    }

    #[test]
    fn the_file_stays_bounded_by_its_snapshots() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = AlarmFile::open(Some(dir.path()), 500).file;
        // The same ten alarms rewritten 2000 times.
        for round in 0..2000u64 {
            let id = round % 10;
            f.append(&[AlarmRecord::Alarm(alarm(id, &format!("round {round}")))]);
        }
        let bytes = f.state().bytes;
        assert!(bytes <= COMPACT_AT + 1024, "{bytes}");
        assert_eq!(fs::metadata(dir.path().join(FILE)).unwrap().len(), bytes);
        assert_eq!(AlarmFile::open(Some(dir.path()), 500).alarms.len(), 10);
    }

    #[test]
    fn a_file_beyond_what_is_kept_is_read_from_its_end_and_compacted() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE);
        // 20000 alarms, each raised then cleared, and a dropped number.
        let mut bytes = format::header_of(ALARM_FILE);
        for id in 1..=20_000u64 {
            let mut a = alarm(id, "raised");
            bytes.extend(format::frame(&AlarmRecord::Alarm(a.clone())));
            a.cleared_ms = Some(a.raised_ms + 1);
            bytes.extend(format::frame(&AlarmRecord::Alarm(a)));
        }
        bytes.extend(format::frame(&AlarmRecord::Dropped { id: 20_000 }));
        fs::write(&path, &bytes).unwrap();
        let opened = AlarmFile::open(Some(dir.path()), 10);
        // The newest ten that are still there, each as last written.
        let ids: Vec<u64> = opened.alarms.iter().map(|a| a.id).collect();
        assert_eq!(ids, (19_990..20_000).collect::<Vec<_>>());
        assert!(opened.alarms.iter().all(|a| a.cleared_ms.is_some()));
        assert_eq!(opened.last_id, 20_000);
        let state = opened.file.state();
        assert!(state.skipped_bytes > bytes.len() as u64 / 2, "{state:?}");
        assert!(
            opened.news.iter().any(|n| n.contains("skipped unread")),
            "{:?}",
            opened.news
        );
        // Compacted to what was kept.
        assert!(fs::metadata(&path).unwrap().len() < 20 * 1024);
        assert_eq!(AlarmFile::open(Some(dir.path()), 10).alarms, opened.alarms);
    }

    #[test]
    fn without_a_directory_alarms_live_in_memory() {
        let mut opened = AlarmFile::open(None, 500);
        opened.file.append(&[AlarmRecord::Alarm(alarm(1, "x"))]);
        assert_eq!(opened.file.state(), &FileState::default());
        assert!(opened.news[0].contains("memory only"));
    }
}
