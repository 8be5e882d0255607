use super::*;

fn ip(s: &str) -> IpAddr {
    s.parse().unwrap()
}

fn tally(of: &[(&str, usize)]) -> Tally {
    let mut t = Tally::default();
    for (a, n) in of {
        for _ in 0..*n {
            t.add(ip(a));
        }
    }
    t
}

const OPEN: Limits = Limits {
    max: 96,
    per_address: None,
};

#[test]
fn a_tally_knows_the_heaviest_other_address() {
    let mut t = tally(&[("10.0.0.1", 5), ("10.0.0.2", 3), ("10.0.0.3", 5)]);
    assert_eq!(t.total(), 13);
    assert_eq!(t.heaviest_other(ip("10.0.0.1")), 5, "a tie");
    assert_eq!(t.heaviest_other(ip("10.0.0.2")), 5);
    assert_eq!(t.heaviest_other(ip("10.0.0.9")), 5);
    t.remove(ip("10.0.0.3"));
    assert_eq!(t.heaviest_other(ip("10.0.0.1")), 4);
    assert_eq!(t.heaviest(), Some((ip("10.0.0.1"), 5)));
    for _ in 0..4 {
        t.remove(ip("10.0.0.3"));
    }
    t.remove(ip("10.0.0.3"));
    assert_eq!(t.heaviest_other(ip("10.0.0.1")), 3);
    assert_eq!(t.addresses(), 2);
    assert_eq!(
        t.by_weight(),
        vec![(ip("10.0.0.1"), 5), (ip("10.0.0.2"), 3)]
    );
    assert_eq!(Tally::default().heaviest_other(ip("10.0.0.1")), 0);
}

#[test]
fn an_address_shares_every_free_slot_while_there_is_room() {
    // A SCADA with a connection per drive: 32 from one address, and more.
    let mut t = Tally::default();
    let p = Tally::default();
    let scada = ip("10.0.0.5");
    for _ in 0..84 {
        assert_eq!(judge(OPEN, &t, &p, Files::Plenty, scada), Verdict::Admit);
        t.add(scada);
    }
    // The last eighth is kept for the others.
    assert_eq!(
        judge(OPEN, &t, &p, Files::Plenty, scada),
        Verdict::Refuse(Refused::Heaviest)
    );
    assert_eq!(
        judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.6")),
        Verdict::Admit
    );
}

#[test]
fn near_the_limit_the_heaviest_address_gives_way_first() {
    // 32 from the SCADA, then a flood of idle sockets from another host.
    let scada = ip("10.0.0.5");
    let flood = ip("10.0.0.66");
    let p = Tally::default();
    let mut t = tally(&[("10.0.0.5", 32)]);
    let mut admitted = 0;
    let mut refused = 0;
    for _ in 0..300 {
        match judge(OPEN, &t, &p, Files::Plenty, flood) {
            Verdict::Admit => {
                t.add(flood);
                admitted += 1;
            }
            Verdict::Refuse(Refused::Heaviest) => refused += 1,
            other => panic!("{other:?}"),
        }
    }
    assert_eq!((admitted, refused), (52, 248));
    // The SCADA and a third address still get in, up to the limit.
    assert_eq!(judge(OPEN, &t, &p, Files::Plenty, scada), Verdict::Admit);
    assert_eq!(
        judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.7")),
        Verdict::Admit
    );
}

#[test]
fn a_full_listener_closes_a_connection_of_the_heaviest_for_a_lighter_address() {
    let p = Tally::default();
    // The flood came first and holds all but the SCADA's few.
    let mut t = tally(&[("10.0.0.66", 90), ("10.0.0.5", 6)]);
    assert_eq!(t.total(), 96);
    let v = judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.5"));
    assert_eq!(v, Verdict::MakeRoom(Room::Listener(ip("10.0.0.66"))));
    // The flood itself is refused.
    assert_eq!(
        judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.66")),
        Verdict::Refuse(Refused::Limit)
    );
    // Until the shares meet: then a full listener is full.
    t = tally(&[("10.0.0.66", 49), ("10.0.0.5", 47)]);
    assert!(matches!(
        judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.5")),
        Verdict::MakeRoom(_)
    ));
    t = tally(&[("10.0.0.66", 48), ("10.0.0.5", 48)]);
    assert_eq!(
        judge(OPEN, &t, &p, Files::Plenty, ip("10.0.0.5")),
        Verdict::Refuse(Refused::Limit)
    );
    // Every address with one: nobody gives way.
    let mut many = Tally::default();
    for i in 0..96u32 {
        many.add(IpAddr::from((0x0A00_0000 + i).to_be_bytes()));
    }
    assert_eq!(
        judge(OPEN, &many, &p, Files::Plenty, ip("192.168.1.1")),
        Verdict::Refuse(Refused::Limit)
    );
}

#[test]
fn a_hard_cap_per_address_is_applied_first() {
    let capped = Limits {
        max: 96,
        per_address: Some(16),
    };
    let p = Tally::default();
    let t = tally(&[("10.0.0.5", 16)]);
    assert_eq!(
        judge(capped, &t, &p, Files::Plenty, ip("10.0.0.5")),
        Verdict::Refuse(Refused::PerAddress)
    );
    assert_eq!(
        judge(capped, &t, &p, Files::Plenty, ip("10.0.0.6")),
        Verdict::Admit
    );
}

#[test]
fn short_of_files_the_heaviest_address_of_the_process_is_refused() {
    // This listener holds little; the process's heaviest is elsewhere
    // (a flood of OPC UA channels), and it is the flood that gives way.
    let t = tally(&[("10.0.0.9", 1)]);
    let p = tally(&[("10.0.0.66", 800), ("10.0.0.9", 1), ("10.0.0.5", 32)]);
    assert_eq!(
        judge(OPEN, &t, &p, Files::Short, ip("10.0.0.9")),
        Verdict::Admit
    );
    assert_eq!(
        judge(OPEN, &t, &p, Files::Short, ip("10.0.0.7")),
        Verdict::Admit
    );
    assert_eq!(
        judge(OPEN, &t, &p, Files::Short, ip("10.0.0.66")),
        Verdict::Refuse(Refused::Files)
    );
    // At the last reserve a lighter address gets in by making room...
    assert_eq!(
        judge(OPEN, &t, &p, Files::Exhausted, ip("10.0.0.7")),
        Verdict::MakeRoom(Room::Process(ip("10.0.0.66")))
    );
    // ... and the heaviest does not.
    assert_eq!(
        judge(OPEN, &t, &p, Files::Exhausted, ip("10.0.0.66")),
        Verdict::Refuse(Refused::Files)
    );
    // With nobody to give way, nobody gets in.
    let alone = tally(&[("10.0.0.9", 1)]);
    assert_eq!(
        judge(OPEN, &alone, &alone, Files::Exhausted, ip("10.0.0.7")),
        Verdict::Refuse(Refused::Files)
    );
    // An address that holds nothing is admitted while files are short,
    // even when nobody else holds anything either.
    let empty = Tally::default();
    assert_eq!(
        judge(OPEN, &empty, &empty, Files::Short, ip("10.0.0.7")),
        Verdict::Admit
    );
}

#[test]
fn making_room_on_the_listener_wins_over_the_process() {
    let t = tally(&[("10.0.0.66", 90), ("10.0.0.5", 6)]);
    let p = tally(&[("10.0.0.66", 90), ("10.0.0.5", 6), ("10.0.0.77", 500)]);
    assert_eq!(
        judge(OPEN, &t, &p, Files::Exhausted, ip("10.0.0.5")),
        Verdict::MakeRoom(Room::Listener(ip("10.0.0.66")))
    );
}

#[test]
fn an_ipv6_host_counts_by_its_slash_64() {
    assert_eq!(
        host_key(ip("2001:db8:0:1::1")),
        host_key(ip("2001:db8:0:1::2"))
    );
    assert_ne!(
        host_key(ip("2001:db8:0:1::1")),
        host_key(ip("2001:db8:0:2::1"))
    );
    assert_eq!(host_key(ip("::ffff:10.0.0.1")), ip("10.0.0.1"));
}

#[test]
fn tiny_listeners_keep_no_headroom() {
    let two = Limits {
        max: 2,
        per_address: None,
    };
    let p = Tally::default();
    let t = tally(&[("127.0.0.1", 1)]);
    assert_eq!(
        judge(two, &t, &p, Files::Plenty, ip("127.0.0.1")),
        Verdict::Admit
    );
    let t = tally(&[("127.0.0.1", 2)]);
    assert_eq!(
        judge(two, &t, &p, Files::Plenty, ip("127.0.0.2")),
        Verdict::MakeRoom(Room::Listener(ip("127.0.0.1")))
    );
}
