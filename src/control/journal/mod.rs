//! The safety journal: what a restart must know of the promises drivegate
//! made about the motors (leases, stops still owed, brakes), kept in
//! `[safety] state_dir` so that none is forgotten when the process dies
//! (a `kill -9`, an OOM kill, a watchdog restart, a power cut).
//!
//! Records ([`format`]) are appended and synced to the disk before the
//! write that needs them goes to the bus; the file is compacted (a snapshot
//! written to a temporary file, synced, renamed over it, the directory
//! synced) when it grows. At start-up [`replay`] decides, as a pure
//! function, what is owed. A journal that cannot be read is set aside
//! (renamed) and never keeps the daemon from starting; a disk that cannot
//! be written leaves the leases working in memory, with a warning on each
//! write the journal misses.
//!
//! The journal is read from its end ([`tail`]) back to its last clean stop
//! (nothing before one is owed), its start, or a budget of bytes: a
//! journal this daemon wrote is compacted at 64 KiB, or twice its
//! snapshot (a few hundred bytes per drive), so one longer than
//! [`read_budget`] was not; its older records are skipped, counted and
//! logged, and what they promised is taken as unknown
//! ([`replay::Recovered::Tail`]).

pub mod chunk;
pub mod format;
pub mod replay;
pub mod tail;

use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use format::{Record, Unreadable};
use replay::{JournalState, Recovered};
use tail::Wanted;

/// The journal's file name in the state directory.
pub const FILE: &str = "safety.journal";
/// Compacted once it is this long (and twice its last snapshot).
pub const COMPACT_AT: u64 = 64 * 1024;
/// At most this much of the journal of a plant of `drives` drives is read
/// at start-up, from its end: [`COMPACT_AT`], and twice a snapshot's
/// three records of each drive (each well under 700 bytes).
pub fn read_budget(drives: usize) -> u64 {
    COMPACT_AT + (drives as u64).saturating_mul(4 * 1024)
}

/// The state directory of `drivegate serve` without a configuration:
/// `$XDG_STATE_HOME/drivegate`, else `~/.local/state/drivegate`, else
/// `./drivegate-state`.
pub fn default_dir() -> PathBuf {
    if let Some(xdg) = std::env::var_os("XDG_STATE_HOME").filter(|x| !x.is_empty()) {
        return PathBuf::from(xdg).join("drivegate");
    }
    match std::env::var_os("HOME").filter(|h| !h.is_empty()) {
        Some(home) => PathBuf::from(home).join(".local/state/drivegate"),
        None => PathBuf::from("drivegate-state"),
    }
}

/// Checks that the journal can be kept in `dir`: created if missing, a
/// file written, synced and removed. The error says what to fix.
pub fn check_writable(dir: &Path) -> Result<(), String> {
    let probe = dir.join(format!("{FILE}.check"));
    let result = fs::create_dir_all(dir).and_then(|()| {
        let mut f = File::create(&probe)?;
        f.write_all(b"drivegate")?;
        f.sync_all()?;
        fs::remove_file(&probe)
    });
    result.map_err(|e| {
        format!(
            "[safety] state_dir {}: the safety journal cannot be written there: {e}; leases would not be kept across a restart (make it a writable directory, or with systemd set StateDirectory=drivegate)",
            dir.display()
        )
    })
}

/// How the journal stands, for the log, `/readyz` and the metrics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Health {
    /// Written and synced.
    Ok,
    /// There is no state directory: nothing survives a restart.
    Off(String),
    /// It cannot be written: leases work in memory only (why, in words).
    Failing(String),
}

/// Counts of the journal's life, for the metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counts {
    /// Records appended.
    pub records: u64,
    /// Appends that failed.
    pub write_errors: u64,
    /// Compactions done.
    pub compactions: u64,
    /// Journals found unreadable at start-up (set aside when they could be).
    pub unreadable: u64,
    /// Bytes of the file.
    pub bytes: u64,
    /// Bytes of older records skipped unread at start-up.
    pub skipped_bytes: u64,
}

/// The open journal.
pub struct Journal {
    dir: Option<PathBuf>,
    file: Option<File>,
    state: JournalState,
    /// The file must be rewritten from `state` before the next append (an
    /// append failed half way, or it was never created).
    rewrite: bool,
    health: Health,
    counts: Counts,
    /// Bytes of the last snapshot.
    snapshot_len: u64,
}

/// What opening the journal found.
pub struct Opened {
    /// The journal, ready for appends.
    pub journal: Journal,
    /// What it held.
    pub recovered: Recovered,
    /// What happened, in words, for the log and `/readyz` (empty: nothing
    /// worth saying).
    pub news: Vec<String>,
}

/// What reading the journal at start-up found.
struct ReadBack {
    /// The state its records come to.
    state: JournalState,
    /// Everything owed is known: it was read back to its start or to its
    /// last clean stop.
    whole: bool,
    /// Bytes of older records skipped.
    skipped: u64,
    /// What is worth saying, in words.
    news: Vec<String>,
}

/// Reads the journal at `path` from its end back to its last clean stop,
/// its start, or `budget` bytes.
fn read(path: &Path, budget: u64) -> Result<ReadBack, Unreadable> {
    let mut newest_first: Vec<Record> = Vec::new();
    let mut clean = false;
    let read = tail::read_from_end(path, format::SAFETY_JOURNAL, budget, |records| {
        for r in records.into_iter().rev() {
            if matches!(r, Record::Shutdown) {
                clean = true;
                return Wanted::Enough;
            }
            newest_first.push(r);
        }
        Wanted::More
    })?;
    let Some(read) = read else {
        return Ok(ReadBack {
            state: JournalState::default(),
            whole: true,
            skipped: 0,
            news: Vec::new(),
        });
    };
    newest_first.reverse();
    let mut news = Vec::new();
    if read.torn > 0 {
        news.push(format!(
            "the safety journal {} ended in a record cut short ({} bytes, a write the power cut or the crash interrupted); it was left out",
            path.display(),
            read.torn
        ));
    }
    let whole = clean || read.skipped == 0;
    if read.skipped > 0 {
        news.push(if whole {
            format!(
                "the safety journal {} is {}: it was read from its end back to its last clean stop, and the {} before it were skipped (nothing before a clean stop is owed)",
                path.display(),
                tail::size(read.len),
                tail::size(read.skipped)
            )
        } else {
            format!(
                "the safety journal {} is {}, more than a journal drivegate keeps for this plant (it is compacted at 64 KiB, or twice what it holds): its last {} were read and the {} before them skipped. What those promised is unknown: [safety] on_unknown_state is applied to every drive found moving that the records read say nothing about",
                path.display(),
                tail::size(read.len),
                tail::size(read.len - read.skipped),
                tail::size(read.skipped)
            )
        });
    }
    Ok(ReadBack {
        state: JournalState::of(&newest_first),
        whole,
        skipped: read.skipped,
        news,
    })
}

impl Journal {
    /// Opens (or creates) the journal in `dir` of a plant of `drives`
    /// drives; `None`: there is none.
    pub fn open(dir: Option<&Path>, drives: usize) -> Opened {
        let Some(dir) = dir else {
            let why = "no state directory ([safety] state_dir, or systemd's $STATE_DIRECTORY): leases and stops owed are not kept across a restart".to_string();
            return Opened {
                journal: Journal::new(None, Health::Off(why.clone())),
                recovered: Recovered::Read(JournalState::default()),
                news: vec![why],
            };
        };
        let path = dir.join(FILE);
        let mut news = Vec::new();
        let mut journal = Journal::new(Some(dir.to_path_buf()), Health::Ok);
        let recovered = match read(&path, read_budget(drives)) {
            Ok(read) => {
                news.extend(read.news);
                journal.counts.skipped_bytes = read.skipped;
                journal.state = read.state;
                if read.whole {
                    Recovered::Read(journal.state.clone())
                } else {
                    Recovered::Tail(journal.state.clone())
                }
            }
            Err(why) => {
                journal.counts.unreadable += 1;
                let aside = dir.join(format!(
                    "{FILE}.unreadable-{}",
                    format::unix_ms(SystemTime::now())
                ));
                let moved = match fs::rename(&path, &aside) {
                    Ok(()) => format!("it was set aside as {}", aside.display()),
                    Err(e) => format!("it could not be set aside ({e})"),
                };
                news.push(format!(
                    "the safety journal {} could not be read: {why}; {moved}. What the last process promised about the motors is unknown: [safety] on_unknown_state is applied to every drive found moving",
                    path.display()
                ));
                Recovered::Unreadable
            }
        };
        // Start from a clean snapshot: no torn tail, nothing ended.
        journal.rewrite = true;
        if let Err(e) = journal.compact() {
            journal.fail(format!(
                "the safety journal {} cannot be written: {e}",
                path.display()
            ));
            if let Health::Failing(why) = &journal.health {
                news.push(format!(
                    "{why}; leases work in memory only and are not kept across a restart"
                ));
            }
        }
        Opened {
            journal,
            recovered,
            news,
        }
    }

    fn new(dir: Option<PathBuf>, health: Health) -> Self {
        Journal {
            dir,
            file: None,
            state: JournalState::default(),
            rewrite: false,
            health,
            counts: Counts::default(),
            snapshot_len: 0,
        }
    }

    /// How it stands.
    pub fn health(&self) -> &Health {
        &self.health
    }

    /// Its counts.
    pub fn counts(&self) -> Counts {
        self.counts
    }

    /// What it holds now.
    pub fn state(&self) -> &JournalState {
        &self.state
    }

    /// What is owed to drive `old` is owed to `new` from now on (the same
    /// motor, renamed by a reload): appended and synced like any record.
    pub fn rename(&mut self, old: &str, new: &str) -> Result<(), String> {
        let records = self.state.renamed(old, new);
        if records.is_empty() {
            return Ok(());
        }
        self.append(&records)
    }

    /// Appends `records` and syncs them to the disk (one sync for all).
    /// The state is kept in memory even when the disk fails, so the
    /// journal is whole again once the disk takes writes.
    pub fn append(&mut self, records: &[Record]) -> Result<(), String> {
        for r in records {
            self.state.apply(r);
        }
        if self.dir.is_none() || records.is_empty() {
            return Ok(());
        }
        let result = if self.rewrite {
            self.compact()
        } else {
            self.write(records)
        };
        match result {
            Ok(()) => {
                self.counts.records += records.len() as u64;
                if !matches!(self.health, Health::Ok) {
                    tracing::info!("the safety journal is written again");
                    self.health = Health::Ok;
                }
                if self.counts.bytes > COMPACT_AT.max(2 * self.snapshot_len)
                    && let Err(e) = self.compact()
                {
                    self.fail(format!("the safety journal could not be compacted: {e}"));
                }
                Ok(())
            }
            Err(e) => {
                self.counts.write_errors += 1;
                self.rewrite = true;
                let why = format!("the safety journal could not be written: {e}");
                self.fail(why.clone());
                Err(why)
            }
        }
    }

    fn fail(&mut self, why: String) {
        self.health = Health::Failing(why);
        self.file = None;
        self.rewrite = true;
    }

    fn write(&mut self, records: &[Record]) -> io::Result<()> {
        let Some(file) = self.file.as_mut() else {
            return Err(io::Error::other("the journal is not open"));
        };
        let mut bytes = Vec::new();
        for r in records {
            bytes.extend(format::encode(r));
        }
        file.write_all(&bytes)?;
        file.sync_data()?;
        self.counts.bytes += bytes.len() as u64;
        Ok(())
    }

    /// Rewrites the journal as a snapshot of its state: a temporary file,
    /// synced, renamed over the journal, and the directory synced, so the
    /// journal is at every instant either the old file or the new one.
    fn compact(&mut self) -> io::Result<()> {
        let Some(dir) = self.dir.clone() else {
            return Ok(());
        };
        fs::create_dir_all(&dir)?;
        let tmp = dir.join(format!("{FILE}.tmp"));
        let path = dir.join(FILE);
        let mut bytes = format::header();
        for r in self.state.snapshot() {
            bytes.extend(format::encode(&r));
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
        self.counts.bytes = bytes.len() as u64;
        self.snapshot_len = bytes.len() as u64;
        self.counts.compactions += 1;
        self.rewrite = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::format::{Action, HolderKind, ModeName};
    use super::*;

    fn lease(deadline_ms: u64) -> Record {
        Record::Lease {
            drive: "conveyor".into(),
            owner: "scada".into(),
            holder: HolderKind::Http,
            deadline_ms,
            length_ms: 1000,
            action: Action::ZeroSpeed,
            mode: ModeName::Speed,
        }
    }

    #[test]
    fn what_is_appended_is_read_back_by_the_next_process() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::open(Some(dir.path()), 4).journal;
        assert_eq!(j.health(), &Health::Ok);
        j.append(&[lease(5)]).unwrap();
        let state = j.state().clone();
        drop(j);
        let opened = Journal::open(Some(dir.path()), 4);
        assert_eq!(opened.recovered, Recovered::Read(state));
        assert!(opened.news.is_empty(), "{:?}", opened.news);
    }

    #[test]
    fn a_growing_journal_is_compacted_to_what_it_holds() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::open(Some(dir.path()), 4).journal;
        // 5000 records, ten to a sync.
        for i in 0..500 {
            let batch: Vec<Record> = (0..10).map(|k| lease(i * 10 + k)).collect();
            j.append(&batch).unwrap();
        }
        let c = j.counts();
        assert!(c.compactions >= 3, "{c:?}");
        assert!(c.bytes <= COMPACT_AT + 200, "{c:?}");
        let on_disk = fs::metadata(dir.path().join(FILE)).unwrap().len();
        assert_eq!(on_disk, c.bytes);
        let read = Journal::open(Some(dir.path()), 4).recovered;
        assert_eq!(read, Recovered::Read(JournalState::of(&[lease(4_999)])));
        assert!(!dir.path().join(format!("{FILE}.tmp")).exists());
    }

    #[test]
    fn a_torn_tail_is_said_and_dropped_and_garbage_is_set_aside() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::open(Some(dir.path()), 4).journal;
        j.append(&[lease(7)]).unwrap();
        drop(j);
        let path = dir.path().join(FILE);
        let mut bytes = fs::read(&path).unwrap();
        bytes.extend_from_slice(&[40, 0, 0, 0, 1, 2]);
        fs::write(&path, &bytes).unwrap();
        let opened = Journal::open(Some(dir.path()), 4);
        assert_eq!(
            opened.recovered,
            Recovered::Read(JournalState::of(&[lease(7)]))
        );
        assert!(opened.news[0].contains("cut short"), "{:?}", opened.news);
        drop(opened);
        // Rewritten without the tail.
        assert!(Journal::open(Some(dir.path()), 4).news.is_empty());

        fs::write(&path, b"garbage").unwrap();
        let opened = Journal::open(Some(dir.path()), 4);
        assert_eq!(opened.recovered, Recovered::Unreadable);
        assert_eq!(opened.journal.counts().unreadable, 1);
        assert!(opened.news[0].contains("set aside"), "{:?}", opened.news);
        let aside = fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .is_ok_and(|e| e.file_name().to_string_lossy().contains("unreadable"))
            })
            .count();
        assert_eq!(aside, 1);
    }

    #[test]
    fn a_journal_beyond_its_bound_is_read_from_its_end() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE);
        // Renewals without a clean stop, longer than the read budget.
        let mut bytes = format::header();
        let mut deadline = 0;
        while (bytes.len() as u64) < 3 * tail::CHUNK + read_budget(4) {
            deadline += 1;
            bytes.extend(format::encode(&lease(deadline)));
        }
        fs::write(&path, &bytes).unwrap();
        let opened = Journal::open(Some(dir.path()), 4);
        // The newest record read is the last word; older ones are unknown.
        assert_eq!(
            opened.recovered,
            Recovered::Tail(JournalState::of(&[lease(deadline)]))
        );
        let skipped = opened.journal.counts().skipped_bytes;
        assert!(skipped >= tail::CHUNK, "{skipped}");
        assert!(
            opened.news.iter().any(|n| n.contains("on_unknown_state")),
            "{:?}",
            opened.news
        );
        // Compacted: the next start reads it whole.
        drop(opened);
        assert!(fs::metadata(&path).unwrap().len() < 1024);
        assert!(matches!(
            Journal::open(Some(dir.path()), 4).recovered,
            Recovered::Read(_)
        ));

        // With a clean stop near its end, all that is owed is after it.
        bytes.extend(format::encode(&Record::Shutdown));
        bytes.extend(format::encode(&lease(7)));
        fs::write(&path, &bytes).unwrap();
        let opened = Journal::open(Some(dir.path()), 4);
        assert_eq!(
            opened.recovered,
            Recovered::Read(JournalState::of(&[lease(7)]))
        );
        assert!(opened.journal.counts().skipped_bytes > 0);
    }

    #[test]
    fn a_directory_that_cannot_be_written_keeps_the_state_in_memory() {
        let dir = tempfile::tempdir().unwrap();
        let blocked = dir.path().join("a-file");
        fs::write(&blocked, b"x").unwrap();
        let mut opened = Journal::open(Some(&blocked), 4);
        assert_eq!(opened.recovered, Recovered::Unreadable);
        assert!(matches!(opened.journal.health(), Health::Failing(_)));
        assert!(opened.journal.append(&[lease(9)]).is_err());
        assert_eq!(opened.journal.counts().write_errors, 1);
        assert_eq!(opened.journal.state(), &JournalState::of(&[lease(9)]));
        assert!(check_writable(&blocked).is_err());
        assert!(check_writable(&dir.path().join("state")).is_ok());
    }
}
