//! The safety journal's file format, pure: no I/O here.
//!
//! ```text
//! header:  "DRVGJRNL" (8 bytes)  version: u32 LE (2; 1 is read too)
//! record:  length: u32 LE  crc32(payload): u32 LE  payload (JSON, `length` bytes)
//! ```
//!
//! Every time the file is written whole (at its creation, at each start,
//! at a compaction) its first record is a [`Record::Snapshot`]: a journal
//! this drivegate wrote is never shorter than its header and that record.
//! So an empty file, or one that ends at its header, is no empty journal
//! but one whose contents were lost (a power cut on a disk that did not
//! keep what it was told to keep, a hand that emptied it): what it held
//! is unknown, and the reader says so rather than "nothing is owed".
//!
//! Why this shape: the file is only ever appended to, and a power cut can
//! leave the last append half written. Each record says how long it is and
//! carries a CRC-32 of its bytes, so a torn or garbled tail is recognised
//! (too short, or a CRC that does not match) and ignored instead of being
//! read as something the daemon promised. A bad record with good records
//! after it cannot come from a torn append: that file is not trusted at
//! all. The header's magic and version make a file of another program, or
//! of a newer drivegate, readable as "not mine" rather than as garbage.
//! The payload is JSON so an engineer can read a journal with a few lines
//! of script, and a field added later is ignored by an older reader.
//!
//! The framing is not the safety journal's alone: [`Kind`] names a file's
//! magic and version, and [`header_of`], [`frame`] and [`decode_as`] read
//! and write any record type in it (the alarm book's file uses them).

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

/// The first 8 bytes of a journal.
pub const MAGIC: &[u8; 8] = b"DRVGJRNL";

/// A kind of framed file: its magic, its format versions, and its name in
/// words (for the errors).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Kind {
    /// The first 8 bytes.
    pub magic: &'static [u8; 8],
    /// The format version this drivegate writes (and reads).
    pub version: u32,
    /// The oldest format version it reads.
    pub oldest: u32,
    /// What it is, as in "it is not a drivegate ...".
    pub what: &'static str,
}

/// The safety journal.
pub const SAFETY_JOURNAL: Kind = Kind {
    magic: MAGIC,
    version: VERSION,
    oldest: 1,
    what: "safety journal",
};
/// The format this drivegate writes: 2, whose files begin with a
/// [`Record::Snapshot`]. Version 1 (the same records, without that one)
/// is read too.
pub const VERSION: u32 = 2;
/// Header length: the magic and the version.
pub const HEADER_LEN: usize = 12;
/// A record's frame: its length and its CRC.
pub const FRAME_LEN: usize = 8;
/// No record is longer: a longer length field is garbage.
pub const MAX_RECORD: usize = 64 * 1024;

/// Who held a lease, as a restart must know it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum HolderKind {
    /// A single request (REST, with a token): its client can renew it
    /// against the next process.
    Http,
    /// A session (a WebSocket): it ends with the process.
    Session,
    /// A session's communication-loss function (a Modbus TCP client's
    /// network, the MQTT session, an OPC UA session): it ends with the
    /// process.
    CommLoss,
}

impl HolderKind {
    /// In words.
    pub fn words(self) -> &'static str {
        match self {
            HolderKind::Http => "an HTTP client",
            HolderKind::Session => "a WebSocket stream session",
            HolderKind::CommLoss => {
                "a session with a communication-loss time (a Modbus TCP connection, the MQTT session or an OPC UA session)"
            }
        }
    }
}

/// A stop action as written in the journal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Action {
    /// Zero speed (or torque) in the drive's mode.
    ZeroSpeed,
    /// The emergency brake.
    Brake,
    /// Nothing.
    None,
}

/// A drive mode as written in the journal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ModeName {
    /// Open loop.
    OpenLoop,
    /// Speed.
    Speed,
    /// Position.
    Position,
    /// Torque.
    Torque,
}

/// Where a brake sent to a drive stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BrakeState {
    /// Sent; the drive has not confirmed it (yet).
    Sent,
    /// The drive confirmed it: the last confirmed command was a brake.
    Confirmed,
    /// Surely not applied, or a write since released it.
    Off,
}

/// One record: a fact a restart must know. Drives by name, so a journal
/// survives a reordering of the configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "record", rename_all = "kebab-case")]
pub enum Record {
    /// A lease is on the drive, until `deadline_ms` (Unix ms) at the
    /// latest.
    Lease {
        /// Drive name.
        drive: String,
        /// Who holds it (token name, client address).
        owner: String,
        /// What holds it.
        holder: HolderKind,
        /// Its deadline, Unix time in ms: never later than the one
        /// promised (see `Journal`'s horizon rule).
        deadline_ms: u64,
        /// Its length, ms.
        length_ms: u64,
        /// What its end sends.
        action: Action,
        /// The mode its setpoint drives the motor in.
        mode: ModeName,
    },
    /// The drive's lease ended without a stop (released, ended by a brake
    /// or deactivation, or its setpoint surely never landed).
    LeaseEnded {
        /// Drive name.
        drive: String,
    },
    /// A stop of the drive is being carried out (it ends the drive's
    /// lease when `ends_lease`).
    Stop {
        /// Drive name.
        drive: String,
        /// Who held the lease it ends, if it ends one.
        owner: Option<String>,
        /// What to send.
        action: Action,
        /// The mode to decide on when the drive's cannot be read.
        mode: ModeName,
        /// It ends the drive's lease.
        ends_lease: bool,
    },
    /// The drive's stop ended: confirmed, or taken over by something newer.
    StopEnded {
        /// Drive name.
        drive: String,
    },
    /// A brake on its way, confirmed, or released.
    Brake {
        /// Drive name.
        drive: String,
        /// Where it stands.
        state: BrakeState,
    },
    /// drivegate stopped cleanly: its safe stop covered every drive, and
    /// nothing before this record is owed.
    Shutdown,
    /// The file was written whole at `at_ms` (Unix ms): the first record
    /// of every journal this drivegate writes, so a file without any
    /// record is known to have lost what it held. It says nothing of the
    /// drives: the records after it do.
    Snapshot {
        /// When, Unix ms.
        at_ms: u64,
    },
}

/// Milliseconds since the Unix epoch (0 before it).
pub fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// The time `ms` after the Unix epoch.
pub fn from_unix_ms(ms: u64) -> SystemTime {
    UNIX_EPOCH + Duration::from_millis(ms)
}

/// The header of a new journal.
pub fn header() -> Vec<u8> {
    header_of(SAFETY_JOURNAL)
}

/// The header of a new file of `kind`.
pub fn header_of(kind: Kind) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_LEN);
    out.extend_from_slice(kind.magic);
    out.extend_from_slice(&kind.version.to_le_bytes());
    out
}

/// One record, framed.
pub fn encode(record: &Record) -> Vec<u8> {
    frame(record)
}

/// Any record, as JSON, framed (its length and CRC-32 before it).
pub fn frame<T: Serialize>(record: &T) -> Vec<u8> {
    // A record of strings and numbers always serializes.
    let payload = serde_json::to_vec(record).unwrap_or_default();
    let mut out = Vec::with_capacity(FRAME_LEN + payload.len());
    out.extend_from_slice(&u32::try_from(payload.len()).unwrap_or(0).to_le_bytes());
    out.extend_from_slice(&crc32(&payload).to_le_bytes());
    out.extend_from_slice(&payload);
    out
}

/// Why a journal cannot be trusted, in words.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Unreadable {
    /// The file does not start with the magic.
    #[error("it is not a drivegate {} (its first bytes are not \"{}\")", .0.what, String::from_utf8_lossy(.0.magic))]
    NotAJournal(Kind),
    /// Another version of the format.
    #[error("it is in format version {found}; this drivegate reads {}", versions(*.oldest, *.newest))]
    Version {
        /// The file's.
        found: u32,
        /// The oldest this drivegate reads.
        oldest: u32,
        /// The newest this drivegate reads (the one it writes).
        newest: u32,
    },
    /// A bad record with more after it: not a torn append.
    #[error("the record at byte {offset} is damaged ({why}) and more follows it")]
    Damaged {
        /// Its byte offset in the file.
        offset: u64,
        /// What is wrong with it.
        why: &'static str,
    },
    /// The file could not be read at all.
    #[error("it could not be read: {0}")]
    Io(String),
}

/// "version 2", or "versions 1 to 2".
fn versions(oldest: u32, newest: u32) -> String {
    if oldest == newest {
        format!("version {newest}")
    } else {
        format!("versions {oldest} to {newest}")
    }
}

/// A journal read back.
pub type Decoded = DecodedAs<Record>;

/// A framed file read back.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedAs<T> {
    /// Its records, in order.
    pub records: Vec<T>,
    /// Bytes of good records, header included: where the next append goes.
    pub good_len: usize,
    /// Bytes of a torn last record ignored (0: none).
    pub torn: usize,
}

/// Reads a journal's bytes. An empty file is an empty journal (a crash
/// while creating it); a torn last record is left out and counted.
pub fn decode(bytes: &[u8]) -> Result<Decoded, Unreadable> {
    decode_as(SAFETY_JOURNAL, bytes)
}

/// What a file's first bytes say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Header {
    /// A whole header of `kind`: records follow it.
    Whole,
    /// An empty file, or a header cut short while the file was created:
    /// an empty file of `kind`.
    Torn,
}

/// Checks the header of a file of `kind` (its first [`HEADER_LEN`] bytes,
/// or all of it if shorter).
pub fn check_header(kind: Kind, head: &[u8]) -> Result<Header, Unreadable> {
    let magic = kind.magic;
    if head.len() < HEADER_LEN {
        // A header cut short is a file torn while it was created, if what
        // there is matches.
        let n = head.len().min(magic.len());
        if head[..n] == magic[..n] {
            return Ok(Header::Torn);
        }
        return Err(Unreadable::NotAJournal(kind));
    }
    if &head[..8] != magic {
        return Err(Unreadable::NotAJournal(kind));
    }
    let version = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if !(kind.oldest..=kind.version).contains(&version) {
        return Err(Unreadable::Version {
            found: version,
            oldest: kind.oldest,
            newest: kind.version,
        });
    }
    Ok(Header::Whole)
}

/// Reads the bytes of a file of `kind` with records of type `T`, as
/// [`decode`] reads a journal.
pub fn decode_as<T: serde::de::DeserializeOwned>(
    kind: Kind,
    bytes: &[u8],
) -> Result<DecodedAs<T>, Unreadable> {
    if check_header(kind, &bytes[..bytes.len().min(HEADER_LEN)])? == Header::Torn {
        return Ok(DecodedAs {
            records: Vec::new(),
            good_len: 0,
            torn: bytes.len(),
        });
    }
    let chain = frames(bytes, HEADER_LEN, true).map_err(|(at, why)| Unreadable::Damaged {
        offset: at as u64,
        why,
    })?;
    let records = parse(bytes, &chain.payloads, 0)?;
    Ok(DecodedAs {
        records,
        good_len: chain.good_len,
        torn: bytes.len() - chain.good_len,
    })
}

/// The records of `payloads` (ranges of `bytes`, which starts at byte
/// `base` of its file).
pub(super) fn parse<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
    payloads: &[std::ops::Range<usize>],
    base: u64,
) -> Result<Vec<T>, Unreadable> {
    payloads
        .iter()
        .map(|p| {
            serde_json::from_slice::<T>(&bytes[p.clone()]).map_err(|_| Unreadable::Damaged {
                offset: base + (p.start - FRAME_LEN) as u64,
                why: "its CRC matches but its content is not a known record",
            })
        })
        .collect()
}

/// Frames that follow one another to the end of some bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Chain {
    /// Each whole frame's payload, in order.
    pub payloads: Vec<std::ops::Range<usize>>,
    /// Where the last whole frame ends (the rest is a torn frame).
    pub good_len: usize,
}

/// What is at some offset of a framed file's bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum FrameAt {
    /// A whole frame: its payload's range (it ends where that does).
    Whole(std::ops::Range<usize>),
    /// A frame whose bytes do not all come before the end.
    Short,
    /// Not a good frame: why, and where it ends when its length could be
    /// read.
    Bad(&'static str, Option<usize>),
}

/// The frame at `at` of `bytes`.
pub(super) fn frame_at(bytes: &[u8], at: usize) -> FrameAt {
    let Some(head) = bytes.get(at..at + FRAME_LEN) else {
        return FrameAt::Short;
    };
    let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
    if len > MAX_RECORD {
        return FrameAt::Bad("its length is impossible", None);
    }
    let payload = at + FRAME_LEN..at + FRAME_LEN + len;
    let Some(body) = bytes.get(payload.clone()) else {
        return FrameAt::Short;
    };
    let crc = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
    if crc32(body) != crc {
        return FrameAt::Bad("its CRC does not match", Some(payload.end));
    }
    FrameAt::Whole(payload)
}

/// Follows the frames of `bytes` from `from` to its end. With `torn_ok`
/// the last frame may be cut short or garbled (a torn append); anything
/// else that is not a whole frame is an error, with its offset.
pub(super) fn frames(
    bytes: &[u8],
    from: usize,
    torn_ok: bool,
) -> Result<Chain, (usize, &'static str)> {
    let mut payloads = Vec::new();
    let mut at = from;
    while at < bytes.len() {
        match frame_at(bytes, at) {
            FrameAt::Whole(payload) => {
                at = payload.end;
                payloads.push(payload);
            }
            // Torn mid-write: its bytes never all reached the disk.
            FrameAt::Short if torn_ok => break,
            FrameAt::Bad(_, Some(end)) if torn_ok && end == bytes.len() => break,
            FrameAt::Short => return Err((at, "it is cut short")),
            FrameAt::Bad(why, _) => return Err((at, why)),
        }
    }
    Ok(Chain {
        payloads,
        good_len: at,
    })
}

/// CRC-32 (IEEE 802.3, the one of zip and PNG).
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc = TABLE[((crc ^ u32::from(b)) & 0xFF) as usize] ^ (crc >> 8);
    }
    !crc
}

const TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
};

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn lease(drive: &str) -> Record {
        Record::Lease {
            drive: drive.to_string(),
            owner: "scada".to_string(),
            holder: HolderKind::Http,
            deadline_ms: 1_700_000_000_000,
            length_ms: 1000,
            action: Action::ZeroSpeed,
            mode: ModeName::Speed,
        }
    }

    fn journal(records: &[Record]) -> Vec<u8> {
        let mut bytes = header();
        for r in records {
            bytes.extend(encode(r));
        }
        bytes
    }

    #[test]
    fn crc32_matches_the_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn records_read_back_as_written() {
        let records = vec![
            lease("conveyor"),
            Record::Brake {
                drive: "lift".into(),
                state: BrakeState::Confirmed,
            },
            Record::Shutdown,
            Record::Snapshot { at_ms: 17 },
        ];
        let bytes = journal(&records);
        let d = decode(&bytes).unwrap();
        assert_eq!(d.records, records);
        assert_eq!((d.good_len, d.torn), (bytes.len(), 0));
    }

    #[test]
    fn a_torn_last_record_is_ignored_at_every_cut() {
        let whole = journal(&[lease("conveyor"), lease("lift")]);
        let first_end = journal(&[lease("conveyor")]).len();
        for cut in first_end + 1..whole.len() {
            let d = decode(&whole[..cut]).unwrap();
            assert_eq!(d.records, vec![lease("conveyor")], "cut at {cut}");
            assert_eq!((d.good_len, d.torn), (first_end, cut - first_end));
        }
        // A last record with its bytes written but garbled (the sectors
        // reached the disk out of order) is torn too.
        let mut garbled = whole.clone();
        let last = garbled.len() - 2;
        garbled[last] ^= 0x55;
        assert_eq!(decode(&garbled).unwrap().records.len(), 1);
    }

    #[test]
    fn a_damaged_record_before_good_ones_makes_the_journal_unreadable() {
        let mut bytes = journal(&[lease("conveyor"), lease("lift")]);
        bytes[HEADER_LEN + FRAME_LEN + 3] ^= 0x55;
        assert!(matches!(
            decode(&bytes),
            Err(Unreadable::Damaged { offset, .. }) if offset == HEADER_LEN as u64
        ));
    }

    #[test]
    fn other_files_and_versions_are_not_read() {
        let not = decode(b"hello, this is not a journal");
        assert_eq!(not, Err(Unreadable::NotAJournal(SAFETY_JOURNAL)));
        assert_eq!(
            not.unwrap_err().to_string(),
            "it is not a drivegate safety journal (its first bytes are not \"DRVGJRNL\")"
        );
        let mut v3 = journal(&[]);
        v3[8] = 3;
        let newer = decode(&v3);
        assert_eq!(
            newer,
            Err(Unreadable::Version {
                found: 3,
                oldest: 1,
                newest: 2
            })
        );
        assert_eq!(
            newer.unwrap_err().to_string(),
            "it is in format version 3; this drivegate reads versions 1 to 2"
        );
        // Version 1, the same records without the snapshot, is read.
        let mut v1 = journal(&[lease("conveyor")]);
        v1[8] = 1;
        assert_eq!(decode(&v1).unwrap().records, vec![lease("conveyor")]);
        // An impossible length.
        let mut long = journal(&[]);
        long.extend_from_slice(&u32::MAX.to_le_bytes());
        long.extend_from_slice(&[0; 100]);
        assert!(matches!(decode(&long), Err(Unreadable::Damaged { .. })));
    }

    #[test]
    fn empty_and_half_headers_are_new_journals() {
        assert!(decode(b"").unwrap().records.is_empty());
        assert_eq!(decode(b"DRVG").unwrap().torn, 4);
    }
}
