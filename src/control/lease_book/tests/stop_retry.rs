//! A lease's stop, retried until the drive confirms it.

use super::*;
use crate::control::lease_book::stop_retry::backoff;

#[test]
fn an_unrenewed_lease_ends_with_its_stop_and_says_how_it_went() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    assert!(book.tick(t0 + 999 * MS).is_empty());
    let effects = book.tick(t0 + SECOND);
    let orders = stops(&effects);
    assert_eq!(orders.len(), 1);
    let order = orders[0].clone();
    assert_eq!(
        (order.drive, order.action, order.mode, order.attempt),
        (CONVEYOR, StopAction::ZeroSpeed, Mode::Speed, 1)
    );
    assert_eq!(order.owner.as_deref(), Some("scada"));
    assert!(book.lease(CONVEYOR, t0 + SECOND).is_none());
    assert!(
        book.no_lease(CONVEYOR, t0 + SECOND)
            .0
            .contains("is being sent")
    );

    let effects = book.stop_tried(
        CONVEYOR,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + SECOND,
    );
    let news = events(&effects);
    assert_eq!(news.len(), 1);
    let LeaseEvent::Expired {
        reason,
        ok,
        result,
        retrying,
        sent,
        action,
        ..
    } = news[0]
    else {
        panic!("{news:?}");
    };
    assert_eq!(reason, "it was not renewed in time");
    assert_eq!(
        (*ok, *retrying, *action),
        (true, false, StopAction::ZeroSpeed)
    );
    assert_eq!(result, "confirmed by the drive");
    assert_eq!(sent.as_deref(), Some("speed setpoint 0 rpm"));
    let said = book.no_lease(CONVEYOR, t0 + 3 * SECOND).0;
    assert!(
        said.contains("held by scada, ended 2.0 s ago because it was not renewed in time"),
        "{said}"
    );
    assert!(
        said.contains("was carried out: speed setpoint 0 rpm confirmed by the drive"),
        "{said}"
    );
    assert_eq!(book.next_wake(), None);
}

#[test]
fn a_failed_stop_is_retried_with_backoff_until_the_drive_confirms_it() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let first = stops(&book.tick(t1))[0].clone();
    let effects = book.stop_tried(CONVEYOR, first.id, failed(), t1);
    let LeaseEvent::Expired {
        ok,
        retrying,
        result,
        ..
    } = events(&effects)[0]
    else {
        panic!();
    };
    assert_eq!((*ok, *retrying), (false, true));
    assert!(result.contains("did not answer"));
    let said = book.no_lease(CONVEYOR, t1).0;
    assert!(
        said.contains("not confirmed yet: 1 attempt(s) failed") && said.contains("did not answer"),
        "{said}"
    );

    // 250 ms, then 500 ms, then 1 s ...
    assert_eq!(book.next_wake(), Some(t1 + RETRY_FIRST));
    assert!(book.tick(t1 + RETRY_FIRST - MS).is_empty());
    let second = stops(&book.tick(t1 + RETRY_FIRST))[0].clone();
    assert_eq!(second.attempt, 2);
    let said = book.no_lease(CONVEYOR, t1 + RETRY_FIRST).0;
    assert!(
        said.contains("1 attempt(s) failed"),
        "the try under way has not failed: {said}"
    );
    let t2 = t1 + RETRY_FIRST;
    let effects = book.stop_tried(CONVEYOR, second.id, failed(), t2);
    assert!(
        events(&effects).is_empty(),
        "retries are announced only at the end"
    );
    assert_eq!(book.next_wake(), Some(t2 + 2 * RETRY_FIRST));
    let third = stops(&book.tick(t2 + 2 * RETRY_FIRST))[0].clone();
    let t3 = t2 + 2 * RETRY_FIRST;
    let effects = book.stop_tried(CONVEYOR, third.id, confirmed("speed setpoint 0 rpm"), t3);
    let LeaseEvent::StopSettled {
        stopped,
        attempts,
        result,
        ..
    } = events(&effects)[0]
    else {
        panic!();
    };
    assert_eq!((*stopped, *attempts), (true, 3));
    assert_eq!(result, "confirmed by the drive");
    assert!(book.no_lease(CONVEYOR, t3).0.contains("was carried out"));
}

#[test]
fn the_backoff_stops_growing_and_a_link_back_cuts_it_short() {
    assert_eq!(backoff(RETRY_FIRST, RETRY_MAX, 1), RETRY_FIRST);
    assert_eq!(backoff(RETRY_FIRST, RETRY_MAX, 3), 4 * RETRY_FIRST);
    assert_eq!(backoff(RETRY_FIRST, RETRY_MAX, 40), RETRY_MAX);
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let first = stops(&book.tick(t1))[0].clone();
    book.stop_tried(CONVEYOR, first.id, failed(), t1);
    // The bus comes back 10 ms later: the stop goes at once.
    let effects = book.link_back(&[LIFT], t1 + 10 * MS);
    assert!(stops(&effects).is_empty(), "another drive's link");
    let effects = book.link_back(&[CONVEYOR], t1 + 10 * MS);
    assert_eq!(stops(&effects)[0].attempt, 2);
}

#[test]
fn a_setpoint_without_a_lease_takes_over_a_stop_still_being_tried() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(CONVEYOR, order.id, failed(), t1);
    // A PLC writes a speed without a lease; the drive confirms it.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: None,
            mode: Mode::Speed,
        },
        "a setpoint without a lease from 10.0.0.5:4000 over Modbus TCP".into(),
    );
    let effects = book.end_write(&ticket, Applied::Yes, t1 + 10 * MS);
    let LeaseEvent::StopSettled {
        stopped, result, ..
    } = events(&effects)[0]
    else {
        panic!();
    };
    assert!(!stopped);
    assert!(result.contains("not sent again: a setpoint without a lease from 10.0.0.5:4000 over Modbus TCP took over the drive"));
    assert!(stops(&book.tick(t1 + 10 * SECOND)).is_empty());
    assert!(book.no_lease(CONVEYOR, t1).0.contains("is not tried again"));
    // A setpoint whose result is unknown takes nothing over.
    leased(&mut book, LIFT, "scada", SECOND, t0);
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(LIFT, order.id, failed(), t1);
    let ticket = unleased(&mut book, LIFT, Mode::Speed);
    book.end_write(&ticket, Applied::Maybe, t1);
    assert!(book.stopping(LIFT));
    // A setpoint without a lease leaves a lease in place.
    leased(&mut book, CONVEYOR, "scada", SECOND, t1);
    let ticket = unleased(&mut book, CONVEYOR, Mode::Speed);
    book.end_write(&ticket, Applied::Yes, t1);
    assert!(book.lease(CONVEYOR, t1).is_some());
}

#[test]
fn a_setpoint_without_a_lease_of_another_mode_takes_over_no_stop() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    // A lease in speed mode ends; its stop fails.
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    assert_eq!(order.mode, Mode::Speed);
    book.stop_tried(CONVEYOR, order.id, failed(), t1);
    // A torque setpoint without a lease, confirmed: the drive still turns
    // at the ended lease's speed, and the stop goes on.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: None,
            mode: Mode::Torque,
        },
        "a setpoint without a lease from panel over HTTP".into(),
    );
    let effects = book.end_write(&ticket, Applied::Yes, t1 + 10 * MS);
    assert!(events(&effects).is_empty(), "{effects:?}");
    assert!(book.stopping(CONVEYOR));
    let again = book.tick(t1 + 10 * SECOND);
    assert_eq!(stops(&again)[0].attempt, 2);
    assert_eq!(stops(&again)[0].mode, Mode::Speed);
    // A mode command (which releases a brake) takes nothing over either.
    let again = stops(&again)[0].clone();
    book.stop_tried(CONVEYOR, again.id, failed(), t1 + 10 * SECOND);
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::ReleasesBrake { lease: None },
        "x".into(),
    );
    book.end_write(&ticket, Applied::Yes, t1 + 10 * SECOND);
    assert!(book.stopping(CONVEYOR));
    // A speed setpoint sets the motion the stop ends: it takes over.
    let ticket = unleased(&mut book, CONVEYOR, Mode::Speed);
    book.end_write(&ticket, Applied::Yes, t1 + 10 * SECOND);
    assert!(!book.stopping(CONVEYOR));
    // A lease in torque mode: a speed setpoint takes its stop over no more.
    let t2 = t1 + 20 * SECOND;
    let (_, ticket) = leased_write(
        &mut book,
        LIFT,
        ask("panel", Holder::Request, Mode::Torque, SECOND),
        t2,
    );
    book.end_write(&ticket, Applied::Yes, t2);
    let order = stops(&book.tick(t2 + SECOND))[0].clone();
    assert_eq!(order.mode, Mode::Torque);
    book.stop_tried(LIFT, order.id, failed(), t2 + SECOND);
    let ticket = unleased(&mut book, LIFT, Mode::Speed);
    book.end_write(&ticket, Applied::Yes, t2 + SECOND);
    assert!(book.stopping(LIFT));
}

#[test]
fn a_stop_due_waits_while_a_newer_lease_is_on_its_way() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(CONVEYOR, order.id, failed(), t1);
    let (grant, _) = book.grant(
        CONVEYOR,
        ask("panel", Holder::Request, Mode::Speed, SECOND),
        t1,
    );
    assert!(
        stops(&book.tick(t1 + SECOND)).is_empty(),
        "held for the newer lease"
    );
    // Withdrawn (its setpoint surely did not land): the stop goes on.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "x".into(),
    );
    let effects = book.end_write(&ticket, Applied::No, t1 + SECOND);
    assert_eq!(stops(&effects)[0].attempt, 2);
}

#[test]
fn a_leased_setpoint_landing_while_its_stop_is_on_its_way_has_it_sent_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let (_, ticket) = leased_write(
        &mut book,
        CONVEYOR,
        ask("scada", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    let order = stops(&book.tick(t0 + 6 * SECOND))[0].clone();
    book.end_write(&ticket, Applied::Yes, t0 + 6 * SECOND);
    let effects = book.stop_tried(
        CONVEYOR,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + 6 * SECOND,
    );
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].attempt, 2);
}

#[test]
fn the_stop_action_and_the_lease_mode_are_what_the_stop_is_sent_with() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::Brake);
    let (_, ticket) = leased_write(
        &mut book,
        LIFT,
        ask("scada", Holder::Request, Mode::Torque, SECOND),
        t0,
    );
    book.end_write(&ticket, Applied::Yes, t0);
    let order = stops(&book.tick(t0 + SECOND))[0].clone();
    assert_eq!(
        (order.action, order.mode),
        (StopAction::Brake, Mode::Torque)
    );
    assert_eq!(book.action(), StopAction::Brake);
}

#[test]
fn a_replaced_lease_setpoint_landing_after_the_stop_has_the_stop_again() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    // A PLC's setpoint waits on the bus; an operator's lease replaces its
    // lease, and its caller goes away.
    let (_, plc) = leased_write(
        &mut book,
        CONVEYOR,
        ask("plc", Holder::Request, Mode::Speed, SECOND),
        t0,
    );
    let (_, panel) = leased_write(
        &mut book,
        CONVEYOR,
        ask("panel", Holder::Request, Mode::Speed, 100 * MS),
        t0,
    );
    book.end_write(&panel, Applied::Maybe, t0);
    // That lease runs out and its stop is confirmed ...
    let order = stops(&book.tick(t0 + 100 * MS))[0].clone();
    let effects = book.stop_tried(
        CONVEYOR,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + 200 * MS,
    );
    assert!(stops(&effects).is_empty());
    // ... before the PLC's setpoint lands: the stop goes again.
    let effects = book.end_write(&plc, Applied::Yes, t0 + 300 * MS);
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].action, StopAction::ZeroSpeed);
    assert_eq!(again[0].owner.as_deref(), Some("panel"));
}
