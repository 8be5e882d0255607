//! Every transition of the lease book, with time passed in.

use super::*;

mod brake_guard;
mod sessions;
mod stop_retry;

const SECOND: Duration = Duration::from_secs(1);
const MS: Duration = Duration::from_millis(1);
const CONVEYOR: usize = 0;
const LIFT: usize = 1;

fn ask(owner: &str, holder: Holder, mode: Mode, length: Duration) -> LeaseAsk {
    LeaseAsk {
        owner: owner.into(),
        holder,
        mode,
        length,
        allowance: 5 * SECOND,
        action: None,
        comm_loss: false,
    }
}

/// A leased setpoint on `drive`, granted and confirmed at `at`.
/// A lease granted to `ask` at `at`, and its setpoint sent (not settled).
fn leased_write(book: &mut LeaseBook, drive: usize, ask: LeaseAsk, at: Instant) -> (Grant, Ticket) {
    let by = format!("a leased setpoint from {}", ask.owner);
    let (grant, _) = book.grant(drive, ask, at);
    let ticket = book.begin_write(
        drive,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        by.into(),
    );
    (grant, ticket)
}

fn leased(book: &mut LeaseBook, drive: usize, owner: &str, length: Duration, at: Instant) -> Grant {
    let (grant, ticket) = leased_write(
        book,
        drive,
        ask(owner, Holder::Request, Mode::Speed, length),
        at,
    );
    book.end_write(&ticket, Applied::Yes, at);
    grant
}

fn stops(effects: &[Effect]) -> Vec<&StopOrder> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Stop(o) => Some(o),
            Effect::Event(_) | Effect::CommLoss { .. } => None,
        })
        .collect()
}

fn events(effects: &[Effect]) -> Vec<&LeaseEvent> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Event(e) => Some(e),
            Effect::Stop(_) | Effect::CommLoss { .. } => None,
        })
        .collect()
}

fn confirmed(sent: &str) -> StopReport {
    StopReport {
        sent: Some(sent.to_string()),
        result: StopResult::Confirmed,
        released_brake: true,
    }
}

/// A try of a zero-speed stop the drive did not answer.
fn failed() -> StopReport {
    StopReport {
        sent: Some("zero-speed".to_string()),
        result: StopResult::Failed(crate::bus::BusError::Timeout {
            unit: 1,
            attempts: 3,
            timeout_ms: 250,
        }),
        released_brake: false,
    }
}

/// A setpoint of `mode` without a lease begun on `drive`.
fn unleased(book: &mut LeaseBook, drive: usize, mode: Mode) -> Ticket {
    book.begin_write(drive, WriteKind::Setpoint { lease: None, mode }, "x".into())
}

/// A brake (or deactivation) from `by`, settled as `applied` at `at`.
fn stopping_write(
    book: &mut LeaseBook,
    drive: usize,
    kind: WriteKind,
    by: &str,
    applied: Applied,
    at: Instant,
) -> Vec<Effect> {
    let ticket = book.begin_write(drive, kind, by.into());
    book.end_write(&ticket, applied, at)
}

#[test]
fn a_grant_allows_for_the_queue_until_its_setpoint_is_settled() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let (grant, effects) = book.grant(
        CONVEYOR,
        ask("scada", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    assert!(!grant.replaced && effects.is_empty());
    let view = book.lease(CONVEYOR, t0).unwrap();
    assert_eq!((view.id, view.length), (grant.id, SECOND));
    assert_eq!(view.expires_in, 6 * SECOND, "length + allowance");
    assert!(
        book.tick(t0 + 2 * SECOND).is_empty(),
        "no stop while the setpoint waits"
    );

    // Settled: its own deadline from then on.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    book.end_write(&ticket, Applied::Yes, t0 + 2 * SECOND);
    assert_eq!(
        book.lease(CONVEYOR, t0 + 2 * SECOND).unwrap().expires_in,
        SECOND
    );
    assert_eq!(book.next_wake(), Some(t0 + 3 * SECOND));
}

#[test]
fn renewals_push_the_deadline_and_never_cut_a_pending_allowance() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let err = book.renew(CONVEYOR, None, t0).unwrap_err();
    assert!(err.0.contains("none was granted since drivegate started"));

    let (grant, _) = book.grant(
        CONVEYOR,
        ask("scada", Holder::Request, Mode::Speed, 300 * MS),
        t0,
    );
    // Pending: renewing keeps the allowance.
    let view = book.renew(CONVEYOR, None, t0 + 100 * MS).unwrap();
    assert!(view.expires_in > SECOND, "{view:?}");
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    book.end_write(&ticket, Applied::Yes, t0 + 200 * MS);
    // Confirmed: each renewal is a full length from now, or a new length.
    let view = book.renew(CONVEYOR, None, t0 + 400 * MS).unwrap();
    assert_eq!(view.expires_in, 300 * MS);
    let view = book
        .renew(CONVEYOR, Some(2 * SECOND), t0 + 600 * MS)
        .unwrap();
    assert_eq!((view.length, view.expires_in), (2 * SECOND, 2 * SECOND));
    assert!(book.tick(t0 + 2599 * MS).is_empty());
    assert_eq!(stops(&book.tick(t0 + 2600 * MS)).len(), 1);
}

#[test]
fn a_release_ends_the_lease_without_a_stop() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::Brake);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let (view, effects) = book.release(CONVEYOR, &"operator".into(), t0).unwrap();
    assert_eq!(&*view.owner, "scada");
    let LeaseEvent::Ended { reason, owner, .. } = events(&effects)[0] else {
        panic!();
    };
    assert_eq!(
        (&**owner, reason.as_str()),
        ("scada", "released by operator without a stop")
    );
    assert!(book.tick(t0 + 10 * SECOND).is_empty());
    assert!(
        book.no_lease(CONVEYOR, t0)
            .0
            .contains("released by operator without a stop")
    );
    assert!(book.release(CONVEYOR, &"operator".into(), t0).is_err());
}

#[test]
fn a_setpoint_that_surely_did_not_land_takes_its_lease_back() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let (_, ticket) = leased_write(
        &mut book,
        CONVEYOR,
        ask("scada", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    let effects = book.end_write(&ticket, Applied::No, t0);
    assert!(effects.is_empty());
    assert!(book.lease(CONVEYOR, t0).is_none());
    assert!(
        book.tick(t0 + 10 * SECOND).is_empty(),
        "no stop for a withdrawn lease"
    );
}

#[test]
fn a_new_lease_takes_over_and_covers_the_motor_even_if_its_setpoint_fails() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let first = leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let (second, effects) = book.grant(
        CONVEYOR,
        ask("panel", Holder::Request, Mode::Torque, SECOND),
        t0 + 100 * MS,
    );
    assert!(second.replaced && second.id != first.id);
    let LeaseEvent::Ended { owner, reason, .. } = events(&effects)[0] else {
        panic!();
    };
    assert_eq!(
        (&**owner, reason.as_str()),
        ("scada", "replaced by a leased setpoint from panel")
    );
    // Its setpoint is refused: the motor still runs the first one's, so
    // the new lease stays and stops it in time.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: Some(second),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    book.end_write(&ticket, Applied::No, t0 + 100 * MS);
    assert_eq!(&*book.lease(CONVEYOR, t0).unwrap().owner, "panel");
    let order = stops(&book.tick(t0 + 1100 * MS))[0].clone();
    assert_eq!(order.mode, Mode::Torque);
}

#[test]
fn at_shutdown_nothing_more_is_sent() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    leased(&mut book, LIFT, "scada", SECOND, t0);
    let order = stops(&book.tick(t0 + SECOND))
        .into_iter()
        .find(|o| o.drive == LIFT)
        .cloned()
        .unwrap();
    book.shutdown();
    assert!(book.lease(CONVEYOR, t0).is_none());
    assert!(book.tick(t0 + 10 * SECOND).is_empty());
    assert_eq!(book.next_wake(), None);
    let effects = book.stop_tried(LIFT, order.id, failed(), t0 + SECOND);
    assert!(stops(&effects).is_empty());
    let said = book.no_lease(LIFT, t0 + SECOND).0;
    assert!(said.contains("left to the safe stop"), "{said}");
    let ticket = unleased(&mut book, CONVEYOR, Mode::Speed);
    stopping_write(
        &mut book,
        CONVEYOR,
        WriteKind::Brake,
        "the brake",
        Applied::Yes,
        t0,
    );
    assert!(stops(&book.end_write(&ticket, Applied::Yes, t0)).is_empty());
}

#[test]
fn a_lease_may_carry_its_own_stop_action() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let ask = LeaseAsk {
        action: Some(StopAction::Brake),
        ..ask("plc", Holder::Session(SessionId(9)), Mode::Speed, SECOND)
    };
    book.session_opened(SessionId(9), "its connection closed", None);
    let (grant, _) = book.grant(CONVEYOR, ask, t0);
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    book.end_write(&ticket, Applied::Yes, t0);
    let effects = book.session_closed(SessionId(9), t0);
    assert_eq!(stops(&effects)[0].action, StopAction::Brake);
    // Another drive's lease keeps the book's action.
    leased(&mut book, LIFT, "scada", SECOND, t0);
    assert_eq!(
        stops(&book.tick(t0 + SECOND))[0].action,
        StopAction::ZeroSpeed
    );
}

/// A new lease costs the journal one record: it is journaled with its
/// length from the grant, and its confirmation a bus wait later moves the
/// deadline by that wait only, within the horizon.
#[test]
fn a_new_lease_is_journaled_once_with_its_length_from_the_grant() {
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let t0 = Instant::now();
    let lease_notes = |notes: Vec<notes::Note>| -> Vec<Instant> {
        notes
            .into_iter()
            .filter_map(|n| match n {
                notes::Note::Lease { deadline, .. } => Some(deadline),
                _ => None,
            })
            .collect()
    };
    let (_, ticket) = leased_write(
        &mut book,
        CONVEYOR,
        ask("token:scada", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    // Journaled at the grant without the queue's allowance: never later
    // than the deadline the confirmation will promise.
    assert_eq!(lease_notes(book.take_notes()), [t0 + SECOND]);
    book.end_write(&ticket, Applied::Yes, t0 + 20 * MS);
    assert_eq!(lease_notes(book.take_notes()), Vec::<Instant>::new());
    // A confirmation later than half the length writes the new deadline.
    let (_, ticket) = leased_write(
        &mut book,
        LIFT,
        ask("token:scada", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    book.take_notes();
    book.end_write(&ticket, Applied::Yes, t0 + 600 * MS);
    assert_eq!(lease_notes(book.take_notes()), [t0 + 1600 * MS]);
}
