//! The latest status of each drive of a bus, with its age, and the events
//! that announce changes to subscribers (WebSocket clients, leases, logs).
//!
//! Faces read drive values from here, so serving a dashboard or a metrics
//! scrape never costs bus time.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};

use tokio::sync::broadcast;

use crate::drive::Status;

/// Whether a drive answers its polls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// Not polled yet.
    Unknown,
    /// Answering.
    Online,
    /// Stopped answering; polled with backoff.
    Offline,
}

impl Link {
    /// Stable name for the API.
    pub fn name(self) -> &'static str {
        match self {
            Link::Unknown => "unknown",
            Link::Online => "online",
            Link::Offline => "offline",
        }
    }
}

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
    /// A write to a drive was carried out or failed (every face's, and the
    /// daemon's own stops): the audit log's line, for live watchers.
    Write(Arc<WriteRecord>),
}

/// One audited write: who sent what to which unit, and the drive's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct WriteRecord {
    /// Bus name.
    pub bus: Arc<str>,
    /// Unit address (0: a broadcast).
    pub unit: u8,
    /// Token name, client address, or the daemon's own (`lease-expiry
    /// (owner)`, `shutdown`).
    pub who: String,
    /// The request in words.
    pub what: String,
    /// True when the drive confirmed it.
    pub ok: bool,
    /// The drive's answer, or why it failed.
    pub answer: String,
    /// When it was decided.
    pub at: SystemTime,
}

/// Capacity of the event channel: a subscriber lagging further behind is
/// told how many events it missed rather than slowing the bus.
pub const EVENT_CAPACITY: usize = 1024;

/// The cache of one bus.
pub struct StatusCache {
    bus: Arc<str>,
    drives: Mutex<BTreeMap<u8, DriveSnapshot>>,
    events: broadcast::Sender<BusEvent>,
    offline_after: u32,
}

impl StatusCache {
    /// A cache for the drives `units` of bus `bus`; a drive is marked offline
    /// after `offline_after` failed polls in a row.
    pub fn new(bus: Arc<str>, units: impl IntoIterator<Item = u8>, offline_after: u32) -> Self {
        let (events, _) = broadcast::channel(EVENT_CAPACITY);
        Self {
            bus,
            drives: Mutex::new(
                units
                    .into_iter()
                    .map(|u| (u, DriveSnapshot::new(u)))
                    .collect(),
            ),
            events,
            offline_after: offline_after.max(1),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u8, DriveSnapshot>> {
        self.drives.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Tells the subscribers of a write (see [`crate::audit`]).
    pub fn record_write(&self, record: WriteRecord) {
        self.publish(BusEvent::Write(Arc::new(record)));
    }

    fn publish(&self, event: BusEvent) {
        // No subscriber is not an error.
        let _ = self.events.send(event);
    }

    /// Stores a good status read from `unit` (polled or read on request).
    pub fn record_status(&self, unit: u8, status: Status) {
        let now = SystemTime::now();
        let came_online = {
            let mut drives = self.lock();
            let entry = drives
                .entry(unit)
                .or_insert_with(|| DriveSnapshot::new(unit));
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
            let entry = drives
                .entry(unit)
                .or_insert_with(|| DriveSnapshot::new(unit));
            entry.consecutive_failures = entry.consecutive_failures.saturating_add(1);
            let offline =
                entry.consecutive_failures >= self.offline_after && entry.link != Link::Offline;
            if offline {
                entry.link = Link::Offline;
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
            .is_some_and(|d| d.link == Link::Offline)
    }

    /// The snapshot of one drive.
    pub fn get(&self, unit: u8) -> Option<DriveSnapshot> {
        self.lock().get(&unit).cloned()
    }

    /// Snapshots of every drive, by unit.
    pub fn all(&self) -> Vec<DriveSnapshot> {
        self.lock().values().cloned().collect()
    }

    /// A receiver of every future event.
    pub fn subscribe(&self) -> broadcast::Receiver<BusEvent> {
        self.events.subscribe()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn online_offline_transitions_are_published_once() {
        let cache = StatusCache::new("line1".into(), [1, 2], 3);
        let mut rx = cache.subscribe();
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
        assert!(cache.is_offline(1));
        assert_eq!(cache.get(2).map(|d| d.link), Some(Link::Unknown));
        // Its last good status is kept, with its age.
        assert!(cache.get(1).unwrap().status.is_some());
    }
}
