//! Who gives way when connections run short: the rule every listener
//! applies to a new connection, pure, on the counts it is shown.
//!
//! Share, don't cap, while there is room: an address may take any free
//! slot. Under pressure the heaviest address gives way first:
//!
//! - the listener near `max_connections` (its last eighth): a new
//!   connection from the address that holds the most is refused, the others
//!   are admitted;
//! - the listener full: a new connection from an address holding less
//!   than the heaviest one by two or more is admitted, and one connection
//!   of the heaviest address is closed to make room (the quietest); from
//!   the heaviest, or when every address holds about as much, it is
//!   refused;
//! - the process short of file descriptors: the same rule, on the
//!   connections every listener of the process holds: the heaviest address
//!   is refused once the shared reserve is reached, and at the last
//!   reserve only a lighter address gets in, by making room.
//!
//! A hard cap per address (`max_connections_per_address`) stays available
//! for those who want one; set, it is applied first.
//!
//! An address that holds nothing is never the heaviest, so a newcomer (the
//! admin, a PLC restarting) always finds a slot while anyone holds more
//! than one.

use std::collections::{BTreeMap, HashMap};
use std::net::{IpAddr, Ipv6Addr};

use crate::listed::listed_enum;

/// The address a client is counted by: an IPv4 address (also when it
/// reaches an IPv6 socket as `::ffff:a.b.c.d`), or an IPv6 client's /64,
/// which one host may fill with addresses of its own.
pub fn host_key(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V6(v6) => {
            let mut segments = v6.segments();
            segments[4..].fill(0);
            IpAddr::V6(Ipv6Addr::from(segments))
        }
        v4 => v4,
    }
}

/// A listener's limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Connections at once.
    pub max: usize,
    /// A hard cap per address, when configured.
    pub per_address: Option<usize>,
}

impl Limits {
    /// Slots near the top where the heaviest address is refused: an eighth
    /// of `max` (none below 8).
    pub fn headroom(&self) -> usize {
        self.max / 8
    }
}

/// How near the process is to its file-descriptor limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Files {
    /// Far from it.
    Plenty,
    /// In the shared reserve: the heaviest address is refused.
    Short,
    /// In the last reserve, kept for what is open: only a lighter address
    /// gets in, by making room.
    Exhausted,
}

listed_enum! {
    /// Why a connection was refused.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum Refused {
        /// Its address holds the configured hard cap.
        PerAddress,
        /// The listener is near its limit and its address holds the most.
        Heaviest,
        /// The listener is full, and no address holds more than its share.
        Limit,
        /// The process is near its file-descriptor limit and its address
        /// holds the most (or nobody can give way).
        Files,
    }
}

impl Refused {
    /// Stable label for the metrics.
    pub fn label(self) -> &'static str {
        match self {
            Refused::PerAddress => "per_address",
            Refused::Heaviest => "heaviest",
            Refused::Limit => "limit",
            Refused::Files => "files",
        }
    }
}

/// Where to make room: a connection of `address` is closed, on this
/// listener or on any listener of the process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Room {
    /// One of this listener's connections from the address.
    Listener(IpAddr),
    /// One of the process's connections from the address.
    Process(IpAddr),
}

/// What to do with a new connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Serve it.
    Admit,
    /// Serve it, once a connection of the heaviest address is closed.
    MakeRoom(Room),
    /// Close it.
    Refuse(Refused),
}

/// The connections held, per address (keys of [`host_key`]): a listener's
/// or the process's.
#[derive(Debug, Default, Clone)]
pub struct Tally {
    held: HashMap<IpAddr, usize>,
    /// How many addresses hold each count: the heaviest in O(log n).
    levels: BTreeMap<usize, usize>,
    total: usize,
}

impl Tally {
    /// One more connection of `key`.
    pub fn add(&mut self, key: IpAddr) {
        let n = self.held.entry(key).or_insert(0);
        Self::level_down(&mut self.levels, *n);
        *n += 1;
        *self.levels.entry(*n).or_insert(0) += 1;
        self.total += 1;
    }

    /// One connection fewer of `key`.
    pub fn remove(&mut self, key: IpAddr) {
        let Some(n) = self.held.get_mut(&key) else {
            return;
        };
        Self::level_down(&mut self.levels, *n);
        *n -= 1;
        if *n == 0 {
            self.held.remove(&key);
        } else {
            *self.levels.entry(*n).or_insert(0) += 1;
        }
        self.total = self.total.saturating_sub(1);
    }

    fn level_down(levels: &mut BTreeMap<usize, usize>, n: usize) {
        if n == 0 {
            return;
        }
        if let Some(c) = levels.get_mut(&n) {
            *c -= 1;
            if *c == 0 {
                levels.remove(&n);
            }
        }
    }

    /// Connections `key` holds.
    pub fn held(&self, key: IpAddr) -> usize {
        self.held.get(&key).copied().unwrap_or(0)
    }

    /// Connections held in all.
    pub fn total(&self) -> usize {
        self.total
    }

    /// Addresses holding any.
    pub fn addresses(&self) -> usize {
        self.held.len()
    }

    /// The most any address other than `key` holds.
    pub fn heaviest_other(&self, key: IpAddr) -> usize {
        let own = self.held(key);
        let mut levels = self.levels.iter().rev();
        match levels.next() {
            None => 0,
            Some((&top, &count)) if top != own || count > 1 => top,
            Some(_) => levels.next().map_or(0, |(&n, _)| n),
        }
    }

    /// The address holding the most (one of them, on a tie), and how many.
    pub fn heaviest(&self) -> Option<(IpAddr, usize)> {
        let (&top, _) = self.levels.iter().next_back()?;
        self.held
            .iter()
            .find(|(_, n)| **n == top)
            .map(|(k, n)| (*k, *n))
    }

    /// Every address and what it holds, the heaviest first.
    pub fn by_weight(&self) -> Vec<(IpAddr, usize)> {
        let mut all: Vec<(IpAddr, usize)> = self.held.iter().map(|(k, n)| (*k, *n)).collect();
        all.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        all
    }
}

/// Whether `key`, holding `held` while the heaviest other address holds
/// `others`, is the one to give way: it holds something, and at least as
/// much as anyone else.
fn gives_way(held: usize, others: usize) -> bool {
    held > 0 && held >= others
}

/// The verdict on a new connection from `key` (a [`host_key`]), given the
/// listener's limits and connections, the process's connections (every
/// listener's) and how near the process is to its file limit.
pub fn judge(
    limits: Limits,
    listener: &Tally,
    process: &Tally,
    files: Files,
    key: IpAddr,
) -> Verdict {
    let held = listener.held(key);
    if limits.per_address.is_some_and(|cap| held >= cap) {
        return Verdict::Refuse(Refused::PerAddress);
    }
    let others = listener.heaviest_other(key);
    let total = listener.total();
    let on_listener = if total >= limits.max {
        if !gives_way(held, others) && others >= held + 2 {
            Verdict::MakeRoom(Room::Listener(heaviest_of(listener, key)))
        } else {
            return Verdict::Refuse(Refused::Limit);
        }
    } else if total + limits.headroom() >= limits.max && gives_way(held, others) {
        return Verdict::Refuse(Refused::Heaviest);
    } else {
        Verdict::Admit
    };
    let p_held = process.held(key);
    let p_others = process.heaviest_other(key);
    let on_files = match files {
        Files::Plenty => Verdict::Admit,
        Files::Short if gives_way(p_held, p_others) => return Verdict::Refuse(Refused::Files),
        Files::Short => Verdict::Admit,
        Files::Exhausted if !gives_way(p_held, p_others) && p_others >= p_held + 2 => {
            Verdict::MakeRoom(Room::Process(heaviest_of(process, key)))
        }
        Files::Exhausted => return Verdict::Refuse(Refused::Files),
    };
    // Closing one of this listener's connections frees a file as well.
    match (on_listener, on_files) {
        (Verdict::MakeRoom(room), _) | (_, Verdict::MakeRoom(room)) => Verdict::MakeRoom(room),
        _ => Verdict::Admit,
    }
}

/// The heaviest address of `tally` other than `key` (which holds less).
fn heaviest_of(tally: &Tally, key: IpAddr) -> IpAddr {
    tally.heaviest().map_or(key, |(k, _)| k)
}

#[cfg(test)]
mod tests;
