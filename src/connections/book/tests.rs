use std::net::IpAddr;
use std::time::Instant;

use super::*;
use crate::connections::words::{HTTP, MODBUS_TCP, OPCUA_SESSIONS};

fn ip(s: &str) -> IpAddr {
    s.parse().unwrap()
}

const SMALL: Limits = Limits {
    max: 8,
    per_address: None,
};

#[test]
fn tickets_hold_their_place_until_dropped() {
    let book = Book::new(false);
    let l = book.listener(MODBUS_TCP, SMALL);
    let tickets: Vec<Ticket> = (0..7).map(|_| l.admit(ip("127.0.0.1")).unwrap()).collect();
    // The last eighth: the heaviest gives way, another address gets in.
    assert_eq!(l.admit(ip("127.0.0.1")).unwrap_err(), Refused::Heaviest);
    let other = l.admit(ip("127.0.0.2")).unwrap();
    let v = l.view();
    assert_eq!(v.held, 8);
    assert_eq!(v.holders, vec![(ip("127.0.0.1"), 7), (ip("127.0.0.2"), 1)]);
    assert_eq!(
        v.refused
            .iter()
            .find(|(r, _)| *r == Refused::Heaviest)
            .unwrap()
            .1,
        1
    );
    drop(tickets);
    drop(other);
    assert_eq!(l.view().held, 0);
    assert!(book.lock().entries.is_empty());
    assert_eq!(book.lock().process.total(), 0);
}

#[test]
fn a_full_listener_closes_the_quietest_connection_of_the_heaviest_address() {
    let book = Book::new(false);
    let l = book.listener(MODBUS_TCP, SMALL);
    let flood: Vec<Ticket> = (0..7).map(|_| l.admit(ip("127.0.0.66")).unwrap()).collect();
    let light = l.admit(ip("127.0.0.5")).unwrap();
    // All but the third are busy.
    std::thread::sleep(std::time::Duration::from_millis(5));
    for (i, t) in flood.iter().enumerate() {
        if i != 2 {
            t.touch();
        }
    }
    let second = l.admit(ip("127.0.0.5")).unwrap();
    assert!(flood[2].closing().is_cancelled(), "the quietest closed");
    assert_eq!(
        flood.iter().filter(|t| t.closing().is_cancelled()).count(),
        1
    );
    let v = l.view();
    assert_eq!(v.held, 8);
    assert_eq!(v.closed, 1);
    assert_eq!(v.recent[0].address, ip("127.0.0.66"));
    // Its drop does not give back the place twice.
    drop(flood);
    assert_eq!(l.view().held, 2);
    drop((light, second));
    assert_eq!(book.lock().process.total(), 0);
}

#[test]
fn listeners_count_on_their_own_and_the_process_sees_them_all() {
    let book = Book::new(false);
    let a = book.listener(MODBUS_TCP, SMALL);
    let b = book.listener(HTTP, SMALL);
    let _one: Vec<Ticket> = (0..5).map(|_| a.admit(ip("127.0.0.9")).unwrap()).collect();
    let _two: Vec<Ticket> = (0..5).map(|_| b.admit(ip("127.0.0.9")).unwrap()).collect();
    assert_eq!(book.lock().process.held(ip("127.0.0.9")), 10);
    assert_eq!(a.view().held, 5);
    drop(b);
    assert!(book.lock().listeners.len() == 1);
}

#[test]
fn short_of_files_the_heaviest_address_of_the_process_gives_way() {
    let book = Book::new(false);
    let l = book.listener(
        HTTP,
        Limits {
            max: 4096,
            per_address: None,
        },
    );
    let opc = book.listener(
        crate::connections::words::OPCUA,
        Limits {
            max: 4096,
            per_address: None,
        },
    );
    let flood: Vec<Ticket> = (0..100)
        .map(|_| opc.admit(ip("127.0.0.66")).unwrap())
        .collect();
    // 900 open of 1024: the shared reserve.
    book.lock()
        .files
        .counted(Instant::now(), Some(800), 0, Some(1024));
    assert_eq!(
        opc.admit(ip("127.0.0.66")).unwrap_err(),
        Refused::Files,
        "the flood is refused"
    );
    let admin = l.admit(ip("127.0.0.5")).expect("the admin gets in");
    // The last reserve: the admin's next gets in by making room.
    book.lock()
        .files
        .counted(Instant::now(), Some(1000), 101, Some(1024));
    let again = l.admit(ip("127.0.0.5")).expect("by making room");
    assert_eq!(
        flood.iter().filter(|t| t.closing().is_cancelled()).count(),
        1
    );
    assert_eq!(opc.view().closed, 1);
    drop((admin, again, flood));
}

#[test]
fn sessions_are_shared_by_the_same_rule() {
    let book = Book::new(false);
    let s = book.listener(
        OPCUA_SESSIONS,
        Limits {
            max: 20,
            per_address: None,
        },
    );
    let t = Instant::now();
    let flood = Some(ip("127.0.0.66"));
    let mut seats: Vec<Seat> = Vec::new();
    for i in 0..20 {
        let admitted = s.admit_seat(flood, &seats);
        if i < 18 {
            assert_eq!(admitted, Ok(None), "session {i}");
            seats.push(Seat {
                address: flood.map(|a| std::net::SocketAddr::new(a, 4000 + i).ip()),
                active: i % 2 == 0,
                last: t + std::time::Duration::from_millis(u64::from(i)),
            });
        } else {
            assert_eq!(admitted, Err(Refused::Heaviest), "session {i}");
        }
    }
    // The operator from another address gets one.
    assert_eq!(s.admit_seat(Some(ip("127.0.0.5")), &seats), Ok(None));
    seats.push(Seat {
        address: Some(ip("127.0.0.5")),
        active: true,
        last: t,
    });
    seats.push(Seat {
        address: Some(ip("127.0.0.6")),
        active: true,
        last: t,
    });
    // Full: a third address makes room, closing the flood's first
    // session that was never activated.
    assert_eq!(s.admit_seat(Some(ip("127.0.0.7")), &seats), Ok(Some(1)));
    assert_eq!(s.view().closed, 1);
}
