//! The listeners' connections (`crate::connections`), read from the book
//! at scrape time: held, their limits, refused by reason, closed to make
//! room, and per address for a bounded number of addresses, so a flood
//! from many addresses cannot grow `/metrics` (the first 16 addresses
//! turned away have series of their own, the rest count as `other`; the
//! 8 heaviest holders have theirs, the rest count as `other`).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Kind, Spec};
use crate::connections::{Book, Face, Limits, Listener, Refused, View};

static HELD: Spec = Spec {
    name: "drivegate_connections",
    help: "Connections (OPC UA sessions: sessions) each listener holds now.",
    kind: Kind::Gauge,
    labels: &["face"],
};
static MAX: Spec = Spec {
    name: "drivegate_connections_max",
    help: "Each listener's limit (max_connections; OPC UA sessions: max_sessions).",
    kind: Kind::Gauge,
    labels: &["face"],
};
static MAX_PER_ADDRESS: Spec = Spec {
    name: "drivegate_connections_max_per_address",
    help: "Each listener's hard cap per address, 0 when none is set (addresses share the free slots).",
    kind: Kind::Gauge,
    labels: &["face"],
};
static REFUSED: Spec = Spec {
    name: "drivegate_connections_refused_total",
    help: "Connections (sessions) refused, by listener and reason: per_address (the hard cap), heaviest (near the limit, from the address holding the most), limit (full, no address above its share), files (near the process's file limit, from the heaviest address).",
    kind: Kind::Counter,
    labels: &["face", "reason"],
};
static CLOSED: Spec = Spec {
    name: "drivegate_connections_closed_total",
    help: "Quiet connections (sessions) of the heaviest address closed to make room for a lighter address.",
    kind: Kind::Counter,
    labels: &["face"],
};
static TURNED_AWAY: Spec = Spec {
    name: "drivegate_connections_turned_away_total",
    help: "Connections refused or closed to make room, per address: the first 16 addresses turned away by a listener have a series of their own, the others count as address=\"other\".",
    kind: Kind::Counter,
    labels: &["face", "address"],
};
static BY_ADDRESS: Spec = Spec {
    name: "drivegate_connections_by_address",
    help: "Connections the 8 heaviest addresses of each listener hold now; the others together as address=\"other\".",
    kind: Kind::Gauge,
    labels: &["face", "address"],
};
static FILES_OPEN: Spec = Spec {
    name: "drivegate_connections_files_open",
    help: "Files the process has open, as the listeners last counted them (the connections opened since added).",
    kind: Kind::Gauge,
    labels: &[],
};
static FILES_RESERVE: Spec = Spec {
    name: "drivegate_connections_files_reserve",
    help: "Open files from which the listeners refuse the heaviest address (level=shared) and admit only by making room (level=last), below the process's limit.",
    kind: Kind::Gauge,
    labels: &["level"],
};

/// Holders with series of their own.
const HOLDERS: usize = 8;

/// The listeners of one daemon, exported.
pub struct Listeners {
    book: Arc<Book>,
    watched: Mutex<Vec<Weak<Listener>>>,
}

impl Listeners {
    pub(super) fn new(book: Arc<Book>) -> Self {
        Listeners {
            book,
            watched: Mutex::new(Vec::new()),
        }
    }

    /// A listener of `face` in the process's book, exported here until it
    /// is dropped.
    pub fn listener(&self, face: Face, limits: Limits) -> Arc<Listener> {
        let listener = self.book.listener(face, limits);
        let mut watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
        watched.retain(|w| w.strong_count() > 0);
        watched.push(Arc::downgrade(&listener));
        listener
    }

    /// Every live listener's view, merged by face (a listener being
    /// replaced and its successor are one face).
    pub fn views(&self) -> Vec<View> {
        let watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
        let mut by_face: BTreeMap<&'static str, View> = BTreeMap::new();
        for v in watched.iter().filter_map(Weak::upgrade).map(|l| l.view()) {
            match by_face.get_mut(v.face.label) {
                None => {
                    by_face.insert(v.face.label, v);
                }
                Some(m) => merge(m, v),
            }
        }
        by_face.into_values().collect()
    }

    /// The view of `face`, if it has a listener.
    pub fn view(&self, face: Face) -> Option<View> {
        self.views().into_iter().find(|v| v.face == face)
    }
}

fn merge(into: &mut View, v: View) {
    into.held += v.held;
    into.limits = v.limits;
    let mut holders: BTreeMap<std::net::IpAddr, usize> = into.holders.drain(..).collect();
    for (a, n) in v.holders {
        *holders.entry(a).or_insert(0) += n;
    }
    into.holders = holders.into_iter().collect();
    into.holders
        .sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    for (r, n) in v.refused {
        if let Some(m) = into.refused.iter_mut().find(|(x, _)| *x == r) {
            m.1 += n;
        }
    }
    into.closed += v.closed;
    for (a, c) in v.by_address {
        match into.by_address.iter_mut().find(|(x, _)| *x == a) {
            Some(m) => {
                m.1.refused += c.refused;
                m.1.closed += c.closed;
            }
            None => into.by_address.push((a, c)),
        }
    }
    into.recent.extend(v.recent);
    into.recent.sort_by_key(|b| std::cmp::Reverse(b.last));
}

/// The collector of [`Listeners`].
pub(super) struct ListenersCollector {
    listeners: Arc<Listeners>,
    descs: Vec<Desc>,
}

impl ListenersCollector {
    pub(super) fn new(listeners: Arc<Listeners>) -> Self {
        let descs = [
            &HELD,
            &MAX,
            &MAX_PER_ADDRESS,
            &REFUSED,
            &CLOSED,
            &TURNED_AWAY,
            &BY_ADDRESS,
            &FILES_OPEN,
            &FILES_RESERVE,
        ]
        .iter()
        .map(|s| s.desc())
        .collect();
        ListenersCollector { listeners, descs }
    }
}

impl Collector for ListenersCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut held = HELD.family();
        let mut max = MAX.family();
        let mut cap = MAX_PER_ADDRESS.family();
        let mut refused = REFUSED.family();
        let mut closed = CLOSED.family();
        let mut turned = TURNED_AWAY.family();
        let mut by_address = BY_ADDRESS.family();
        for v in self.listeners.views() {
            let face = v.face.label;
            held.set(&[face], v.held as f64);
            max.set(&[face], v.limits.max as f64);
            cap.set(&[face], v.limits.per_address.unwrap_or(0) as f64);
            for reason in Refused::ALL {
                let n = v
                    .refused
                    .iter()
                    .find(|(r, _)| *r == reason)
                    .map_or(0, |(_, n)| *n);
                refused.set(&[face, reason.label()], n as f64);
            }
            closed.set(&[face], v.closed as f64);
            for (address, counts) in &v.by_address {
                let name = address.map_or_else(|| "other".to_string(), |a| a.to_string());
                turned.set(&[face, &name], (counts.refused + counts.closed) as f64);
            }
            let mut others = 0;
            for (i, (address, n)) in v.holders.iter().enumerate() {
                if i < HOLDERS {
                    by_address.set(&[face, &address.to_string()], *n as f64);
                } else {
                    others += n;
                }
            }
            by_address.set(&[face, "other"], others as f64);
        }
        let (open, reserve) = self.listeners.book.files();
        let mut files_open = FILES_OPEN.family();
        files_open.set(&[], open as f64);
        let mut files_reserve = FILES_RESERVE.family();
        if let Some(r) = reserve {
            files_reserve.set(&["shared"], r.short_at as f64);
            files_reserve.set(&["last"], r.exhausted_at as f64);
        }
        vec![
            held.finish(),
            max.finish(),
            cap.finish(),
            refused.finish(),
            closed.finish(),
            turned.finish(),
            by_address.finish(),
            files_open.finish(),
            files_reserve.finish(),
        ]
    }
}
