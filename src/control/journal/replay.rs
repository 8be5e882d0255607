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
//! - a journal that cannot be read promises nothing that can be trusted:
//!   every configured drive found moving gets `[safety] on_unknown_state`;
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

/// What was journaled, as read at start-up.
#[derive(Debug, Clone, PartialEq)]
pub enum Recovered {
    /// Read (a missing journal is an empty one).
    Read(JournalState),
    /// Only its newest records were read: what the older ones promised is
    /// unknown.
    Tail(JournalState),
    /// Not readable: nothing in it can be trusted.
    Unreadable,
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
    /// Whether it was found moving (`None`: it did not answer).
    pub moving: Option<bool>,
}

/// Why a replayed stop is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopWhy {
    /// Its lease's holder was a session, gone with the old process.
    HolderGone(HolderKind),
    /// Its HTTP lease ran out while drivegate was not running.
    RanOut,
    /// The stop was being tried when drivegate stopped.
    Unfinished,
    /// A brake was sent but not confirmed before drivegate stopped.
    BrakeUnconfirmed,
    /// The journal could not be read and the drive was moving.
    UnknownState,
}

impl StopWhy {
    /// In words, after "because".
    pub fn words(self) -> String {
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
            StopWhy::UnknownState => {
                "what the safety journal held about it could not be read at start-up and the drive was moving"
                    .to_string()
            }
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
}

/// A decision for one drive.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// The drive's name.
    pub drive: String,
    /// What to do.
    pub what: Replayed,
}

/// What a restart does, drive by drive. `on_unknown` is applied to every
/// moving drive when the journal could not be read, and to those its
/// records read do not name when it was read in part.
pub fn replay(
    journal: &Recovered,
    now: SystemTime,
    drives: &[DriveAtStart],
    on_unknown: Action,
) -> Vec<Decision> {
    let unknown = |known: &dyn Fn(&str) -> bool| -> Vec<Decision> {
        drives
            .iter()
            .filter(|d| d.moving == Some(true) && on_unknown != Action::None && !known(&d.name))
            .map(|d| Decision {
                drive: d.name.clone(),
                what: Replayed::Stop {
                    owner: None,
                    action: on_unknown,
                    mode: ModeName::Speed,
                    why: StopWhy::UnknownState,
                },
            })
            .collect()
    };
    let state = match journal {
        Recovered::Read(state) | Recovered::Tail(state) => state,
        Recovered::Unreadable => return unknown(&|_| false),
    };
    let mut out = Vec::new();
    if matches!(journal, Recovered::Tail(_)) {
        out = unknown(&|name| state.drives.contains_key(name));
    }
    for (name, record) in &state.drives {
        let decision = |what| Decision {
            drive: name.clone(),
            what,
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
            .map(|n| DriveAtStart {
                name: (*n).to_string(),
                moving: Some(true),
            })
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
                },
                Decision {
                    drive: "lift".into(),
                    what: stop(
                        Some("scada"),
                        Action::ZeroSpeed,
                        StopWhy::HolderGone(HolderKind::CommLoss)
                    ),
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
    fn an_unreadable_journal_stops_every_moving_drive_with_on_unknown_state() {
        let mut at_start = drives(&["conveyor", "lift", "belt"]);
        at_start[1].moving = Some(false);
        at_start[2].moving = None;
        let d = replay(&Recovered::Unreadable, at(), &at_start, Action::Brake);
        assert_eq!(
            d,
            vec![Decision {
                drive: "conveyor".into(),
                what: stop(None, Action::Brake, StopWhy::UnknownState),
            }]
        );
        assert!(replay(&Recovered::Unreadable, at(), &at_start, Action::None).is_empty());
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
            stop(None, Action::ZeroSpeed, StopWhy::UnknownState)
        );
        assert_eq!(d[1].drive, "conveyor");
        assert!(matches!(d[1].what, Replayed::Keep { .. }), "{d:?}");
        assert!(Recovered::Tail(JournalState::default()).has_unknowns());
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

    #[test]
    fn a_renamed_drive_is_owed_its_lease_under_its_new_name() {
        let later = at() + 60 * S;
        let mut state = JournalState::of(&[
            lease("conveyor", HolderKind::Http, later),
            Record::Brake {
                drive: "lift".into(),
                state: BrakeState::Sent,
            },
        ]);
        for r in state.renamed("conveyor", "belt") {
            state.apply(&r);
        }
        assert!(!state.drives.contains_key("conveyor"));
        assert_eq!(
            state
                .drives
                .get("belt")
                .and_then(|d| d.lease.as_ref())
                .map(|l| l.holder),
            Some(HolderKind::Http)
        );
        // Replayed as the belt's (a configured drive now).
        let d = replay(
            &Recovered::Read(state.clone()),
            later + S,
            &drives(&["belt", "lift"]),
            Action::ZeroSpeed,
        );
        assert!(d.iter().any(|d| d.drive == "belt"), "{d:?}");
        // Its brake moves too; a drive the journal owes nothing moves nothing.
        let moved = state.renamed("lift", "hoist");
        assert_eq!(moved.len(), 2, "{moved:?}");
        assert!(state.renamed("press", "saw").is_empty());
    }
}
