//! A brake from any face ends a lease, and holds.

use super::*;

#[test]
fn a_brake_or_deactivation_from_any_face_ends_the_lease_and_no_stop_follows() {
    for (kind, by) in [
        (
            WriteKind::Brake,
            "the brake from 10.0.0.5:40000 over Modbus TCP",
        ),
        (WriteKind::Brake, "the brake from operator over HTTP"),
        (
            WriteKind::Brake,
            "the brake from panel over the WebSocket stream",
        ),
        (
            WriteKind::Deactivate,
            "the deactivation from operator over HTTP",
        ),
        (
            WriteKind::Deactivate,
            "the deactivation from 10.0.0.5:40000 over Modbus TCP",
        ),
    ] {
        let t0 = Instant::now();
        let mut book = LeaseBook::new(StopAction::ZeroSpeed);
        leased(&mut book, LIFT, "scada", 1500 * MS, t0);
        let effects = stopping_write(&mut book, LIFT, kind, by, Applied::Yes, t0 + 200 * MS);
        let news = events(&effects);
        let LeaseEvent::Ended {
            owner,
            reason,
            drive,
            ..
        } = news[0]
        else {
            panic!("{news:?}");
        };
        assert_eq!((*drive, &**owner), (LIFT, "scada"));
        assert_eq!(reason, &format!("{by} was confirmed"));
        assert!(book.lease(LIFT, t0).is_none());
        assert_eq!(book.next_wake(), None);
        assert!(
            book.tick(t0 + 10 * SECOND).is_empty(),
            "{by}: a stop after it"
        );
        let said = book.no_lease(LIFT, t0 + SECOND).0;
        assert!(said.contains(&format!("when {by} was confirmed")), "{said}");
    }
}

#[test]
fn a_brake_ends_a_stop_still_being_tried() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, LIFT, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(LIFT, order.id, failed(), t1);
    let effects = stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Yes,
        t1,
    );
    let LeaseEvent::StopSettled { result, .. } = events(&effects)[0] else {
        panic!();
    };
    assert!(result.contains("the brake from plc took over"), "{result}");
    assert!(book.tick(t1 + 10 * SECOND).is_empty());
}

#[test]
fn a_stop_waits_for_a_brake_on_its_way() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, LIFT, "scada", SECOND, t0);
    // The brake is sent just before the lease runs out.
    let ticket = book.begin_write(LIFT, WriteKind::Brake, "the brake from plc".into());
    assert!(
        stops(&book.tick(t0 + SECOND)).is_empty(),
        "a stop overtook the brake"
    );
    // Confirmed: nothing more is sent.
    let effects = book.end_write(&ticket, Applied::Yes, t0 + SECOND + 5 * MS);
    assert!(stops(&effects).is_empty());
    assert!(book.tick(t0 + 10 * SECOND).is_empty());

    // Surely not sent: the stop goes on.
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let ticket = book.begin_write(CONVEYOR, WriteKind::Brake, "the brake from plc".into());
    assert!(stops(&book.tick(t0 + SECOND)).is_empty());
    let effects = book.end_write(&ticket, Applied::No, t0 + SECOND);
    assert_eq!(stops(&effects)[0].action, StopAction::ZeroSpeed);
}

#[test]
fn a_brake_the_drive_did_not_confirm_is_applied_until_it_does() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, LIFT, "scada", 1500 * MS, t0);
    let effects = stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Maybe,
        t0,
    );
    let order = stops(&effects)[0].clone();
    // Never a zero speed: the brake, whatever the configured action.
    assert_eq!((order.action, order.attempt), (StopAction::Brake, 1));
    assert!(book.lease(LIFT, t0).is_none());
    let effects = book.stop_tried(LIFT, order.id, failed(), t0);
    let LeaseEvent::Expired {
        reason,
        action,
        retrying,
        ..
    } = events(&effects)[0]
    else {
        panic!();
    };
    assert_eq!(
        reason,
        "the brake from plc was sent but not confirmed by the drive"
    );
    assert_eq!((*action, *retrying), (StopAction::Brake, true));
    let order = stops(&book.tick(t0 + RETRY_FIRST))[0].clone();
    assert_eq!(order.action, StopAction::Brake);
}

#[test]
fn a_zero_speed_on_its_way_when_a_brake_is_confirmed_has_the_brake_applied_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, LIFT, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    // The brake is confirmed while the zero speed is on its way ...
    stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Yes,
        t1,
    );
    // ... which then lands, after the brake: it released it.
    let effects = book.stop_tried(
        LIFT,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t1 + 2 * MS,
    );
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].action, StopAction::Brake);
    assert_eq!(again[0].owner, None);
    // Confirmed: done.
    let effects = book.stop_tried(
        LIFT,
        again[0].id,
        confirmed("config command brake 5"),
        t1 + 3 * MS,
    );
    assert!(effects.is_empty(), "{effects:?}");
    assert!(book.tick(t1 + 10 * SECOND).is_empty());
}

#[test]
fn a_write_sent_before_a_brake_and_landing_after_it_has_the_brake_applied_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let setpoint = book.begin_write(
        LIFT,
        WriteKind::Setpoint {
            lease: None,
            mode: Mode::Speed,
        },
        "a setpoint without a lease from panel".into(),
    );
    let mode = book.begin_write(
        LIFT,
        WriteKind::ReleasesBrake { lease: None },
        "a write from panel".into(),
    );
    stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Yes,
        t0,
    );
    let effects = book.end_write(&setpoint, Applied::Yes, t0 + MS);
    let order = stops(&effects)[0].clone();
    assert_eq!(order.action, StopAction::Brake);
    // Two writes landing before the brake goes: one brake.
    let other = book.begin_write(
        CONVEYOR,
        WriteKind::ReleasesBrake { lease: None },
        "x".into(),
    );
    let third = book.begin_write(
        CONVEYOR,
        WriteKind::ReleasesBrake { lease: None },
        "x".into(),
    );
    stopping_write(
        &mut book,
        CONVEYOR,
        WriteKind::Brake,
        "the brake",
        Applied::Yes,
        t0,
    );
    book.begin_write(CONVEYOR, WriteKind::Brake, "a brake on its way".into());
    assert!(
        stops(&book.end_write(&other, Applied::Yes, t0)).is_empty(),
        "held by the brake on its way"
    );
    assert!(stops(&book.end_write(&third, Applied::Yes, t0)).is_empty());
    assert!(book.stopping(CONVEYOR));
    // The mode command lands too while that brake is on its way: it may
    // have landed after it, so the brake goes once more.
    let effects = book.end_write(&mode, Applied::Maybe, t0 + 2 * MS);
    let once_more = stops(&effects)[0].clone();
    assert_eq!(once_more.action, StopAction::Brake);
    assert!(
        book.stop_tried(
            LIFT,
            order.id,
            confirmed("config command brake 5"),
            t0 + 3 * MS
        )
        .is_empty()
    );
    book.stop_tried(
        LIFT,
        once_more.id,
        confirmed("config command brake 5"),
        t0 + 3 * MS,
    );
    assert!(!book.stopping(LIFT));
    // A write sent after the brake releases it as asked: nothing follows.
    let after = unleased(&mut book, LIFT, Mode::Speed);
    assert!(stops(&book.end_write(&after, Applied::Yes, t0 + 4 * MS)).is_empty());
    // One that surely did not land neither.
    let before = book.begin_write(
        CONVEYOR,
        WriteKind::ReleasesBrake { lease: None },
        "x".into(),
    );
    stopping_write(
        &mut book,
        CONVEYOR,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Yes,
        t0,
    );
    assert!(stops(&book.end_write(&before, Applied::No, t0)).is_empty());
}

#[test]
fn a_newer_setpoint_takes_over_a_brake_being_applied_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let old = unleased(&mut book, LIFT, Mode::Speed);
    stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from plc",
        Applied::Yes,
        t0,
    );
    // A leased setpoint sent after the brake is on its way ...
    let (grant, _) = book.grant(LIFT, ask("panel", Holder::Request, Mode::Speed, SECOND), t0);
    let newer = book.begin_write(
        LIFT,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    // ... when the old one lands: the brake again waits for the newer lease.
    let effects = book.end_write(&old, Applied::Yes, t0 + MS);
    assert!(stops(&effects).is_empty(), "held by the newer lease");
    assert!(book.stopping(LIFT));
    // The newer one lands: it takes over, the brake is not applied.
    book.end_write(&newer, Applied::Yes, t0 + 2 * MS);
    assert!(!book.stopping(LIFT));
    assert!(stops(&book.tick(t0 + 500 * MS)).is_empty());
    assert!(book.lease(LIFT, t0).is_some());
}

#[test]
fn the_brake_is_applied_again_whichever_result_comes_back_first() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    // A setpoint, then a brake that overtakes it on the bus; the setpoint's
    // result is settled first, the brake's after.
    let setpoint = unleased(&mut book, LIFT, Mode::Speed);
    let brake = book.begin_write(LIFT, WriteKind::Brake, "the brake from plc".into());
    assert!(stops(&book.end_write(&setpoint, Applied::Yes, t0)).is_empty());
    let effects = book.end_write(&brake, Applied::Yes, t0 + MS);
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].action, StopAction::Brake);

    // The same with a brake that was never sent: nothing to apply again.
    let setpoint = unleased(&mut book, CONVEYOR, Mode::Speed);
    let brake = book.begin_write(CONVEYOR, WriteKind::Brake, "the brake from plc".into());
    book.end_write(&setpoint, Applied::Yes, t0);
    assert!(stops(&book.end_write(&brake, Applied::No, t0)).is_empty());
    assert!(!book.stopping(CONVEYOR));

    // A setpoint sent after the brake, settled before it: no brake again.
    let brake = book.begin_write(CONVEYOR, WriteKind::Brake, "the brake from plc".into());
    let after = unleased(&mut book, CONVEYOR, Mode::Speed);
    book.end_write(&after, Applied::Yes, t0);
    assert!(stops(&book.end_write(&brake, Applied::Yes, t0)).is_empty());
}

#[test]
fn a_brake_ends_only_the_leases_granted_before_it_was_sent() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let brake = book.begin_write(LIFT, WriteKind::Brake, "the brake from panel".into());
    let (grant, setpoint) = leased_write(
        &mut book,
        LIFT,
        ask("panel", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    book.take_notes();
    // The brake lands first (emergency), then the setpoint sent after it,
    // which releases it as asked: its lease goes on.
    let effects = book.end_write(&brake, Applied::Yes, t0 + MS);
    assert!(events(&effects).is_empty(), "{effects:?}");
    assert_eq!(book.lease(LIFT, t0 + MS).map(|l| l.id), Some(grant.id));
    // The journal reads the lease after the brake (a confirmed brake ends
    // the leases before it).
    let notes = book.take_notes();
    assert!(
        matches!(
            notes.as_slice(),
            [
                Note::Brake {
                    state: BrakeState::Confirmed,
                    ..
                },
                Note::Lease { .. }
            ]
        ),
        "{notes:?}"
    );
    assert!(stops(&book.end_write(&setpoint, Applied::Yes, t0 + 2 * MS)).is_empty());
    // Its end stops the motor.
    let order = stops(&book.tick(t0 + 2 * MS + SECOND))[0].clone();
    assert_eq!(order.action, StopAction::ZeroSpeed);
    assert_eq!(order.owner.as_deref(), Some("panel"));
}

#[test]
fn a_write_sent_before_a_stop_brake_and_landing_after_it_has_the_brake_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::Brake);
    leased(&mut book, LIFT, "plc", SECOND, t0);
    let setpoint = book.begin_write(
        LIFT,
        WriteKind::Setpoint {
            lease: None,
            mode: Mode::Speed,
        },
        "a setpoint without a lease from panel".into(),
    );
    // The lease ends with a brake, which overtakes the setpoint on the
    // bus (emergency first) ...
    let order = stops(&book.tick(t0 + SECOND))[0].clone();
    assert_eq!(order.action, StopAction::Brake);
    let effects = book.stop_tried(
        LIFT,
        order.id,
        confirmed("config command brake 5"),
        t0 + SECOND + MS,
    );
    assert!(stops(&effects).is_empty(), "{effects:?}");
    // ... and the setpoint lands after it, releasing it: the brake again.
    let again = stops(&book.end_write(&setpoint, Applied::Yes, t0 + SECOND + 2 * MS))
        .into_iter()
        .cloned()
        .collect::<Vec<_>>();
    assert_eq!(again.len(), 1, "{again:?}");
    assert_eq!(
        (again[0].action, again[0].owner.clone()),
        (StopAction::Brake, None)
    );

    // The same when the setpoint lands while the brake is on its way.
    let mut book = LeaseBook::new(StopAction::Brake);
    leased(&mut book, LIFT, "plc", SECOND, t0);
    let setpoint = book.begin_write(
        LIFT,
        WriteKind::Setpoint {
            lease: None,
            mode: Mode::Speed,
        },
        "a setpoint without a lease from panel".into(),
    );
    let order = stops(&book.tick(t0 + SECOND))[0].clone();
    book.end_write(&setpoint, Applied::Yes, t0 + SECOND + MS);
    let effects = book.stop_tried(
        LIFT,
        order.id,
        confirmed("config command brake 5"),
        t0 + SECOND + 2 * MS,
    );
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].action, StopAction::Brake);
}
