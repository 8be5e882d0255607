//! The process's connections, listener by listener: one book that every
//! listener (Modbus TCP, Modbus/TCP Security, HTTP, OPC UA) asks before it
//! serves a new connection, so the file-descriptor reserve and "the
//! heaviest address gives way first" see every connection of the process.
//!
//! A connection holds a [`Ticket`] until it ends: dropping it gives the
//! slot back. The ticket knows when its connection last moved a byte
//! ([`Ticket::touch`]), and carries the token that closes it when it is
//! chosen to make room ([`Ticket::closing`]): of the heaviest address's
//! connections, the quietest is closed first.
//!
//! The decision is [`super::budget::judge`]'s; this file keeps the counts
//! it is shown, the records of what was turned away
//! ([`super::record`]), and the log lines, each written once per cause and
//! second at most ([`super::repeats`]).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, LazyLock, Mutex, MutexGuard};
use std::time::Instant;

use tokio_util::sync::CancellationToken;

use super::budget::{self, Files, Limits, Refused, Room, Tally, Verdict, host_key};
use super::files::{self, Estimate, Reserve};
use super::record::{Burst, Counts, Record, Turned};
use super::repeats::{Repeats, Say, folded_words};
use super::words::Face;

/// The connections of one process.
#[derive(Debug)]
pub struct Book {
    inner: Mutex<Inner>,
    epoch: Instant,
}

#[derive(Debug, Default)]
struct Inner {
    process: Tally,
    entries: HashMap<u64, Entry>,
    next_entry: u64,
    listeners: HashMap<u64, ListenerState>,
    next_listener: u64,
    files: Estimate,
    /// Counting `/proc/self/fd` is not done in unit tests' books.
    count_files: bool,
}

#[derive(Debug)]
struct Entry {
    listener: u64,
    key: IpAddr,
    activity: Arc<AtomicU64>,
    close: CancellationToken,
    /// False once it was chosen to make room: its place is given back then.
    counted: bool,
}

#[derive(Debug)]
struct ListenerState {
    face: Face,
    bound: Option<SocketAddr>,
    limits: Limits,
    tally: Tally,
    record: Record,
    log: Repeats<(IpAddr, Turned)>,
}

static PROCESS: LazyLock<Arc<Book>> = LazyLock::new(|| Book::new(true));

impl Book {
    /// The book of this process, which every listener shares (the file
    /// descriptors are the process's).
    pub fn process() -> Arc<Book> {
        PROCESS.clone()
    }

    /// A book of its own (tests), counting the process's open files or not.
    pub fn new(count_files: bool) -> Arc<Book> {
        Arc::new(Book {
            inner: Mutex::new(Inner {
                count_files,
                ..Inner::default()
            }),
            epoch: Instant::now(),
        })
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A listener of `face` with `limits`, in this book until dropped.
    pub fn listener(self: &Arc<Self>, face: Face, limits: Limits) -> Arc<Listener> {
        let mut inner = self.lock();
        let id = inner.next_listener;
        inner.next_listener += 1;
        inner.listeners.insert(
            id,
            ListenerState {
                face,
                bound: None,
                limits,
                tally: Tally::default(),
                record: Record::default(),
                log: Repeats::default(),
            },
        );
        Arc::new(Listener {
            book: self.clone(),
            id,
            face,
        })
    }

    /// The files open and the reserves, as last estimated.
    pub fn files(&self) -> (usize, Option<Reserve>) {
        let inner = self.lock();
        let held = inner.process.total();
        (inner.files.open(held), inner.files.reserve())
    }

    fn millis(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_millis()).unwrap_or(u64::MAX)
    }

    fn release(&self, entry: u64) {
        let mut inner = self.lock();
        let Some(e) = inner.entries.remove(&entry) else {
            return;
        };
        if e.counted {
            inner.process.remove(e.key);
            if let Some(l) = inner.listeners.get_mut(&e.listener) {
                l.tally.remove(e.key);
            }
        }
    }
}

impl Inner {
    /// How near the process is to its file limit, counting again if due.
    fn files(&mut self, now: Instant) -> Files {
        let held = self.process.total();
        if self.count_files && self.files.stale(now) {
            self.files
                .counted(now, files::count_open(), held, files::limit());
        }
        self.files.judge(held)
    }

    /// Closes the quietest connection of `key` (on `listener` only, or
    /// anywhere), giving its place back now. Returns its listener's id.
    fn make_room(&mut self, key: IpAddr, listener: Option<u64>) -> Option<u64> {
        let (&id, _) = self
            .entries
            .iter()
            .filter(|(_, e)| e.counted && e.key == key && listener.is_none_or(|l| l == e.listener))
            .min_by_key(|(_, e)| e.activity.load(Ordering::Relaxed))?;
        let e = self.entries.get_mut(&id)?;
        e.counted = false;
        e.close.cancel();
        let (key, on) = (e.key, e.listener);
        self.process.remove(key);
        if let Some(l) = self.listeners.get_mut(&on) {
            l.tally.remove(key);
        }
        Some(on)
    }
}

/// A connection's place in the book, until it ends.
#[derive(Debug)]
pub struct Ticket {
    book: Arc<Book>,
    entry: u64,
    activity: Arc<AtomicU64>,
    close: CancellationToken,
}

impl Ticket {
    /// The connection moved a byte now.
    pub fn touch(&self) {
        self.activity
            .store(self.book.millis(Instant::now()), Ordering::Relaxed);
    }

    /// Fires when the connection is to be closed to make room for another
    /// address.
    pub fn closing(&self) -> &CancellationToken {
        &self.close
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.book.release(self.entry);
    }
}

/// A listener's share of the book: its limits, its connections, what it
/// turned away.
#[derive(Debug)]
pub struct Listener {
    book: Arc<Book>,
    id: u64,
    face: Face,
}

/// A log line to write once the book is let go.
struct Line {
    face: Face,
    listener: Option<SocketAddr>,
    text: String,
}

impl Line {
    fn write(&self) {
        match self.listener {
            Some(at) => tracing::warn!(face = self.face.label, listener = %at, "{}", self.text),
            None => tracing::warn!(face = self.face.label, "{}", self.text),
        }
    }
}

impl Listener {
    /// Its face.
    pub fn face(&self) -> Face {
        self.face
    }

    /// New limits (a reload, drives added to the plant): they apply to the
    /// next connection.
    pub fn set_limits(&self, limits: Limits) {
        if let Some(l) = self.book.lock().listeners.get_mut(&self.id) {
            l.limits = limits;
        }
    }

    /// Where it listens, for the console.
    pub fn set_bound(&self, bound: SocketAddr) {
        if let Some(l) = self.book.lock().listeners.get_mut(&self.id) {
            l.bound = Some(bound);
        }
    }

    /// Its limits now.
    pub fn limits(&self) -> Limits {
        self.book.lock().listeners.get(&self.id).map_or(
            Limits {
                max: 0,
                per_address: None,
            },
            |l| l.limits,
        )
    }

    /// A new connection from `ip`: its ticket, or why it is refused
    /// (counted and logged here, once per cause and second at most).
    pub fn admit(&self, ip: IpAddr) -> Result<Ticket, Refused> {
        let now = Instant::now();
        let key = host_key(ip);
        let mut lines = Vec::new();
        let verdict = {
            let mut inner = self.book.lock();
            let files = inner.files(now);
            let open = inner.files.open(inner.process.total());
            let reserve = inner.files.reserve();
            let Some(state) = inner.listeners.get(&self.id) else {
                return Err(Refused::Limit);
            };
            let limits = state.limits;
            let verdict = budget::judge(limits, &state.tally, &inner.process, files, key);
            match verdict {
                Verdict::Refuse(reason) => {
                    let held = state.tally.held(key);
                    let total = state.tally.total();
                    let everywhere = inner.process.held(key);
                    let state = inner.listeners.get_mut(&self.id);
                    if let Some(state) = state {
                        state.record.note(key, Turned::Refused(reason), now);
                        let say = state.log.note((key, Turned::Refused(reason)), now);
                        if let Some(text) = refusal_words(
                            self.face,
                            say,
                            key,
                            reason,
                            Facts {
                                held,
                                total,
                                everywhere,
                                limits,
                                open,
                                reserve,
                            },
                        ) {
                            lines.push(Line {
                                face: self.face,
                                listener: state.bound,
                                text,
                            });
                        }
                    }
                    Err(reason)
                }
                Verdict::Admit => Ok(()),
                Verdict::MakeRoom(room) => {
                    let (victim, only_here) = match room {
                        Room::Listener(k) => (k, Some(self.id)),
                        Room::Process(k) => (k, None),
                    };
                    let victim_held = inner.process.held(victim);
                    if let Some(on) = inner.make_room(victim, only_here)
                        && let Some(state) = inner.listeners.get_mut(&on)
                    {
                        state.record.note(victim, Turned::Closed, now);
                        if let Say::Line { folded, first } =
                            state.log.note((victim, Turned::Closed), now)
                        {
                            let why = match room {
                                Room::Listener(_) => format!(
                                    "the listener was full ({} connections, {} {}) and {victim} held the most ({})",
                                    limits.max, state.face.section, state.face.max_key, victim_held
                                ),
                                Room::Process(_) => format!(
                                    "the process is near its file limit ({} of {} open; LimitNOFILE) and {victim} held the most ({victim_held} in all)",
                                    open,
                                    reserve.map_or(0, |r| r.limit)
                                ),
                            };
                            lines.push(Line {
                                face: state.face,
                                listener: state.bound,
                                text: format!(
                                    "{}: a quiet connection of {victim} closed to make room for {key} ({} client): {why}. Counted in drivegate_connections_closed_total{{face=\"{}\"}}; further ones logged once per cause and second at most{}",
                                    state.face.name,
                                    self.face.name,
                                    state.face.label,
                                    folded_words(folded, first)
                                ),
                            });
                        }
                    }
                    Ok(())
                }
            }
            .map(|()| {
                let id = inner.next_entry;
                inner.next_entry += 1;
                let activity = Arc::new(AtomicU64::new(self.book.millis(now)));
                let close = CancellationToken::new();
                inner.entries.insert(
                    id,
                    Entry {
                        listener: self.id,
                        key,
                        activity: activity.clone(),
                        close: close.clone(),
                        counted: true,
                    },
                );
                inner.process.add(key);
                if let Some(l) = inner.listeners.get_mut(&self.id) {
                    l.tally.add(key);
                }
                Ticket {
                    book: self.book.clone(),
                    entry: id,
                    activity,
                    close,
                }
            })
        };
        for line in lines {
            line.write();
        }
        verdict
    }

    /// A new session from `peer` among `seats` (each with its address,
    /// when known, and when it last asked for anything): OPC UA sessions
    /// are shared by the same rule as connections, with [`Files::Plenty`]
    /// (a session is no file). `Ok(Some(i))`: admitted once `seats[i]` is
    /// closed to make room.
    pub fn admit_seat(
        &self,
        peer: Option<IpAddr>,
        seats: &[Seat],
    ) -> Result<Option<usize>, Refused> {
        let now = Instant::now();
        let key = peer.map(host_key);
        let mut tally = Tally::default();
        for s in seats {
            if let Some(a) = s.address {
                tally.add(host_key(a));
            }
        }
        // Sessions whose address is unknown count as one address of their own.
        let unknown: IpAddr = std::net::Ipv6Addr::UNSPECIFIED.into();
        for s in seats.iter().filter(|s| s.address.is_none()) {
            let _ = s;
            tally.add(unknown);
        }
        let key = key.unwrap_or(unknown);
        let mut lines = Vec::new();
        let result = {
            let mut inner = self.book.lock();
            let Some(state) = inner.listeners.get_mut(&self.id) else {
                return Err(Refused::Limit);
            };
            let limits = state.limits;
            match budget::judge(limits, &tally, &Tally::default(), Files::Plenty, key) {
                Verdict::Admit => Ok(None),
                Verdict::Refuse(reason) => {
                    state.record.note(key, Turned::Refused(reason), now);
                    let say = state.log.note((key, Turned::Refused(reason)), now);
                    let facts = Facts {
                        held: tally.held(key),
                        total: tally.total(),
                        everywhere: tally.held(key),
                        limits,
                        open: 0,
                        reserve: None,
                    };
                    if let Some(text) = refusal_words(self.face, say, key, reason, facts) {
                        lines.push(Line {
                            face: self.face,
                            listener: state.bound,
                            text,
                        });
                    }
                    Err(reason)
                }
                Verdict::MakeRoom(Room::Listener(victim) | Room::Process(victim)) => {
                    let quietest = seats
                        .iter()
                        .enumerate()
                        .filter(|(_, s)| s.address.map_or(unknown, host_key) == victim)
                        .min_by_key(|(_, s)| (s.active, s.last))
                        .map(|(i, _)| i);
                    if quietest.is_some() {
                        state.record.note(victim, Turned::Closed, now);
                        if let Say::Line { folded, first } =
                            state.log.note((victim, Turned::Closed), now)
                        {
                            lines.push(Line {
                                face: self.face,
                                listener: state.bound,
                                text: format!(
                                    "{}: a quiet session of {victim} closed to make room for {key}: {} sessions are open ({} {}) and {victim} held the most ({}). Counted in drivegate_connections_closed_total{{face=\"{}\"}}{}",
                                    self.face.name,
                                    limits.max,
                                    self.face.section,
                                    self.face.max_key,
                                    tally.held(victim),
                                    self.face.label,
                                    folded_words(folded, first)
                                ),
                            });
                        }
                    }
                    Ok(quietest)
                }
            }
        };
        for line in lines {
            line.write();
        }
        result
    }

    /// The sessions held now, by their clients' addresses (`None`: not
    /// known yet): a listener of sessions is told, not asked.
    pub fn set_seats(&self, addresses: impl IntoIterator<Item = Option<IpAddr>>) {
        let unknown: IpAddr = std::net::Ipv6Addr::UNSPECIFIED.into();
        let mut tally = Tally::default();
        for a in addresses {
            tally.add(a.map_or(unknown, host_key));
        }
        if let Some(l) = self.book.lock().listeners.get_mut(&self.id) {
            l.tally = tally;
        }
    }

    /// What it holds and what it turned away, now.
    pub fn view(&self) -> View {
        let inner = self.book.lock();
        let Some(state) = inner.listeners.get(&self.id) else {
            return View::default();
        };
        View {
            face: self.face,
            bound: state.bound,
            limits: state.limits,
            held: state.tally.total(),
            holders: state.tally.by_weight(),
            refused: Refused::ALL.map(|r| (r, state.record.refused(r))).to_vec(),
            closed: state.record.closed(),
            by_address: state.record.by_address(),
            recent: state.record.recent(),
        }
    }
}

impl Drop for Listener {
    fn drop(&mut self) {
        self.book.lock().listeners.remove(&self.id);
    }
}

/// A session as [`Listener::admit_seat`] sees it.
#[derive(Debug, Clone, Copy)]
pub struct Seat {
    /// Its client's address, when known.
    pub address: Option<IpAddr>,
    /// Whether it was activated (an inactive one is closed first).
    pub active: bool,
    /// When it last asked for anything.
    pub last: Instant,
}

/// A listener as the metrics and the console show it.
#[derive(Debug, Clone)]
pub struct View {
    /// Its face.
    pub face: Face,
    /// Where it listens, when it said.
    pub bound: Option<SocketAddr>,
    /// Its limits.
    pub limits: Limits,
    /// Connections held.
    pub held: usize,
    /// Per address, the heaviest first.
    pub holders: Vec<(IpAddr, usize)>,
    /// Refusals by reason.
    pub refused: Vec<(Refused, u64)>,
    /// Connections closed to make room.
    pub closed: u64,
    /// Per address (`None`: the addresses beyond the named ones).
    pub by_address: Vec<(Option<IpAddr>, Counts)>,
    /// The last bursts, the latest first.
    pub recent: Vec<Burst>,
}

impl Default for View {
    fn default() -> Self {
        View {
            face: super::words::HTTP,
            bound: None,
            limits: Limits {
                max: 0,
                per_address: None,
            },
            held: 0,
            holders: Vec::new(),
            refused: Vec::new(),
            closed: 0,
            by_address: Vec::new(),
            recent: Vec::new(),
        }
    }
}

/// What a refusal's line says besides its reason.
#[derive(Debug, Clone, Copy)]
struct Facts {
    held: usize,
    total: usize,
    everywhere: usize,
    limits: Limits,
    open: usize,
    reserve: Option<Reserve>,
}

/// The line for a refusal of `key` for `reason`, if one is due.
fn refusal_words(face: Face, say: Say, key: IpAddr, reason: Refused, f: Facts) -> Option<String> {
    let (folded, first) = match say {
        Say::Quiet => return None,
        Say::Line { folded, first } => (folded, first),
        Say::Many { folded } => {
            return Some(format!(
                "{}: connections refused from more than {} addresses at once; further refusals of addresses not yet logged are counted in drivegate_connections_refused_total{{face=\"{}\"}}, not logged{}",
                face.name,
                super::repeats::CAPACITY,
                face.label,
                folded_words(folded, false)
            ));
        }
    };
    let unit = face.unit;
    let why = match reason {
        Refused::PerAddress => format!(
            "the address holds {} {unit}s, the most one address may ({} {}; without it an address shares every free slot)",
            f.held, face.section, face.per_address_key
        ),
        Refused::Heaviest => format!(
            "the listener holds {} of its {} {unit}s and this address the most ({}); the last {} are kept for other addresses ({} {})",
            f.total,
            f.limits.max,
            f.held,
            f.limits.headroom(),
            face.section,
            face.max_key
        ),
        Refused::Limit => format!(
            "the listener was full ({} {unit}s, {} {}) and no address held more than its share",
            f.limits.max, face.section, face.max_key
        ),
        Refused::Files => format!(
            "the process has {} of its {} files open (LimitNOFILE in the unit) and this address holds {} connections, the most of any",
            f.open,
            f.reserve.map_or(0, |r| r.limit),
            f.everywhere
        ),
    };
    Some(format!(
        "{}: {unit}s from {key} refused: {why}. Counted in drivegate_connections_refused_total{{face=\"{}\",reason=\"{}\"}}; logged once per address and second at most, less often as it goes on{}",
        face.name,
        face.label,
        reason.label(),
        folded_words(folded, first)
    ))
}

#[cfg(test)]
mod tests;
