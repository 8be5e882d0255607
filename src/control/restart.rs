//! The start-up replay of the safety journal, carried out: before any face
//! takes a client, what the last process owed the motors is put back into
//! the lease book (leases an HTTP client may still renew, stops owed, tried
//! until the drives confirm them), each decision audited with
//! `face="restart"` and counted for the metrics. The decisions themselves
//! are [`super::journal::replay::replay`], a pure function.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use super::journal::format::Action;
use super::journal::replay::{
    self, Decision, DriveAtStart, Recovered, Replayed, StopWhy, Unknown, Unsaid,
};
use super::leases::{self, Leases};
pub use super::news::{DecisionKind, RestartNote};
use crate::bus::cache::Link;
use crate::control::stop_action::{self, StopAction};
use crate::plant::Plant;

/// How long start-up waits for the drives' first statuses when the journal
/// could not be read (only then does it matter which drives move).
const FIRST_STATUS: Duration = Duration::from_secs(5);

/// Replayed decisions by kind, for the metrics.
pub type Counts = BTreeMap<DecisionKind, u64>;

/// The kind of a decision.
pub fn kind(what: &Replayed) -> DecisionKind {
    match what {
        Replayed::Stop { why, .. } => match why {
            StopWhy::HolderGone(_) => DecisionKind::StopHolderGone,
            StopWhy::RanOut => DecisionKind::StopRanOut,
            StopWhy::Unfinished => DecisionKind::StopUnfinished,
            StopWhy::BrakeUnconfirmed => DecisionKind::BrakeAgain,
            StopWhy::UnknownState(Unsaid::Journal(
                Unknown::Empty | Unknown::HeaderOnly | Unknown::Missing(_),
            )) => DecisionKind::StopJournalLost,
            StopWhy::UnknownState(_) => DecisionKind::StopUnknownState,
        },
        Replayed::Keep { .. } => DecisionKind::LeaseKept,
        Replayed::BrakeHolds { .. } => DecisionKind::BrakeHolds,
        Replayed::NotConfigured => DecisionKind::NotConfigured,
        Replayed::LeftMoving { .. } => DecisionKind::UnknownStateLeft,
    }
}

/// Raises the `unknown-state` alarm of a drive (its name) with its text.
pub type Alarm = Arc<dyn Fn(&str, String) + Send + Sync>;

/// Replays `recovered` into the lease book; returns the decisions made.
/// A drive silent at the start whose state is unknown is decided at its
/// first answer, and `alarm` says what was done then.
pub async fn run(
    plant: &Arc<Plant>,
    leases: &Arc<Leases>,
    recovered: &Recovered,
    on_unknown: StopAction,
    alarm: Alarm,
) -> Vec<Decision> {
    let statuses = if recovered.has_unknowns() {
        first_statuses(plant).await
    } else {
        plant
            .now()
            .drives()
            .map(|d| DriveAtStart::unread(&d.name))
            .collect()
    };
    let on_unknown = match on_unknown {
        StopAction::ZeroSpeed => Action::ZeroSpeed,
        StopAction::Brake => Action::Brake,
        StopAction::None => Action::None,
    };
    let decisions = replay::replay(recovered, leases.clock().wall_now(), &statuses, on_unknown);
    let directory = plant.now();
    let index = |name: &str| {
        directory
            .indexed_drives()
            .find(|(_, d)| d.name == name)
            .map(|(i, _)| i)
    };
    leases.with(|book, now: Instant| {
        for d in &decisions {
            super::audit::restart(&note(d, leases.clock().wall_now()));
            let Some(drive) = index(&d.drive) else {
                continue;
            };
            match &d.what {
                Replayed::Stop {
                    owner,
                    action,
                    mode,
                    why,
                } => book.restart_stop(
                    drive,
                    owner.as_deref().map(Arc::from),
                    leases::stop_action(*action),
                    leases::mode(*mode),
                    why.words().into(),
                    now,
                ),
                Replayed::Keep {
                    lease,
                    left,
                    behind,
                } => {
                    book.restore_lease(
                        drive,
                        lease.owner.as_str().into(),
                        lease.length,
                        *left,
                        leases::stop_action(lease.action),
                        leases::mode(lease.mode),
                        now,
                    );
                    // Held while the lease is on the drive, as before.
                    if let Some(stop) = behind {
                        book.restart_stop(
                            drive,
                            stop.owner.as_deref().map(Arc::from),
                            leases::stop_action(stop.action),
                            leases::mode(stop.mode),
                            StopWhy::Unfinished.words().into(),
                            now,
                        );
                    }
                }
                Replayed::BrakeHolds { .. } => book.restore_brake(drive),
                Replayed::NotConfigured | Replayed::LeftMoving { .. } => {}
            }
        }
        ((), book.tick(now))
    });
    // A drive that did not answer, whose journal said nothing to trust:
    // decided at its first answer.
    let unsaid = match recovered {
        Recovered::Read(_) => None,
        Recovered::Tail(_) => Some(Unsaid::Partial),
        Recovered::Unknown(unknown) => Some(Unsaid::Journal(unknown.clone())),
    };
    if let Some(unsaid) = unsaid {
        let vouched = |name: &str| match recovered {
            Recovered::Tail(state) => state.drives.contains_key(name),
            Recovered::Read(_) | Recovered::Unknown(_) => false,
        };
        let why: Arc<str> = StopWhy::UnknownState(unsaid.clone()).words().into();
        let action = leases::stop_action(on_unknown);
        for s in statuses.iter().filter(|s| s.moving.is_none()) {
            if let Some(drive) = index(&s.name)
                && !vouched(&s.name)
            {
                let (alarm, unsaid, name) = (alarm.clone(), unsaid.clone(), s.name.clone());
                let decided = Box::new(move |rpm: i16| {
                    alarm(&name, first_answer_alarm(&unsaid, &name, rpm, action));
                });
                leases.stop_at_first_answer(drive, action, why.clone(), decided);
            }
        }
    }
    decisions
}

/// Each configured drive, moving or not, once it was polled (or the wait
/// ran out: then `None`).
async fn first_statuses(plant: &Plant) -> Vec<DriveAtStart> {
    let deadline = tokio::time::Instant::now() + FIRST_STATUS;
    loop {
        let now = plant.now();
        let seen: Vec<DriveAtStart> = now
            .drives()
            .map(|d| {
                let state = now.handle_of(d).and_then(|h| h.drive(d.unit));
                let known = state.as_ref().is_some_and(|s| s.link != Link::Unknown);
                match state.and_then(|s| s.status).filter(|_| known) {
                    Some(s) => {
                        DriveAtStart::polled(&d.name, stop_action::is_moving(&s), s.speed_rpm)
                    }
                    None => DriveAtStart::unread(&d.name),
                }
            })
            .collect();
        let all = now.drives().all(|d| {
            now.handle_of(d)
                .and_then(|h| h.drive(d.unit))
                .is_some_and(|s| s.link != Link::Unknown)
        });
        if all || tokio::time::Instant::now() >= deadline {
            return seen;
        }
        // The poller's first round: a status per drive, each a few ms.
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The alarm's words for a drive found moving while the journal could not
/// say who owned it (`None` for every other decision): the journal's
/// state, the drive, how it moved and what was done. "the safety journal
/// was empty at start: belt was turning at 150 rpm and was stopped
/// (on_unknown_state = zero-speed)".
pub fn unknown_state_alarm(d: &Decision) -> Option<String> {
    let unsaid = d.unsaid()?;
    let done = match &d.what {
        Replayed::Stop { action, .. } => leases::stop_action(*action),
        _ => StopAction::None,
    };
    Some(format!(
        "{}: {} {} and {}",
        unsaid.words(),
        d.drive,
        how_moving(d.speed_rpm),
        what_was_done(done)
    ))
}

/// The alarm's words for a drive that did not answer at the start while
/// the journal could not say who owned it, found moving at its first
/// answer (at `rpm`) and given `action` then.
pub fn first_answer_alarm(unsaid: &Unsaid, drive: &str, rpm: i16, action: StopAction) -> String {
    format!(
        "{}: {drive} did not answer at the start; at its first answer it {} and {}",
        unsaid.words(),
        how_moving(Some(rpm)),
        what_was_done(action)
    )
}

/// How a drive found moving moved, after its name.
fn how_moving(rpm: Option<i16>) -> String {
    match rpm {
        Some(rpm) if rpm != 0 => format!("was turning at {rpm} rpm"),
        _ => "was holding torque at standstill".to_string(),
    }
}

/// What `on_unknown_state` (`action`) did to a drive found moving.
fn what_was_done(action: StopAction) -> String {
    match action {
        StopAction::Brake => "was braked (on_unknown_state = brake)".to_string(),
        StopAction::None => "was left moving (on_unknown_state = none)".to_string(),
        StopAction::ZeroSpeed => format!("was stopped (on_unknown_state = {})", action.name()),
    }
}

/// `d` in words, decided at `at`.
pub fn note(d: &Decision, at: SystemTime) -> RestartNote {
    let (who, text) = match &d.what {
        Replayed::Stop {
            owner, action, why, ..
        } => (
            owner.clone(),
            format!(
                "a stop ({}) is owed because {}; it is sent and tried until the drive confirms it",
                leases::stop_action(*action).name(),
                why.words()
            ),
        ),
        Replayed::Keep {
            lease,
            left,
            behind,
        } => (
            Some(lease.owner.to_string()),
            format!(
                "the HTTP lease goes on until its deadline ({} ms left); its client may renew it{}",
                left.as_millis(),
                behind.as_ref().map_or_else(String::new, |s| format!(
                    "; the stop ({}) owed before it was taken is sent when it ends, unless something newer takes over the drive",
                    leases::stop_action(s.action).name()
                ))
            ),
        ),
        Replayed::BrakeHolds { owner } => (
            owner.clone(),
            "the drive's last confirmed command was a brake; no stop that would release it is sent"
                .to_string(),
        ),
        Replayed::NotConfigured => (
            None,
            "the safety journal names a drive that is not configured any more; nothing is sent"
                .to_string(),
        ),
        Replayed::LeftMoving { why } => (
            None,
            format!(
                "{}, so who owned the motor is unknown, and the drive was moving; nothing is sent ([safety] on_unknown_state = none)",
                why.words()
            ),
        ),
    };
    RestartNote {
        drive: d.drive.clone(),
        decision: kind(&d.what),
        who,
        text,
        at,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::control::journal::format::ModeName;

    fn moving(what: Replayed, rpm: i16) -> Decision {
        Decision {
            drive: "belt".into(),
            what,
            speed_rpm: Some(rpm),
        }
    }

    #[test]
    fn a_drive_found_moving_with_the_journal_lost_is_an_alarm_in_words() {
        let why = Unsaid::Journal(Unknown::Empty);
        let stopped = moving(
            Replayed::Stop {
                owner: None,
                action: Action::ZeroSpeed,
                mode: ModeName::Speed,
                why: StopWhy::UnknownState(why.clone()),
            },
            150,
        );
        assert_eq!(
            unknown_state_alarm(&stopped).as_deref(),
            Some(
                "the safety journal was empty at start: belt was turning at 150 rpm and was stopped (on_unknown_state = zero-speed)"
            )
        );
        assert_eq!(kind(&stopped.what), DecisionKind::StopJournalLost);
        let braked = moving(
            Replayed::Stop {
                owner: None,
                action: Action::Brake,
                mode: ModeName::Speed,
                why: StopWhy::UnknownState(Unsaid::Journal(Unknown::Unreadable("x".into()))),
            },
            0,
        );
        let text = unknown_state_alarm(&braked).unwrap();
        assert!(
            text.ends_with(
                "belt was holding torque at standstill and was braked (on_unknown_state = brake)"
            ),
            "{text}"
        );
        assert_eq!(kind(&braked.what), DecisionKind::StopUnknownState);
        let left = moving(Replayed::LeftMoving { why }, -80);
        assert_eq!(
            unknown_state_alarm(&left).as_deref(),
            Some(
                "the safety journal was empty at start: belt was turning at -80 rpm and was left moving (on_unknown_state = none)"
            )
        );
        assert_eq!(kind(&left.what), DecisionKind::UnknownStateLeft);
        // Every other decision is no such alarm.
        let kept = moving(Replayed::NotConfigured, 150);
        assert_eq!(unknown_state_alarm(&kept), None);
    }

    #[test]
    fn a_drive_silent_at_the_start_and_moving_at_its_first_answer_is_an_alarm_in_words() {
        let why = Unsaid::Journal(Unknown::Missing("its marker is there".into()));
        let text = first_answer_alarm(&why, "belt", 150, StopAction::ZeroSpeed);
        assert!(
            text.starts_with("the safety journal was missing at start"),
            "{text}"
        );
        assert!(
            text.ends_with(
                ": belt did not answer at the start; at its first answer it was turning at 150 rpm and was stopped (on_unknown_state = zero-speed)"
            ),
            "{text}"
        );
        assert_eq!(
            first_answer_alarm(&Unsaid::Partial, "belt", 0, StopAction::None),
            format!(
                "{}: belt did not answer at the start; at its first answer it was holding torque at standstill and was left moving (on_unknown_state = none)",
                Unsaid::Partial.words()
            )
        );
    }

    #[test]
    fn a_lost_journal_has_its_own_decision_label() {
        for unknown in [
            Unknown::Empty,
            Unknown::HeaderOnly,
            Unknown::Missing("x".into()),
        ] {
            let what = Replayed::Stop {
                owner: None,
                action: Action::ZeroSpeed,
                mode: ModeName::Speed,
                why: StopWhy::UnknownState(Unsaid::Journal(unknown)),
            };
            assert_eq!(kind(&what).name(), "stop-journal-lost");
        }
        let partial = Replayed::Stop {
            owner: None,
            action: Action::ZeroSpeed,
            mode: ModeName::Speed,
            why: StopWhy::UnknownState(Unsaid::Partial),
        };
        assert_eq!(kind(&partial).name(), "stop-unknown-state");
    }
}
