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
        // What is owed: a stop under way, else the lease's.
        let owed = match (&record.stop, &record.lease) {
            (Some(stop), _) => Some(Replayed::Stop {
                owner: stop.owner.clone(),
                action: stop.action,
                mode: stop.mode,
                why: StopWhy::Unfinished,
            }),
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
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::control::journal::format::unix_ms;

    const S: Duration = Duration::from_secs(1);

    fn at() -> SystemTime {
        from_unix_ms(1_800_000_000_000)
    }

    fn lease(drive: &str, holder: HolderKind, deadline: SystemTime) -> Record {
        Record::Lease {
            drive: drive.into(),
            owner: "scada".into(),
            holder,
            deadline_ms: unix_ms(deadline),
            length_ms: 1000,
            action: Action::ZeroSpeed,
            mode: ModeName::Speed,
        }
    }

    fn drives(names: &[&str]) -> Vec<DriveAtStart> {
        names
            .iter()
            .map(|n| DriveAtStart::polled(n, true, 150))
            .collect()
    }

    fn run(records: &[Record], now: SystemTime) -> Vec<Decision> {
        replay(
            &Recovered::Read(JournalState::of(records)),
            now,
            &drives(&["conveyor", "lift", "belt"]),
            Action::ZeroSpeed,
        )
    }

    fn stop(owner: Option<&str>, action: Action, why: StopWhy) -> Replayed {
        Replayed::Stop {
            owner: owner.map(str::to_string),
            action,
            mode: ModeName::Speed,
            why,
        }
    }

    #[test]
    fn session_leases_end_with_their_stop_at_once() {
        let later = at() + 60 * S;
        let d = run(
            &[
                lease("conveyor", HolderKind::Session, later),
                lease("lift", HolderKind::CommLoss, later),
            ],
            at(),
        );
        assert_eq!(
            d,
            vec![
                Decision {
                    drive: "conveyor".into(),
                    what: stop(
                        Some("scada"),
                        Action::ZeroSpeed,
                        StopWhy::HolderGone(HolderKind::Session)
                    ),
                    speed_rpm: None,
                },
                Decision {
                    drive: "lift".into(),
                    what: stop(
                        Some("scada"),
                        Action::ZeroSpeed,
                        StopWhy::HolderGone(HolderKind::CommLoss)
                    ),
                    speed_rpm: None,
                },
            ]
        );
    }

    #[test]
    fn an_http_lease_keeps_its_deadline_or_stops_if_it_ran_out() {
        let records = [lease("conveyor", HolderKind::Http, at() + 5 * S)];
        let d = run(&records, at() + 2 * S);
        assert!(
            matches!(&d[..], [Decision { what: Replayed::Keep { left, .. }, .. }] if *left == 3 * S),
            "{d:?}"
        );
        for now in [at() + 5 * S, at() + 60 * S] {
            assert_eq!(
                run(&records, now)[0].what,
                stop(Some("scada"), Action::ZeroSpeed, StopWhy::RanOut)
            );
        }
    }

    #[test]
    fn a_stop_being_tried_is_tried_again() {
        let d = run(
            &[
                lease("conveyor", HolderKind::Http, at() + 60 * S),
                Record::Stop {
                    drive: "conveyor".into(),
                    owner: Some("scada".into()),
                    action: Action::ZeroSpeed,
                    mode: ModeName::Speed,
                    ends_lease: true,
                },
            ],
            at(),
        );
        assert_eq!(
            d[0].what,
            stop(Some("scada"), Action::ZeroSpeed, StopWhy::Unfinished)
        );
        // Confirmed: nothing owed.
        assert!(
            run(
                &[
                    Record::Stop {
                        drive: "conveyor".into(),
                        owner: None,
                        action: Action::ZeroSpeed,
                        mode: ModeName::Speed,
                        ends_lease: true,
                    },
                    Record::StopEnded {
                        drive: "conveyor".into()
                    },
                ],
                at()
            )
            .is_empty()
        );
    }

    #[test]
    fn a_confirmed_brake_gets_no_stop_that_would_release_it() {
        let brake = |state| Record::Brake {
            drive: "lift".into(),
            state,
        };
        // The brake ended the lease: nothing at all.
        let d = run(
            &[
                lease("lift", HolderKind::Session, at()),
                brake(BrakeState::Sent),
                brake(BrakeState::Confirmed),
            ],
            at(),
        );
        assert!(d.is_empty(), "{d:?}");
        // A zero-speed stop recorded after the brake (a stop the brake
        // guard started) is not sent.
        let d = run(
            &[
                brake(BrakeState::Confirmed),
                Record::Stop {
                    drive: "lift".into(),
                    owner: Some("scada".into()),
                    action: Action::ZeroSpeed,
                    mode: ModeName::Speed,
                    ends_lease: false,
                },
            ],
            at(),
        );
        assert_eq!(
            d[0].what,
            Replayed::BrakeHolds {
                owner: Some("scada".into())
            }
        );
        // A leased setpoint after the brake released it: its lease counts.
        let d = run(
            &[
                brake(BrakeState::Confirmed),
                lease("lift", HolderKind::Session, at()),
            ],
            at(),
        );
        assert_eq!(
            d[0].what,
            stop(
                Some("scada"),
                Action::ZeroSpeed,
                StopWhy::HolderGone(HolderKind::Session)
            )
        );
    }

    #[test]
    fn a_brake_never_confirmed_is_applied_again() {
        let d = run(
            &[
                lease("belt", HolderKind::Http, at() + 60 * S),
                Record::Brake {
                    drive: "belt".into(),
                    state: BrakeState::Sent,
                },
            ],
            at(),
        );
        assert_eq!(
            d[0].what,
            stop(Some("scada"), Action::Brake, StopWhy::BrakeUnconfirmed)
        );
    }

    #[test]
    fn unleased_setpoints_ended_leases_and_clean_stops_are_left_alone() {
        assert!(run(&[], at()).is_empty());
        let ended = [
            lease("conveyor", HolderKind::Http, at()),
            Record::LeaseEnded {
                drive: "conveyor".into(),
            },
        ];
        assert!(run(&ended, at() + 60 * S).is_empty());
        let clean = [
            lease("conveyor", HolderKind::Session, at()),
            Record::Shutdown,
        ];
        assert!(run(&clean, at()).is_empty());
    }

    #[test]
    fn a_drive_no_longer_configured_is_named() {
        let d = run(&[lease("old", HolderKind::Session, at())], at());
        assert_eq!(d[0].what, Replayed::NotConfigured);
    }

    #[test]
    fn a_journal_whose_contents_are_unknown_stops_every_moving_drive_with_on_unknown_state() {
        let mut at_start = drives(&["conveyor", "lift", "belt"]);
        at_start[1] = DriveAtStart::polled("lift", false, 0);
        at_start[2] = DriveAtStart::unread("belt");
        for unknown in [
            Unknown::Unreadable("garbage".into()),
            Unknown::Empty,
            Unknown::HeaderOnly,
            Unknown::Missing("its marker is there".into()),
        ] {
            let why = Unsaid::Journal(unknown.clone());
            let d = replay(&Recovered::Unknown(unknown), at(), &at_start, Action::Brake);
            assert_eq!(
                d,
                vec![Decision {
                    drive: "conveyor".into(),
                    what: stop(None, Action::Brake, StopWhy::UnknownState(why.clone())),
                    speed_rpm: Some(150),
                }]
            );
            assert_eq!(d[0].unsaid(), Some(&why));
        }
    }

    #[test]
    fn with_on_unknown_state_none_a_moving_drive_is_left_moving_and_said() {
        let at_start = vec![
            DriveAtStart::polled("belt", true, 150),
            DriveAtStart::polled("lift", false, 0),
        ];
        let d = replay(
            &Recovered::Unknown(Unknown::Empty),
            at(),
            &at_start,
            Action::None,
        );
        let why = Unsaid::Journal(Unknown::Empty);
        assert_eq!(
            d,
            vec![Decision {
                drive: "belt".into(),
                what: Replayed::LeftMoving { why: why.clone() },
                speed_rpm: Some(150),
            }]
        );
        assert_eq!(d[0].unsaid(), Some(&why));
    }

    #[test]
    fn unknown_journals_say_what_was_found() {
        assert_eq!(
            Unknown::Empty.words(),
            "the safety journal was empty at start"
        );
        assert_eq!(
            Unknown::HeaderOnly.words(),
            "the safety journal held only its header at start"
        );
        assert!(
            Unknown::Missing("alarms.journal is there".into())
                .words()
                .contains("(alarms.journal is there)")
        );
        let names: Vec<_> = [
            Unknown::Unreadable(String::new()),
            Unknown::Empty,
            Unknown::HeaderOnly,
            Unknown::Missing(String::new()),
        ]
        .iter()
        .map(Unknown::name)
        .collect();
        assert_eq!(names, ["unreadable", "empty", "header-only", "missing"]);
        let why = StopWhy::UnknownState(Unsaid::Journal(Unknown::Empty)).words();
        assert_eq!(
            why,
            "the safety journal was empty at start, so who owned the motor is unknown, and the drive was moving"
        );
    }

    #[test]
    fn a_journal_read_in_part_stops_the_moving_drives_it_does_not_name() {
        // The records read keep the conveyor's HTTP lease; the lift and
        // the belt move, and what older records said of them is unknown.
        let tail = JournalState::of(&[lease("conveyor", HolderKind::Http, at() + 5 * S)]);
        let mut at_start = drives(&["conveyor", "lift", "belt"]);
        at_start[2].moving = Some(false);
        let d = replay(&Recovered::Tail(tail), at(), &at_start, Action::ZeroSpeed);
        assert_eq!(d.len(), 2, "{d:?}");
        assert_eq!(d[0].drive, "lift");
        assert_eq!(
            d[0].what,
            stop(
                None,
                Action::ZeroSpeed,
                StopWhy::UnknownState(Unsaid::Partial)
            )
        );
        assert_eq!(d[1].drive, "conveyor");
        assert!(matches!(d[1].what, Replayed::Keep { .. }), "{d:?}");
        assert!(Recovered::Tail(JournalState::default()).has_unknowns());
        assert!(Recovered::Unknown(Unknown::Empty).has_unknowns());
        assert!(!Recovered::Read(JournalState::default()).has_unknowns());
    }

    #[test]
    fn a_snapshot_rebuilds_the_same_state() {
        let records = [
            lease("conveyor", HolderKind::Http, at() + 5 * S),
            Record::Brake {
                drive: "lift".into(),
                state: BrakeState::Confirmed,
            },
            Record::Stop {
                drive: "belt".into(),
                owner: None,
                action: Action::Brake,
                mode: ModeName::Torque,
                ends_lease: true,
            },
        ];
        let state = JournalState::of(&records);
        assert_eq!(JournalState::of(&state.snapshot()), state);
    }
}
