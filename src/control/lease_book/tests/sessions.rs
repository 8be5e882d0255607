//! Sessions and the communication-loss function.

use super::*;

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

/// A Modbus TCP connection with a communication-loss time of `after`.
const PLC: SessionId = SessionId(21);

fn plc_book(after: Duration, action: StopAction) -> LeaseBook {
    let mut book = LeaseBook::new(StopAction::ZeroSpeed);
    book.session_opened(
        PLC,
        "its Modbus TCP connection closed",
        Some(CommLoss {
            after,
            action,
            face: Face::ModbusTcp,
        }),
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
        WriteKind::Setpoint {
            lease: grant,
            mode: Mode::Speed,
        }
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
            Effect::CommLoss { drive, closed, .. } => Some((*drive, *closed)),
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
        result: StopResult::ActionNone,
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
    book.stop_tried(CONVEYOR, order.id, failed(), t0 + 600 * MS);
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
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
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

#[test]
fn a_comm_loss_end_names_the_face_of_the_session_that_held_the_lease() {
    let t0 = Instant::now();
    // The PLC's session is Modbus TCP's; an MQTT session beside it.
    let mut book = plc_book(500 * MS, StopAction::ZeroSpeed);
    let mqtt = SessionId(22);
    book.session_opened(
        mqtt,
        "the MQTT session ended",
        Some(CommLoss {
            after: 500 * MS,
            action: StopAction::ZeroSpeed,
            face: Face::Mqtt,
        }),
    );
    plc_write(&mut book, CONVEYOR, Mode::Speed, true, Applied::Yes, t0);
    let terms = book.terms(Some(mqtt), None, None).unwrap();
    let (grant, _) = book.grant(
        LIFT,
        LeaseAsk {
            action: terms.action,
            comm_loss: terms.comm_loss,
            ..ask(
                "mqtt scada",
                Holder::Session(mqtt),
                Mode::Speed,
                terms.length,
            )
        },
        t0,
    );
    let ticket = book.begin_write(
        LIFT,
        WriteKind::Setpoint {
            lease: Some(grant),
            mode: Mode::Speed,
        },
        "a write from MQTT".into(),
    );
    book.end_write(&ticket, Applied::Yes, t0);
    let faces = |effects: &[Effect]| -> Vec<(usize, bool, Face)> {
        effects
            .iter()
            .filter_map(|e| match e {
                Effect::CommLoss {
                    drive,
                    closed,
                    face,
                } => Some((*drive, *closed, *face)),
                _ => None,
            })
            .collect()
    };
    // The MQTT session ends (its primary host went offline): its lease
    // ends, counted as MQTT's.
    assert_eq!(
        faces(&book.session_closed(mqtt, t0 + 100 * MS)),
        [(LIFT, true, Face::Mqtt)]
    );
    // The PLC falls silent: its lease ends, counted as Modbus TCP's.
    assert_eq!(
        faces(&book.tick(t0 + 600 * MS)),
        [(CONVEYOR, false, Face::ModbusTcp)]
    );
}
