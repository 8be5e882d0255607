//! What a restart owes the motors, as a pure function of the journal, the
//! time and the drives' statuses: [`replay`]. The rules (docs/safety.md):
//!
//! - a lease held by a session (a WebSocket, a Modbus TCP connection with a
//!   communication-loss time) ends with its stop at once: its holder died
//!   with the old process;
//! - an HTTP lease keeps its deadline: its client can renew it against the
//!   new process, else it ends with its stop then; one that ran out while
//!   drivegate was down ends with its stop at once;
//! - a stop that was being tried is tried again until the drive confirms
//!   it; a brake sent but never confirmed is applied again;
//! - a drive whose last confirmed command was a brake gets no stop that
//!   could release it (a zero speed would);
//! - a setpoint without a lease is left alone: nothing was promised;
//! - a journal whose contents are unknown ([`Unknown`]: it cannot be
//!   read, it is empty or ends at its header, it is missing where the
//!   state directory shows an earlier run) promises nothing that can be
//!   trusted: every configured drive found moving gets `[safety]
//!   on_unknown_state` (with `none`, it is left moving, and said);
//! - a journal read only in part (its older records skipped, see
//!   [`super::tail`]) is trusted for what its records read say, and every
//!   other drive found moving gets `on_unknown_state`.

use std::collections::BTreeMap;
use std::time::{Duration, SystemTime};

use super::format::{Action, BrakeState, HolderKind, ModeName, Record, from_unix_ms};

/// A lease as the journal last recorded it.
#[derive(Debug, Clone, PartialEq)]
pub struct JournaledLease {
    /// Who held it.
    pub owner: String,
    /// What held it.
    pub holder: HolderKind,
    /// Its deadline (never later than the one promised).
    pub deadline: SystemTime,
    /// Its length.
    pub length: Duration,
    /// What its end sends.
    pub action: Action,
    /// Its setpoint's mode.
    pub mode: ModeName,
}

/// A stop as the journal last recorded it.
#[derive(Debug, Clone, PartialEq)]
pub struct JournaledStop {
    /// Who held the lease it ends, if any.
    pub owner: Option<String>,
    /// What it sends.
    pub action: Action,
    /// The mode to decide on.
    pub mode: ModeName,
}

/// What the journal says of one drive.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DriveRecord {
    /// Its lease.
    pub lease: Option<JournaledLease>,
    /// A stop being carried out.
    pub stop: Option<JournaledStop>,
    /// Its last brake.
    pub brake: Option<BrakeState>,
}

impl DriveRecord {
    fn is_empty(&self) -> bool {
        self.lease.is_none()
            && self.stop.is_none()
            && matches!(self.brake, None | Some(BrakeState::Off))
    }
}

/// What the journal says, drive by drive: its records folded.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct JournalState {
    /// By drive name.
    pub drives: BTreeMap<String, DriveRecord>,
}

impl JournalState {
    /// The state after `records`.
    pub fn of(records: &[Record]) -> Self {
        let mut state = JournalState::default();
        for r in records {
            state.apply(r);
        }
        state
    }

    /// Folds one record in.
    pub fn apply(&mut self, record: &Record) {
        fn entry<'a>(
            drives: &'a mut BTreeMap<String, DriveRecord>,
            drive: &str,
        ) -> &'a mut DriveRecord {
            drives.entry(drive.to_string()).or_default()
        }
        let drives = &mut self.drives;
        match record {
            Record::Lease {
                drive,
                owner,
                holder,
                deadline_ms,
                length_ms,
                action,
                mode,
            } => {
                let d = entry(drives, drive);
                d.lease = Some(JournaledLease {
                    owner: owner.clone(),
                    holder: *holder,
                    deadline: from_unix_ms(*deadline_ms),
                    length: Duration::from_millis(*length_ms),
                    action: *action,
                    mode: *mode,
                });
                // Its setpoint releases a brake.
                d.brake = None;
            }
            Record::LeaseEnded { drive } => entry(drives, drive).lease = None,
            Record::Stop {
                drive,
                owner,
                action,
                mode,
                ends_lease,
            } => {
                let d = entry(drives, drive);
                if *ends_lease {
                    d.lease = None;
                }
                d.stop = Some(JournaledStop {
                    owner: owner.clone(),
                    action: *action,
                    mode: *mode,
                });
            }
            Record::StopEnded { drive } => entry(drives, drive).stop = None,
            Record::Brake { drive, state } => {
                let d = entry(drives, drive);
                d.brake = match state {
                    BrakeState::Off => None,
                    s => Some(*s),
                };
                if *state == BrakeState::Confirmed {
                    // A confirmed brake ends the lease and a stop under way.
                    d.lease = None;
                    d.stop = None;
                }
            }
            Record::Shutdown => drives.clear(),
            Record::Snapshot { .. } => {}
        }
        self.drives.retain(|_, d| !d.is_empty());
    }

    /// The records that move what is owed to drive `old` to `new` (the
    /// same motor, renamed by a reload): the state restated under the new
    /// name first, then ended under the old one, so a journal cut between
    /// the two still owes it (the old name, no longer configured, is then
    /// told apart at the restart).
    pub fn renamed(&self, old: &str, new: &str) -> Vec<Record> {
        let Some(d) = self.drives.get(old) else {
            return Vec::new();
        };
        let one = JournalState {
            drives: BTreeMap::from([(new.to_string(), d.clone())]),
        };
        let mut out = one.snapshot();
        if d.lease.is_some() {
            out.push(Record::LeaseEnded {
                drive: old.to_string(),
            });
        }
        if d.stop.is_some() {
            out.push(Record::StopEnded {
                drive: old.to_string(),
            });
        }
        if d.brake.is_some() {
            out.push(Record::Brake {
                drive: old.to_string(),
                state: BrakeState::Off,
            });
        }
        out
    }

    /// The records that rebuild this state (a compacted journal).
    pub fn snapshot(&self) -> Vec<Record> {
        let mut out = Vec::new();
        for (drive, d) in &self.drives {
            if let Some(state) = d.brake {
                out.push(Record::Brake {
                    drive: drive.clone(),
                    state,
                });
            }
            if let Some(l) = &d.lease {
                out.push(Record::Lease {
                    drive: drive.clone(),
                    owner: l.owner.clone(),
                    holder: l.holder,
                    deadline_ms: super::format::unix_ms(l.deadline),
                    length_ms: u64::try_from(l.length.as_millis()).unwrap_or(u64::MAX),
                    action: l.action,
                    mode: l.mode,
                });
            }
            if let Some(s) = &d.stop {
                out.push(Record::Stop {
                    drive: drive.clone(),
                    owner: s.owner.clone(),
                    action: s.action,
                    mode: s.mode,
                    ends_lease: false,
                });
            }
        }
        out
    }
}

/// Why what the last process promised is unknown.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Unknown {
    /// The file could not be read (why, and what became of it).
    Unreadable(String),
    /// The file was empty (or held part of its header).
    Empty,
    /// The file ended at its header: no record, not even the snapshot
    /// every journal begins with.
    HeaderOnly,
    /// There was no file, and the state directory shows an earlier run
    /// (what shows it).
    Missing(String),
}

impl Unknown {
    /// "the safety journal was empty at start", for the log and alarms.
    pub fn words(&self) -> String {
        match self {
            Unknown::Unreadable(why) => {
                format!("the safety journal could not be read at start: {why}")
            }
            Unknown::Empty => "the safety journal was empty at start".to_string(),
            Unknown::HeaderOnly => "the safety journal held only its header at start".to_string(),
            Unknown::Missing(evidence) => format!(
                "the safety journal was missing at start, where an earlier run kept one ({evidence})"
            ),
        }
    }

    /// The journal's state in a word or two, for the metrics and the
    /// audit log: `unreadable`, `empty`, `header-only`, `missing`.
    pub fn name(&self) -> &'static str {
        match self {
            Unknown::Unreadable(_) => "unreadable",
            Unknown::Empty => "empty",
            Unknown::HeaderOnly => "header-only",
            Unknown::Missing(_) => "missing",
        }
    }
}

/// What was journaled, as read at start-up.
#[derive(Debug, Clone, PartialEq)]
pub enum Recovered {
    /// Read (a missing journal on a first start is an empty one).
    Read(JournalState),
    /// Only its newest records were read: what the older ones promised is
    /// unknown.
    Tail(JournalState),
    /// Nothing in it can be trusted, and why.
    Unknown(Unknown),
}

impl Recovered {
    /// Some of what the last process promised is unknown: the drives'
    /// motion must be read to decide.
    pub fn has_unknowns(&self) -> bool {
        !matches!(self, Recovered::Read(_))
    }
}

/// A configured drive at start-up.
#[derive(Debug, Clone, PartialEq)]
pub struct DriveAtStart {
    /// Its name.
    pub name: String,
    /// Whether it was found moving (`None`: it did not answer, or it was
    /// not read: nothing needed it).
    pub moving: Option<bool>,
    /// Its speed at its first poll, rpm, for the words.
    pub speed_rpm: Option<i16>,
}

impl DriveAtStart {
    /// A drive found at its first poll: moving or not, at `speed_rpm`.
    pub fn polled(name: &str, moving: bool, speed_rpm: i16) -> Self {
        DriveAtStart {
            name: name.to_string(),
            moving: Some(moving),
            speed_rpm: Some(speed_rpm),
        }
    }

    /// A drive not read (it did not answer, or nothing needed it).
    pub fn unread(name: &str) -> Self {
        DriveAtStart {
            name: name.to_string(),
            moving: None,
            speed_rpm: None,
        }
    }
}

/// Why the journal cannot say what a moving drive is owed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Unsaid {
    /// Its contents are unknown.
    Journal(Unknown),
    /// It was read in part, and its records read do not name the drive.
    Partial,
}

impl Unsaid {
    /// "the safety journal was empty at start", for the log and alarms.
    pub fn words(&self) -> String {
        match self {
            Unsaid::Journal(unknown) => unknown.words(),
            Unsaid::Partial => {
                "the safety journal was read only in part at start (its older records skipped) and what was read does not name the drive".to_string()
            }
        }
    }
}

/// Why a replayed stop is sent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StopWhy {
    /// Its lease's holder was a session, gone with the old process.
    HolderGone(HolderKind),
    /// Its HTTP lease ran out while drivegate was not running.
    RanOut,
    /// The stop was being tried when drivegate stopped.
    Unfinished,
    /// A brake was sent but not confirmed before drivegate stopped.
    BrakeUnconfirmed,
    /// What the journal held is unknown (why) and the drive was moving.
    UnknownState(Unsaid),
}

impl StopWhy {
    /// In words, after "because".
    pub fn words(&self) -> String {
        match self {
            StopWhy::HolderGone(kind) => format!(
                "drivegate restarted and its holder, {}, ended with the old process",
                kind.words()
            ),
            StopWhy::RanOut => "it ran out while drivegate was not running".to_string(),
            StopWhy::Unfinished => {
                "its stop was not confirmed by the drive before drivegate restarted".to_string()
            }
            StopWhy::BrakeUnconfirmed => {
                "a brake was sent but not confirmed by the drive before drivegate restarted"
                    .to_string()
            }
            StopWhy::UnknownState(unsaid) => format!(
                "{}, so who owned the motor is unknown, and the drive was moving",
                unsaid.words()
            ),
        }
    }
}

/// One decision of the replay.
#[derive(Debug, Clone, PartialEq)]
pub enum Replayed {
    /// Send a stop, retried until the drive confirms it.
    Stop {
        /// Who held the lease it ends, if any.
        owner: Option<String>,
        /// What to send.
        action: Action,
        /// The mode to decide on when the drive's cannot be read.
        mode: ModeName,
        /// Why.
        why: StopWhy,
    },
    /// Put an HTTP lease back with the time it has left.
    Keep {
        /// The lease.
        lease: JournaledLease,
        /// Time left.
        left: Duration,
        /// A stop owed before the lease was taken (an older lease's, still
        /// failing when the lease's setpoint was sent), which waits for its
        /// end, as it did in the last process.
        behind: Option<JournaledStop>,
    },
    /// A stop that could release a confirmed brake is not sent.
    BrakeHolds {
        /// Who held the lease, if one was owed a stop.
        owner: Option<String>,
    },
    /// The journal names a drive that is not configured any more.
    NotConfigured,
    /// A drive found moving while what the journal held about it is
    /// unknown, left moving: `[safety] on_unknown_state = "none"`.
    LeftMoving {
        /// Why nothing is known.
        why: Unsaid,
    },
}

/// A decision for one drive.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// The drive's name.
    pub drive: String,
    /// What to do.
    pub what: Replayed,
    /// Its speed at its first poll, rpm, when it was read (only for a
    /// drive found moving while the journal's contents were unknown).
    pub speed_rpm: Option<i16>,
}

impl Decision {
    /// Why nothing is known of the drive, for a decision made on a drive
    /// found moving while the journal could not say (the alarm's words).
    pub fn unsaid(&self) -> Option<&Unsaid> {
        match &self.what {
            Replayed::Stop {
                why: StopWhy::UnknownState(unsaid),
                ..
            }
            | Replayed::LeftMoving { why: unsaid } => Some(unsaid),
            _ => None,
        }
    }
}

/// What a restart does, drive by drive. `on_unknown` is applied to every
/// moving drive when the journal's contents are unknown, and to those its
/// records read do not name when it was read in part; with
/// [`Action::None`] such a drive is left moving, and the decision says so.
pub fn replay(
    journal: &Recovered,
    now: SystemTime,
    drives: &[DriveAtStart],
    on_unknown: Action,
) -> Vec<Decision> {
    let unknown = |why: Unsaid, known: &dyn Fn(&str) -> bool| -> Vec<Decision> {
        drives
            .iter()
            .filter(|d| d.moving == Some(true) && !known(&d.name))
            .map(|d| Decision {
                drive: d.name.clone(),
                what: if on_unknown == Action::None {
                    Replayed::LeftMoving { why: why.clone() }
                } else {
                    Replayed::Stop {
                        owner: None,
                        action: on_unknown,
                        mode: ModeName::Speed,
                        why: StopWhy::UnknownState(why.clone()),
                    }
                },
                speed_rpm: d.speed_rpm,
            })
            .collect()
    };
    let state = match journal {
        Recovered::Read(state) | Recovered::Tail(state) => state,
        Recovered::Unknown(why) => return unknown(Unsaid::Journal(why.clone()), &|_| false),
    };
    let mut out = Vec::new();
    if matches!(journal, Recovered::Tail(_)) {
        out = unknown(Unsaid::Partial, &|name| state.drives.contains_key(name));
    }
    for (name, record) in &state.drives {
        let decision = |what| Decision {
            drive: name.clone(),
            what,
            speed_rpm: None,
        };
        if !drives.iter().any(|d| &d.name == name) {
            out.push(decision(Replayed::NotConfigured));
            continue;
        }
        // What is owed: a stop under way, else the lease's. A stop beside
        // a lease is an older one, which waited for that lease (the
        // records of a stop that ends a lease end it): an HTTP lease with
        // time left comes back with the stop behind it; else the stop is
        // owed now, a brake if either's action was.
        let stop_now = |stop: &JournaledStop, lease: Option<&JournaledLease>| Replayed::Stop {
            owner: stop.owner.clone(),
            action: if lease.is_some_and(|l| l.action == Action::Brake) {
                Action::Brake
            } else {
                stop.action
            },
            mode: stop.mode,
            why: StopWhy::Unfinished,
        };
        let owed = match (&record.stop, &record.lease) {
            (Some(stop), Some(lease)) if lease.holder == HolderKind::Http => {
                match lease.deadline.duration_since(now) {
                    Ok(left) if !left.is_zero() => Some(Replayed::Keep {
                        lease: lease.clone(),
                        left,
                        behind: Some(stop.clone()),
                    }),
                    _ => Some(stop_now(stop, Some(lease))),
                }
            }
            (Some(stop), lease) => Some(stop_now(stop, lease.as_ref())),
            (None, Some(lease)) if lease.holder != HolderKind::Http => Some(Replayed::Stop {
                owner: Some(lease.owner.clone()),
                action: lease.action,
                mode: lease.mode,
                why: StopWhy::HolderGone(lease.holder),
            }),
            (None, Some(lease)) => match lease.deadline.duration_since(now) {
                Ok(left) if !left.is_zero() => Some(Replayed::Keep {
                    lease: lease.clone(),
                    left,
                    behind: None,
                }),
                _ => Some(Replayed::Stop {
                    owner: Some(lease.owner.clone()),
                    action: lease.action,
                    mode: lease.mode,
                    why: StopWhy::RanOut,
                }),
            },
            (None, None) => None,
        };
        let owed = match (record.brake, owed) {
            // A brake that may not have landed is applied again: it
            // releases nothing, and covers any stop owed.
            (Some(BrakeState::Sent), owed) => {
                let owner = match owed {
                    Some(Replayed::Stop { owner, .. }) => owner,
                    Some(Replayed::Keep { lease, .. }) => Some(lease.owner),
                    _ => None,
                };
                Some(Replayed::Stop {
                    owner,
                    action: Action::Brake,
                    mode: ModeName::Speed,
                    why: StopWhy::BrakeUnconfirmed,
                })
            }
            // A confirmed brake holds: a zero speed would release it.
            (
                Some(BrakeState::Confirmed),
                Some(Replayed::Stop {
                    owner,
                    action: Action::ZeroSpeed,
                    ..
                }),
            ) => Some(Replayed::BrakeHolds { owner }),
            (_, owed) => owed,
        };
        if let Some(what) = owed {
            out.push(decision(what));
        }
    }
    out
}

#[cfg(test)]
mod tests;
