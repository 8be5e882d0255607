//! The latest status of each drive of a bus, with its age, and the events
//! that announce changes to subscribers (WebSocket clients, leases, logs).
//!
//! Faces read drive values from here, so serving a dashboard or a metrics
//! scrape never costs bus time.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};

use tokio::sync::broadcast;

use super::freshness::{Expected, Facts};
pub use super::link::Link;
use crate::drive::Status;

/// What the daemon knows of one drive.
#[derive(Debug, Clone, PartialEq)]
pub struct DriveSnapshot {
    /// Unit address on its bus.
    pub unit: u8,
    /// The latest good status, if any.
    pub status: Option<Status>,
    /// Wall-clock time of that status.
    pub seen_at: Option<SystemTime>,
    /// Monotonic time of that status, for its age.
    pub seen_instant: Option<Instant>,
    /// Online / offline.
    pub link: Link,
    /// Polls failed in a row.
    pub consecutive_failures: u32,
}

impl DriveSnapshot {
    fn new(unit: u8) -> Self {
        Self {
            unit,
            status: None,
            seen_at: None,
            seen_instant: None,
            link: Link::Unknown,
            consecutive_failures: 0,
        }
    }

    /// Age of the status, `None` if never seen.
    pub fn age(&self) -> Option<std::time::Duration> {
        self.seen_instant.map(|t| t.elapsed())
    }
}

/// A change on a bus, for subscribers.
#[derive(Debug, Clone, PartialEq)]
pub enum BusEvent {
    /// A new status was read from a drive.
    Status {
        /// Bus name.
        bus: Arc<str>,
        /// Unit address.
        unit: u8,
        /// The status.
        status: Status,
        /// When it was read.
        at: SystemTime,
    },
    /// A drive started answering (again).
    Online {
        /// Bus name.
        bus: Arc<str>,
        /// Unit address.
        unit: u8,
    },
    /// A drive stopped answering.
    Offline {
        /// Bus name.
        bus: Arc<str>,
        /// Unit address.
        unit: u8,
        /// The last failure.
        reason: String,
    },
    /// The serial port opened.
    BusUp {
        /// Bus name.
        bus: Arc<str>,
    },
    /// The serial port failed or closed.
    BusDown {
        /// Bus name.
        bus: Arc<str>,
        /// Why.
        reason: String,
    },
}

/// Capacity of the event channel: a subscriber lagging further behind is
/// told how many events it missed rather than slowing the bus.
pub const EVENT_CAPACITY: usize = 1024;

/// One drive in the cache: its snapshot, and what its freshness needs
/// beside it (when it went offline, why its last poll failed).
#[derive(Debug, Clone)]
struct Entry {
    snapshot: DriveSnapshot,
    offline_since: Option<SystemTime>,
    last_failure: Option<String>,
}

impl Entry {
    fn new(unit: u8) -> Self {
        Entry {
            snapshot: DriveSnapshot::new(unit),
            offline_since: None,
            last_failure: None,
        }
    }

    fn facts(&self) -> Facts {
        Facts {
            seen_at: self.snapshot.seen_at,
            seen_instant: self.snapshot.seen_instant,
            link: self.snapshot.link,
            failures: self.snapshot.consecutive_failures,
            offline_since: self.offline_since,
            last_failure: self.last_failure.clone(),
        }
    }
}

/// The cache of one bus.
pub struct StatusCache {
    bus: Arc<str>,
    drives: Mutex<BTreeMap<u8, Entry>>,
    events: broadcast::Sender<BusEvent>,
    /// The events but statuses: a subscriber that only follows the links
    /// is not woken at every poll (each wake-up of a task costs more than
    /// most of them do with an event).
    links: broadcast::Sender<BusEvent>,
    offline_after: AtomicU32,
    /// How often each drive is polled, for its freshness.
    expected: Mutex<BTreeMap<u8, Expected>>,
}

impl StatusCache {
    /// A cache for the drives `units` of bus `bus`; a drive is marked offline
    /// after `offline_after` failed polls in a row.
    pub fn new(bus: Arc<str>, units: impl IntoIterator<Item = u8>, offline_after: u32) -> Self {
        let (events, _) = broadcast::channel(EVENT_CAPACITY);
        let (links, _) = broadcast::channel(EVENT_CAPACITY);
        Self {
            bus,
            drives: Mutex::new(units.into_iter().map(|u| (u, Entry::new(u))).collect()),
            events,
            links,
            offline_after: AtomicU32::new(offline_after.max(1)),
            expected: Mutex::new(BTreeMap::new()),
        }
    }

    /// The same cache, told how often each drive is polled (what its
    /// data's age is measured against); a drive not named here is
    /// expected at the full rate.
    pub fn expecting(self, expected: impl IntoIterator<Item = (u8, Expected)>) -> Self {
        *self.expected.lock().unwrap_or_else(|p| p.into_inner()) = expected.into_iter().collect();
        self
    }

    /// The bus's drives are now `units`, polled as `expected`, offline
    /// after `offline_after` failed polls (a reload, applied in place): a
    /// drive kept keeps its status, its age and its link; one added is
    /// unknown until its first poll; one removed is forgotten (its last
    /// status must not pass for a drive's that is no longer there).
    pub fn retune(
        &self,
        units: impl IntoIterator<Item = u8>,
        offline_after: u32,
        expected: impl IntoIterator<Item = (u8, Expected)>,
    ) {
        let units: Vec<u8> = units.into_iter().collect();
        {
            let mut drives = self.lock();
            drives.retain(|unit, _| units.contains(unit));
            for &unit in &units {
                drives.entry(unit).or_insert_with(|| Entry::new(unit));
            }
        }
        self.offline_after
            .store(offline_after.max(1), Ordering::Relaxed);
        *self.expected.lock().unwrap_or_else(|p| p.into_inner()) = expected.into_iter().collect();
    }

    /// How often `unit` is polled, as its freshness measures it.
    pub fn expected(&self, unit: u8) -> Expected {
        let expected = self.expected.lock().unwrap_or_else(|p| p.into_inner());
        expected.get(&unit).copied().unwrap_or(Expected {
            period: std::time::Duration::ZERO,
            poll: std::time::Duration::ZERO,
            slack: super::freshness::GRACE,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u8, Entry>> {
        self.drives.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn publish(&self, event: BusEvent) {
        // No subscriber is not an error.
        if !matches!(event, BusEvent::Status { .. }) {
            let _ = self.links.send(event.clone());
        }
        let _ = self.events.send(event);
    }

    /// Stores a good status read from `unit` (polled or read on request).
    pub fn record_status(&self, unit: u8, status: Status) {
        let now = SystemTime::now();
        let came_online = {
            let mut drives = self.lock();
            let entry = drives.entry(unit).or_insert_with(|| Entry::new(unit));
            entry.offline_since = None;
            entry.last_failure = None;
            let entry = &mut entry.snapshot;
            let came_online = entry.link != Link::Online;
            entry.status = Some(status);
            entry.seen_at = Some(now);
            entry.seen_instant = Some(Instant::now());
            entry.link = Link::Online;
            entry.consecutive_failures = 0;
            came_online
        };
        if came_online {
            self.publish(BusEvent::Online {
                bus: self.bus.clone(),
                unit,
            });
        }
        self.publish(BusEvent::Status {
            bus: self.bus.clone(),
            unit,
            status,
            at: now,
        });
    }

    /// Records a failed poll; returns true if the drive just went offline.
    pub fn record_failure(&self, unit: u8, reason: &str) -> bool {
        let went_offline = {
            let mut drives = self.lock();
            let entry = drives.entry(unit).or_insert_with(|| Entry::new(unit));
            entry.last_failure = Some(reason.to_string());
            let snap = &mut entry.snapshot;
            snap.consecutive_failures = snap.consecutive_failures.saturating_add(1);
            let offline = snap.consecutive_failures >= self.offline_after.load(Ordering::Relaxed)
                && snap.link != Link::Offline;
            if offline {
                snap.link = Link::Offline;
                entry.offline_since = Some(SystemTime::now());
            }
            offline
        };
        if went_offline {
            self.publish(BusEvent::Offline {
                bus: self.bus.clone(),
                unit,
                reason: reason.to_string(),
            });
        }
        went_offline
    }

    /// Announces the port opening or failing.
    pub fn record_port(&self, up: bool, reason: &str) {
        self.publish(if up {
            BusEvent::BusUp {
                bus: self.bus.clone(),
            }
        } else {
            BusEvent::BusDown {
                bus: self.bus.clone(),
                reason: reason.to_string(),
            }
        });
    }

    /// True when `unit` is known to be offline.
    pub fn is_offline(&self, unit: u8) -> bool {
        self.lock()
            .get(&unit)
            .is_some_and(|d| d.snapshot.link == Link::Offline)
    }

    /// True when `unit` answered its last poll: only then are its polls worth
    /// a retry (a drive that is off would cost a timeout each time).
    pub fn answering(&self, unit: u8) -> bool {
        self.lock().get(&unit).is_some_and(|d| {
            d.snapshot.link == Link::Online && d.snapshot.consecutive_failures == 0
        })
    }

    /// The snapshot of one drive.
    pub fn get(&self, unit: u8) -> Option<DriveSnapshot> {
        self.lock().get(&unit).map(|e| e.snapshot.clone())
    }

    /// Snapshots of every drive, by unit.
    pub fn all(&self) -> Vec<DriveSnapshot> {
        self.lock().values().map(|e| e.snapshot.clone()).collect()
    }

    /// What the freshness of `unit`'s data is judged from.
    pub fn facts(&self, unit: u8) -> Option<Facts> {
        self.lock().get(&unit).map(Entry::facts)
    }

    /// The same for every drive, by unit.
    pub fn all_facts(&self) -> Vec<(u8, Facts)> {
        self.lock().iter().map(|(u, e)| (*u, e.facts())).collect()
    }

    /// A receiver of every future event.
    pub fn subscribe(&self) -> broadcast::Receiver<BusEvent> {
        self.events.subscribe()
    }

    /// A receiver of every future event but the statuses.
    pub fn subscribe_links(&self) -> broadcast::Receiver<BusEvent> {
        self.links.subscribe()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn online_offline_transitions_are_published_once() {
        let cache = StatusCache::new("line1".into(), [1, 2], 3);
        let mut rx = cache.subscribe();
        let mut links = cache.subscribe_links();
        cache.record_status(1, Status::default());
        assert!(matches!(
            rx.try_recv(),
            Ok(BusEvent::Online { unit: 1, .. })
        ));
        assert!(matches!(
            rx.try_recv(),
            Ok(BusEvent::Status { unit: 1, .. })
        ));
        cache.record_status(1, Status::default());
        assert!(matches!(
            rx.try_recv(),
            Ok(BusEvent::Status { unit: 1, .. })
        ));
        assert!(!cache.record_failure(1, "timeout"));
        assert!(!cache.record_failure(1, "timeout"));
        assert!(cache.record_failure(1, "timeout"));
        assert!(!cache.record_failure(1, "timeout"));
        assert!(matches!(
            rx.try_recv(),
            Ok(BusEvent::Offline { unit: 1, .. })
        ));
        assert!(rx.try_recv().is_err());
        // The links' subscriber saw the same, without the statuses.
        assert!(matches!(
            links.try_recv(),
            Ok(BusEvent::Online { unit: 1, .. })
        ));
        assert!(matches!(
            links.try_recv(),
            Ok(BusEvent::Offline { unit: 1, .. })
        ));
        assert!(links.try_recv().is_err());
        assert!(cache.is_offline(1));
        assert_eq!(cache.get(2).map(|d| d.link), Some(Link::Unknown));
        // Its last good status is kept, with its age.
        assert!(cache.get(1).unwrap().status.is_some());
    }

    #[test]
    fn a_retune_keeps_the_drives_kept_and_forgets_the_removed() {
        let cache = StatusCache::new("line1".into(), [1, 2], 3);
        cache.record_status(1, Status::default());
        cache.record_status(2, Status::default());
        let seen = cache.get(1).unwrap().seen_instant;
        let expected = |ms| Expected {
            period: std::time::Duration::from_millis(ms),
            poll: std::time::Duration::from_millis(ms),
            slack: super::super::freshness::GRACE,
        };
        cache.retune([1, 3], 1, [(1, expected(100)), (3, expected(100))]);
        // Unit 1 kept as it was, with its new period.
        let one = cache.get(1).unwrap();
        assert_eq!((one.link, one.seen_instant), (Link::Online, seen));
        assert_eq!(cache.expected(1), expected(100));
        // Unit 2 gone, unit 3 unknown until it is polled.
        assert_eq!(cache.get(2), None);
        assert_eq!(cache.get(3).map(|d| d.link), Some(Link::Unknown));
        // Offline after one failure now.
        assert!(cache.record_failure(3, "no reply within 50 ms"));
    }

    #[test]
    fn the_facts_of_freshness_follow_the_polls() {
        let cache = StatusCache::new("line1".into(), [1], 2);
        let facts = cache.facts(1).unwrap();
        assert_eq!((facts.link, facts.seen_at), (Link::Unknown, None));
        cache.record_failure(1, "no reply within 50 ms");
        let facts = cache.facts(1).unwrap();
        assert_eq!(facts.last_failure.as_deref(), Some("no reply within 50 ms"));
        assert_eq!(facts.offline_since, None);
        cache.record_failure(1, "no reply within 50 ms");
        let facts = cache.facts(1).unwrap();
        assert_eq!((facts.link, facts.failures), (Link::Offline, 2));
        assert!(facts.offline_since.is_some());
        // An answer clears the failure and the time it went offline.
        cache.record_status(1, Status::default());
        let facts = cache.facts(1).unwrap();
        assert_eq!((facts.link, facts.failures), (Link::Online, 0));
        assert_eq!((facts.offline_since, facts.last_failure), (None, None));
        assert!(facts.seen_instant.is_some());
        assert_eq!(cache.all_facts().len(), 1);
    }
}
