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
//! write the journal misses, and the file cut back to its header so that
//! the next start knows it does not know (below).
//!
//! What a start cannot know is treated as unknown ([`replay::Unknown`]):
//! a journal that cannot be read, one that is empty or ends at its header
//! (every file this daemon writes begins with a snapshot record, so such a
//! file lost what it held), and one that is missing where the state
//! directory shows an earlier run (its marker, [`MARKER`], written with the
//! first journal, or the alarm file, or a journal set aside). Then every
//! drive found moving gets `[safety] on_unknown_state`.
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
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use format::{Record, Unreadable};
use replay::{JournalState, Recovered, Unknown};
use tail::Wanted;

/// The journal's file name in the state directory.
pub const FILE: &str = "safety.journal";
/// The file that says a journal was kept in the state directory: written
/// (and synced, with the directory) before the first journal, never
/// removed by drivegate. A start that finds it but no journal knows the
/// journal was lost.
pub const MARKER: &str = "safety.journal.marker";
/// Other files of the state directory that only an earlier run leaves:
/// the alarm file (written at every start) and journals set aside.
const EARLIER_RUN: &[&str] = &[crate::control::alarms::file::FILE];
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
    /// Journals found lost at start-up: empty, ending at their header, or
    /// missing where the state directory shows an earlier run.
    pub lost: u64,
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

/// What the state directory held of the journal at start-up.
enum Found {
    /// No journal file.
    NoFile,
    /// A file without a single whole record: empty, or its header alone.
    Nothing(Unknown),
    /// Records.
    Records(ReadBack),
}

/// Reads the journal at `path` from its end back to its last clean stop,
/// its start, or `budget` bytes.
fn read(path: &Path, budget: u64) -> Result<Found, Unreadable> {
    let mut newest_first: Vec<Record> = Vec::new();
    let mut clean = false;
    let mut any = false;
    let read = tail::read_from_end(path, format::SAFETY_JOURNAL, budget, |records| {
        any |= !records.is_empty();
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
        return Ok(Found::NoFile);
    };
    if !any {
        // A file this daemon wrote begins with its snapshot record.
        return Ok(Found::Nothing(if read.len < format::HEADER_LEN as u64 {
            Unknown::Empty
        } else {
            Unknown::HeaderOnly
        }));
    }
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
    Ok(Found::Records(ReadBack {
        state: JournalState::of(&newest_first),
        whole,
        skipped: read.skipped,
        news,
    }))
}

/// What in `dir` shows that drivegate ran there before, in words (`None`:
/// nothing, a first start).
pub fn earlier_run(dir: &Path) -> Option<String> {
    if dir.join(MARKER).exists() {
        return Some(format!("its marker {MARKER} is there"));
    }
    if let Some(file) = EARLIER_RUN.iter().find(|f| dir.join(f).exists()) {
        return Some(format!("{file} is there"));
    }
    let aside = fs::read_dir(dir).ok()?.find_map(|e| {
        let name = e.ok()?.file_name().to_string_lossy().into_owned();
        name.starts_with(&format!("{FILE}.unreadable-"))
            .then_some(name)
    })?;
    Some(format!("{aside} is there"))
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
            Ok(Found::Records(read)) => {
                news.extend(read.news);
                journal.counts.skipped_bytes = read.skipped;
                journal.state = read.state;
                if read.whole {
                    Recovered::Read(journal.state.clone())
                } else {
                    Recovered::Tail(journal.state.clone())
                }
            }
            Ok(Found::NoFile) => match earlier_run(dir) {
                None => Recovered::Read(JournalState::default()),
                Some(evidence) => lost(&mut journal, &mut news, &path, Unknown::Missing(evidence)),
            },
            Ok(Found::Nothing(unknown)) => lost(&mut journal, &mut news, &path, unknown),
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
                let unknown = Unknown::Unreadable(format!("{why}; {moved}"));
                news.push(format!(
                    "{} ({}). What the last process promised about the motors is unknown: [safety] on_unknown_state is applied to every drive found moving",
                    unknown.words(),
                    path.display(),
                ));
                Recovered::Unknown(unknown)
            }
        };
        // The marker first, so that from now on a journal that goes
        // missing is known to be lost; then a clean snapshot (no torn
        // tail, nothing ended), whose directory sync covers both.
        if let Err(e) = write_marker(dir) {
            tracing::warn!(
                "the safety journal's marker {} could not be written: {e}",
                dir.join(MARKER).display()
            );
        }
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
            self.write(records).and_then(|kept| {
                if kept {
                    return Ok(());
                }
                // Written to a file nobody can open any more: the journal
                // is written again, whole, where the next start looks.
                tracing::warn!(
                    "the safety journal was deleted while drivegate ran: it is written again"
                );
                self.compact()
            })
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
                self.forget();
                self.fail(why.clone());
                Err(why)
            }
        }
    }

    /// The disk did not take a record: the file is cut back to its header
    /// (which needs no space), so that a start after a crash finds a
    /// journal that says it lost what it held, not an older one that would
    /// pass for the truth. Rewritten whole once the disk takes writes.
    fn forget(&mut self) {
        let Some(dir) = &self.dir else { return };
        let cut = OpenOptions::new()
            .write(true)
            .open(dir.join(FILE))
            .and_then(|f| {
                f.set_len(format::HEADER_LEN as u64)?;
                f.sync_all()
            });
        match cut {
            Ok(()) => {}
            // Nothing on the disk to pass for the truth.
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::NotFound | io::ErrorKind::NotADirectory
                ) => {}
            Err(e) => {
                tracing::warn!("the safety journal could not be cut back to its header: {e}");
            }
        }
    }

    fn fail(&mut self, why: String) {
        self.health = Health::Failing(why);
        self.file = None;
        self.rewrite = true;
    }

    /// Appends `records` and syncs them; `false`: the file has been
    /// deleted (they went to a file no start will find).
    fn write(&mut self, records: &[Record]) -> io::Result<bool> {
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
        Ok(file.metadata()?.nlink() > 0)
    }

    /// Rewrites the journal as a snapshot of its state: a temporary file,
    /// synced, renamed over the journal, and the directory synced, so the
    /// journal is at every instant either the old file or the new one.
    fn compact(&mut self) -> io::Result<()> {
        let Some(dir) = self.dir.clone() else {
            return Ok(());
        };
        create_dir(&dir)?;
        let tmp = dir.join(format!("{FILE}.tmp"));
        let path = dir.join(FILE);
        let mut bytes = format::header();
        bytes.extend(format::encode(&Record::Snapshot {
            at_ms: format::unix_ms(SystemTime::now()),
        }));
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

/// A journal found lost (`unknown`): counted, said, and unknown.
fn lost(journal: &mut Journal, news: &mut Vec<String>, path: &Path, unknown: Unknown) -> Recovered {
    journal.counts.lost += 1;
    news.push(format!(
        "{} ({}): a journal drivegate writes always holds its first record, so what the last process promised about the motors was lost (a power cut on a disk that did not keep what it was told to keep, or the file emptied or deleted by hand). [safety] on_unknown_state is applied to every drive found moving",
        unknown.words(),
        path.display(),
    ));
    Recovered::Unknown(unknown)
}

/// Writes the marker in `dir` (created if missing), unless it is there.
/// The directory is synced by the journal's snapshot written next.
fn write_marker(dir: &Path) -> io::Result<()> {
    let marker = dir.join(MARKER);
    if marker.exists() {
        return Ok(());
    }
    create_dir(dir)?;
    let mut f = File::create(&marker)?;
    f.write_all(
        format!(
            "drivegate keeps its safety journal ({FILE}) in this directory. A start that finds this file but no {FILE} knows the journal was lost, and applies [safety] on_unknown_state to every drive found moving. Do not remove it without the journal.\n"
        )
        .as_bytes(),
    )?;
    f.sync_all()
}

/// Creates `dir` if it is missing, and syncs its parent, so that the
/// directory itself survives a power cut.
fn create_dir(dir: &Path) -> io::Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    fs::create_dir_all(dir)?;
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        File::open(parent)?.sync_all()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
