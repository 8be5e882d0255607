//! Every transition of the lease book, with time passed in.

use super::*;

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
    let ticket = book.begin_write(drive, WriteKind::Setpoint { lease: Some(grant) }, by.into());
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
        result: Ok(format!("{sent} confirmed by the drive")),
        released_brake: true,
    }
}

fn failed(error: &str) -> StopReport {
    StopReport {
        sent: Some("zero-speed".to_string()),
        result: Err(error.to_string()),
        released_brake: false,
    }
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
        WriteKind::Setpoint { lease: Some(grant) },
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
    let effects = book.stop_tried(
        CONVEYOR,
        first.id,
        failed("drive at unit 1 did not answer"),
        t1,
    );
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
    let effects = book.stop_tried(CONVEYOR, second.id, failed("bus sim is down"), t2);
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
    book.stop_tried(CONVEYOR, first.id, failed("bus sim is down"), t1);
    // The bus comes back 10 ms later: the stop goes at once.
    let effects = book.link_back(&[LIFT], t1 + 10 * MS);
    assert!(stops(&effects).is_empty(), "another drive's link");
    let effects = book.link_back(&[CONVEYOR], t1 + 10 * MS);
    assert_eq!(stops(&effects)[0].attempt, 2);
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
        WriteKind::Setpoint { lease: Some(grant) },
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
        },
        "x".into(),
    );
    book.end_write(&ticket, Applied::No, t0 + 100 * MS);
    assert_eq!(&*book.lease(CONVEYOR, t0).unwrap().owner, "panel");
    let order = stops(&book.tick(t0 + 1100 * MS))[0].clone();
    assert_eq!(order.mode, Mode::Torque);
}

#[test]
fn a_setpoint_without_a_lease_takes_over_a_stop_still_being_tried() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(CONVEYOR, order.id, failed("no answer"), t1);
    // A PLC writes a speed without a lease; the drive confirms it.
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint { lease: None },
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
    book.stop_tried(LIFT, order.id, failed("no answer"), t1);
    let ticket = book.begin_write(LIFT, WriteKind::Setpoint { lease: None }, "x".into());
    book.end_write(&ticket, Applied::Maybe, t1);
    assert!(book.stopping(LIFT));
    // A setpoint without a lease leaves a lease in place.
    leased(&mut book, CONVEYOR, "scada", SECOND, t1);
    let ticket = book.begin_write(CONVEYOR, WriteKind::Setpoint { lease: None }, "x".into());
    book.end_write(&ticket, Applied::Yes, t1);
    assert!(book.lease(CONVEYOR, t1).is_some());
}

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
    book.stop_tried(LIFT, order.id, failed("no answer"), t1);
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
    let effects = book.stop_tried(LIFT, order.id, failed("no answer"), t0);
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
        WriteKind::Setpoint { lease: None },
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
    let after = book.begin_write(LIFT, WriteKind::Setpoint { lease: None }, "x".into());
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
    let old = book.begin_write(LIFT, WriteKind::Setpoint { lease: None }, "x".into());
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
    let newer = book.begin_write(LIFT, WriteKind::Setpoint { lease: Some(grant) }, "x".into());
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
fn a_stop_due_waits_while_a_newer_lease_is_on_its_way() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    leased(&mut book, CONVEYOR, "scada", SECOND, t0);
    let t1 = t0 + SECOND;
    let order = stops(&book.tick(t1))[0].clone();
    book.stop_tried(CONVEYOR, order.id, failed("no answer"), t1);
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
        WriteKind::Setpoint { lease: Some(grant) },
        "x".into(),
    );
    let effects = book.end_write(&ticket, Applied::No, t1 + SECOND);
    assert_eq!(stops(&effects)[0].attempt, 2);
}

#[test]
fn a_session_closing_ends_its_leases_with_their_stop() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let session = SessionId(7);
    book.session_opened(session, "its WebSocket closed", None);
    let (_, ticket) = leased_write(
        &mut book,
        CONVEYOR,
        ask("panel", Holder::Session(session), Mode::Speed, 60 * SECOND),
        t0,
    );
    book.end_write(&ticket, Applied::Yes, t0);
    leased(&mut book, LIFT, "scada", 60 * SECOND, t0);
    let effects = book.session_closed(session, t0 + SECOND);
    let orders = stops(&effects);
    assert_eq!(orders.len(), 1);
    assert_eq!(orders[0].drive, CONVEYOR);
    let effects = book.stop_tried(
        CONVEYOR,
        orders[0].id,
        confirmed("speed setpoint 0 rpm"),
        t0 + SECOND,
    );
    let LeaseEvent::Expired { reason, holder, .. } = events(&effects)[0] else {
        panic!();
    };
    assert_eq!(
        (reason.as_str(), *holder),
        ("its WebSocket closed", Holder::Session(session))
    );
    assert!(
        book.lease(LIFT, t0).is_some(),
        "another holder's lease stays"
    );
}

#[test]
fn a_setpoint_settled_after_its_session_closed_ends_at_once() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    let session = SessionId(8);
    book.session_opened(session, "its WebSocket closed", None);
    let (_, ticket) = leased_write(
        &mut book,
        CONVEYOR,
        ask("panel", Holder::Session(session), Mode::Speed, 60 * SECOND),
        t0,
    );
    // Closed while the setpoint is queued: the lease ends with its stop ...
    let effects = book.session_closed(session, t0);
    let first = stops(&effects)[0].clone();
    book.stop_tried(
        CONVEYOR,
        first.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + MS,
    );
    // ... and the setpoint lands after it: the stop is sent again.
    let effects = book.end_write(&ticket, Applied::Maybe, t0 + 2 * MS);
    let again = stops(&effects);
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].action, StopAction::ZeroSpeed);
    // Its end was published already: only how the stop ended follows.
    let effects = book.stop_tried(
        CONVEYOR,
        again[0].id,
        confirmed("speed setpoint 0 rpm"),
        t0 + 3 * MS,
    );
    assert!(matches!(
        events(&effects)[0],
        LeaseEvent::StopSettled { stopped: true, .. }
    ));
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
    let effects = book.stop_tried(
        LIFT,
        order.id,
        failed("the daemon is shutting down"),
        t0 + SECOND,
    );
    assert!(stops(&effects).is_empty());
    let said = book.no_lease(LIFT, t0 + SECOND).0;
    assert!(said.contains("left to the safe stop"), "{said}");
    let ticket = book.begin_write(CONVEYOR, WriteKind::Setpoint { lease: None }, "x".into());
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
fn the_brake_is_applied_again_whichever_result_comes_back_first() {
    let t0 = Instant::now();
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    // A setpoint, then a brake that overtakes it on the bus; the setpoint's
    // result is settled first, the brake's after.
    let setpoint = book.begin_write(LIFT, WriteKind::Setpoint { lease: None }, "x".into());
    let brake = book.begin_write(LIFT, WriteKind::Brake, "the brake from plc".into());
    assert!(stops(&book.end_write(&setpoint, Applied::Yes, t0)).is_empty());
    let effects = book.end_write(&brake, Applied::Yes, t0 + MS);
    let again = stops(&effects);
    assert_eq!(again.len(), 1, "{effects:?}");
    assert_eq!(again[0].action, StopAction::Brake);

    // The same with a brake that was never sent: nothing to apply again.
    let setpoint = book.begin_write(CONVEYOR, WriteKind::Setpoint { lease: None }, "x".into());
    let brake = book.begin_write(CONVEYOR, WriteKind::Brake, "the brake from plc".into());
    book.end_write(&setpoint, Applied::Yes, t0);
    assert!(stops(&book.end_write(&brake, Applied::No, t0)).is_empty());
    assert!(!book.stopping(CONVEYOR));

    // A setpoint sent after the brake, settled before it: no brake again.
    let brake = book.begin_write(CONVEYOR, WriteKind::Brake, "the brake from plc".into());
    let after = book.begin_write(CONVEYOR, WriteKind::Setpoint { lease: None }, "x".into());
    book.end_write(&after, Applied::Yes, t0);
    assert!(stops(&book.end_write(&brake, Applied::Yes, t0)).is_empty());
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
        WriteKind::Setpoint { lease: Some(grant) },
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

/// A Modbus TCP connection with a communication-loss time of `after`.
const PLC: SessionId = SessionId(21);

fn plc_book(after: Duration, action: StopAction) -> LeaseBook {
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    book.session_opened(
        PLC,
        "its Modbus TCP connection closed",
        Some(CommLoss { after, action }),
    );
    book
}

/// A write of `kind` from the PLC on `drive`, with the lease the book's
/// terms give it, settled as `applied` at `at`.
fn plc_write(
    book: &mut LeaseBook,
    drive: usize,
    mode: Mode,
    setpoint: bool,
    applied: Applied,
    at: Instant,
) -> (Option<Grant>, Vec<Effect>) {
    let terms = book.terms(Some(PLC), None, None);
    let mut effects = Vec::new();
    let grant = terms.map(|t| {
        let (grant, e) = book.grant(
            drive,
            LeaseAsk {
                action: t.action,
                comm_loss: t.comm_loss,
                ..ask(
                    "modbus-tcp 127.0.0.1:50412",
                    Holder::Session(PLC),
                    mode,
                    t.length,
                )
            },
            at,
        );
        effects.extend(e);
        grant
    });
    let kind = if setpoint {
        WriteKind::Setpoint { lease: grant }
    } else {
        WriteKind::ReleasesBrake { lease: grant }
    };
    let ticket = book.begin_write(drive, kind, "a write from plc".into());
    effects.extend(book.end_write(&ticket, applied, at));
    (grant, effects)
}

fn comm_losses(effects: &[Effect]) -> Vec<(usize, bool)> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::CommLoss { drive, closed } => Some((*drive, *closed)),
            _ => None,
        })
        .collect()
}

#[test]
fn a_session_without_a_comm_loss_time_takes_no_lease() {
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    book.session_opened(PLC, "its Modbus TCP connection closed", None);
    assert_eq!(book.terms(Some(PLC), None, None), None);
    assert_eq!(book.terms(None, None, None), None, "no session, no lease");
    assert_eq!(
        book.terms(Some(SessionId(99)), None, None),
        None,
        "a session the book does not know"
    );
    // A lease asked for explicitly is granted as asked, in any session.
    assert_eq!(
        book.terms(Some(PLC), Some(SECOND), Some(StopAction::Brake)),
        Some(Terms {
            length: SECOND,
            action: Some(StopAction::Brake),
            comm_loss: false
        })
    );
    let t0 = Instant::now();
    let (grant, effects) = plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    assert!(grant.is_none() && effects.is_empty());
    assert!(book.lease(CONVEYOR, t0).is_none());
    assert!(book.session_closed(PLC, t0 + 60 * SECOND).is_empty());
    assert!(book.tick(t0 + 3600 * SECOND).is_empty(), "nothing happens");
}

#[test]
fn a_comm_loss_lease_is_renewed_by_any_request_of_its_session() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    let terms = book.terms(Some(PLC), None, None).unwrap();
    assert_eq!(
        terms,
        Terms {
            length: 500 * MS,
            action: Some(StopAction::ZeroSpeed),
            comm_loss: true
        }
    );
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    let view = book.lease(CONVEYOR, t0).unwrap();
    assert!(view.comm_loss);
    assert_eq!(view.owner.as_ref(), "modbus-tcp 127.0.0.1:50412");
    assert_eq!((view.length, view.expires_in), (500 * MS, 500 * MS));
    // Reads every 100 ms for ten times the time: never a stop.
    for i in 1..=50u32 {
        let at = t0 + i * 100 * MS;
        assert!(book.tick(at).is_empty(), "stopped at poll {i}");
        book.session_active(PLC, at);
    }
    assert_eq!(
        book.lease(CONVEYOR, t0 + 5 * SECOND).unwrap().expires_in,
        500 * MS
    );
    // Another session's activity renews nothing.
    book.session_active(SessionId(77), t0 + 5300 * MS);
    assert_eq!(book.next_wake(), Some(t0 + 5500 * MS));
}

#[test]
fn silence_for_the_comm_loss_time_ends_the_lease_with_its_action() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::Brake);
    plc_write(&mut book, LIFT, Mode::Torque, true, Applied::Yes, t0);
    book.session_active(PLC, t0 + 200 * MS);
    assert!(book.tick(t0 + 699 * MS).is_empty());
    let effects = book.tick(t0 + 700 * MS);
    assert_eq!(comm_losses(&effects), vec![(LIFT, false)]);
    let order = stops(&effects)[0].clone();
    assert_eq!(
        (order.action, order.mode, order.owner.as_deref()),
        (
            StopAction::Brake,
            Mode::Torque,
            Some("modbus-tcp 127.0.0.1:50412")
        )
    );
    let effects = book.stop_tried(
        LIFT,
        order.id,
        confirmed("config command brake 5"),
        t0 + 710 * MS,
    );
    let LeaseEvent::Expired { reason, action, .. } = events(&effects)[0] else {
        panic!("{effects:?}");
    };
    assert_eq!(
        reason,
        "communication was lost: no request came on its connection for 500 ms"
    );
    assert_eq!(*action, StopAction::Brake);
    // A request after the loss renews nothing: the motor stays stopped
    // until the client writes again, and the loss is counted once.
    book.session_active(PLC, t0 + 800 * MS);
    assert!(book.lease(LIFT, t0 + 800 * MS).is_none());
    assert!(comm_losses(&book.tick(t0 + 10 * SECOND)).is_empty());
    let said = book.no_lease(LIFT, t0 + SECOND).0;
    assert!(said.contains("communication was lost"), "{said}");
}

#[test]
fn the_connection_closing_ends_the_lease_at_once() {
    let t0 = Instant::now();
    let mut book = plc_book(10 * SECOND, StopAction::ZeroSpeed);
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    let effects = book.session_closed(PLC, t0 + 100 * MS);
    assert_eq!(comm_losses(&effects), vec![(CONVEYOR, true)]);
    let order = stops(&effects)[0].clone();
    assert_eq!(order.action, StopAction::ZeroSpeed);
    let effects = book.stop_tried(
        CONVEYOR,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + 110 * MS,
    );
    let LeaseEvent::Expired { reason, .. } = events(&effects)[0] else {
        panic!("{effects:?}");
    };
    assert_eq!(reason, "its Modbus TCP connection closed");
}

#[test]
fn action_none_shows_and_counts_the_loss_and_sends_nothing_else() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::None);
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    assert_eq!(
        book.lease(CONVEYOR, t0).unwrap().action,
        StopAction::None,
        "shown with its action"
    );
    let effects = book.tick(t0 + 500 * MS);
    assert_eq!(comm_losses(&effects), vec![(CONVEYOR, false)]);
    // The driver sends nothing for "none" and reports so.
    let order = stops(&effects)[0].clone();
    assert_eq!(order.action, StopAction::None);
    let report = StopReport {
        sent: None,
        result: Ok("the lease's action is \"none\": nothing sent".to_string()),
        released_brake: false,
    };
    let effects = book.stop_tried(CONVEYOR, order.id, report, t0 + 510 * MS);
    let LeaseEvent::Expired {
        action, sent, ok, ..
    } = events(&effects)[0]
    else {
        panic!("{effects:?}");
    };
    assert_eq!((*action, sent, *ok), (StopAction::None, &None, true));
    let said = book.no_lease(CONVEYOR, t0 + SECOND).0;
    assert!(
        said.contains("its stop (none) was carried out: the lease's action is \"none\""),
        "{said}"
    );
}

#[test]
fn a_mode_command_takes_a_comm_loss_lease_and_never_takes_over_a_stop() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    // The lease of a setpoint ends and its stop fails.
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    let order = stops(&book.tick(t0 + 500 * MS))[0].clone();
    book.stop_tried(CONVEYOR, order.id, failed("timeout"), t0 + 600 * MS);
    // The client comes back with a mode command: it takes a lease ...
    let (grant, _) = plc_write(
        &mut book,
        CONVEYOR,
        Mode::Torque,
        false,
        Applied::Yes,
        t0 + 700 * MS,
    );
    assert!(grant.is_some());
    let view = book.lease(CONVEYOR, t0 + 700 * MS).unwrap();
    assert!(view.comm_loss && view.expires_in == 500 * MS);
    // ... but the stop of the old lease goes on: a mode sets no speed.
    assert!(book.stopping(CONVEYOR));
    // A mode command without communication loss takes no lease.
    let mut plain = LeaseBook::new(StopAction::ZeroSpeed);
    let ticket = plain.begin_write(LIFT, WriteKind::ReleasesBrake { lease: None }, "x".into());
    plain.end_write(&ticket, Applied::Yes, t0);
    assert!(plain.lease(LIFT, t0).is_none());
}

#[test]
fn a_client_writing_its_setpoint_each_cycle_keeps_one_quiet_lease() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    for i in 1..=10u32 {
        let (_, effects) = plc_write(
            &mut book,
            CONVEYOR,
            Mode::Speed,
            true,
            Applied::Yes,
            t0 + i * 100 * MS,
        );
        assert!(events(&effects).is_empty(), "{effects:?}");
    }
    assert_eq!(
        book.next_wake(),
        Some(t0 + 1500 * MS),
        "the last write's time"
    );
}

#[test]
fn a_brake_from_any_face_ends_a_comm_loss_lease_and_no_stop_follows() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    plc_write(&mut book, LIFT, Mode::Torque, true, Applied::Yes, t0);
    let effects = stopping_write(
        &mut book,
        LIFT,
        WriteKind::Brake,
        "the brake from operator over HTTP",
        Applied::Yes,
        t0 + 100 * MS,
    );
    let LeaseEvent::Ended { reason, owner, .. } = events(&effects)[0] else {
        panic!("{effects:?}");
    };
    assert_eq!(owner.as_ref(), "modbus-tcp 127.0.0.1:50412");
    assert_eq!(reason, "the brake from operator over HTTP was confirmed");
    // Neither silence nor the close sends anything after the brake.
    assert!(book.tick(t0 + 10 * SECOND).is_empty());
    assert!(book.session_closed(PLC, t0 + 11 * SECOND).is_empty());
    assert!(!book.stopping(LIFT));
}

#[test]
fn a_leased_setpoint_from_another_face_takes_over_a_comm_loss_lease() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::Brake);
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    let (_, effects) = book.grant(
        CONVEYOR,
        ask("operator", Holder::Request, Mode::Speed, 5 * SECOND),
        t0 + 100 * MS,
    );
    let LeaseEvent::Ended { reason, .. } = events(&effects)[0] else {
        panic!("{effects:?}");
    };
    assert_eq!(reason, "replaced by a leased setpoint from operator");
    // The client's silence and its close end nothing now.
    assert!(book.tick(t0 + 700 * MS).is_empty());
    assert!(book.session_closed(PLC, t0 + 800 * MS).is_empty());
    let view = book.lease(CONVEYOR, t0 + 800 * MS).unwrap();
    assert!(!view.comm_loss && view.owner.as_ref() == "operator");
    assert_eq!(view.action, StopAction::ZeroSpeed, "the book's action");
}

#[test]
fn a_broadcast_setpoint_settled_after_the_close_ends_its_lease_and_counts() {
    let t0 = Instant::now();
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    let terms = book.terms(Some(PLC), None, None).unwrap();
    let (grant, _) = book.grant(
        CONVEYOR,
        LeaseAsk {
            comm_loss: true,
            action: terms.action,
            ..ask("plc", Holder::Session(PLC), Mode::Speed, terms.length)
        },
        t0,
    );
    let ticket = book.begin_write(
        CONVEYOR,
        WriteKind::Setpoint { lease: Some(grant) },
        "x".into(),
    );
    // Closed while the setpoint waits: the lease ends with its stop then.
    let effects = book.session_closed(PLC, t0 + MS);
    assert_eq!(comm_losses(&effects), vec![(CONVEYOR, true)]);
    let order = stops(&effects)[0].clone();
    book.stop_tried(
        CONVEYOR,
        order.id,
        confirmed("speed setpoint 0 rpm"),
        t0 + 2 * MS,
    );
    // The setpoint lands after: the stop goes again, not counted twice.
    let effects = book.end_write(&ticket, Applied::Maybe, t0 + 3 * MS);
    assert_eq!(stops(&effects).len(), 1);
    assert!(comm_losses(&effects).is_empty());
}
