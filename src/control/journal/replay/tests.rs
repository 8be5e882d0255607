//! What a restart owes, rule by rule, with the time passed in.

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

#[test]
fn a_stop_owed_before_an_http_lease_waits_behind_it() {
    // An older lease's stop was failing when the HTTP lease was taken; it
    // waited for that lease, which comes back with it behind.
    let older = Record::Stop {
        drive: "conveyor".into(),
        owner: Some("panel".into()),
        action: Action::ZeroSpeed,
        mode: ModeName::Speed,
        ends_lease: true,
    };
    let records = [
        older.clone(),
        lease("conveyor", HolderKind::Http, at() + 5 * S),
    ];
    let d = run(&records, at() + 2 * S);
    let behind = JournaledStop {
        owner: Some("panel".into()),
        action: Action::ZeroSpeed,
        mode: ModeName::Speed,
    };
    assert!(
        matches!(&d[..], [Decision { what: Replayed::Keep { left, behind: Some(b), .. }, .. }]
            if *left == 3 * S && *b == behind),
        "{d:?}"
    );
    // Run out: the stop is owed now.
    assert_eq!(
        run(&records, at() + 6 * S)[0].what,
        stop(Some("panel"), Action::ZeroSpeed, StopWhy::Unfinished)
    );
    // Beside a session's lease (ended with the old process), the stop is
    // owed now, a brake if the lease's action was.
    let braking = Record::Lease {
        drive: "conveyor".into(),
        owner: "scada".into(),
        holder: HolderKind::CommLoss,
        deadline_ms: unix_ms(at() + 5 * S),
        length_ms: 1000,
        action: Action::Brake,
        mode: ModeName::Speed,
    };
    assert_eq!(
        run(&[older, braking], at())[0].what,
        stop(Some("panel"), Action::Brake, StopWhy::Unfinished)
    );
}
