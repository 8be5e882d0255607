//! Trends: each drive's polled status over the last `[history] minutes`,
//! the recent part at full rate, the rest in one-second buckets
//! ([`store`], pure). An observer of the buses like the monitor and the
//! scope: it follows a bus's status events (one of the bus's followers) and imports nothing above the
//! bus; who starts it says which units are drives (a scan's reads of
//! other units are not kept), asked at each event, so drives added to the
//! configuration later are followed too.
//!
//! Memory is bounded per drive ([`store::Limits::bytes_per_drive`]: with
//! the defaults 60 s of samples at up to 100 per second, 144,000 bytes,
//! and 3600 one-second buckets, 172,800 bytes: 316,800 bytes a drive).

pub mod store;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use tokio_util::sync::CancellationToken;

use crate::bus::{BusEvent, BusFollower, BusHandle};
use crate::drive::Status;
use store::{DriveHistory, Limits, Point};

/// Status reads per second of a drive that the full-rate ring is sized
/// for: a drive polled faster keeps fewer seconds at full rate.
pub const FULL_RATE_HZ: usize = 100;

/// What the history keeps, from `[history]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HistorySettings {
    /// Minutes kept (in one-second buckets).
    pub minutes: u64,
    /// The most recent seconds kept at full rate (at up to
    /// [`FULL_RATE_HZ`] reads a second).
    pub full_rate_s: u64,
}

impl HistorySettings {
    /// The rings' sizes.
    pub fn limits(&self) -> Limits {
        let n = |v: u64| usize::try_from(v).unwrap_or(usize::MAX);
        Limits {
            full_rate_samples: n(self.full_rate_s).saturating_mul(FULL_RATE_HZ),
            buckets: n(self.minutes).saturating_mul(60),
        }
    }
}

/// Unix ms of `t`.
pub fn unix_ms(t: SystemTime) -> i64 {
    match t.duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_millis()).unwrap_or(i64::MAX),
        Err(e) => -i64::try_from(e.duration().as_millis()).unwrap_or(i64::MAX),
    }
}

/// The history of every drive.
pub struct History {
    settings: HistorySettings,
    drives: Mutex<HashMap<(Arc<str>, u8), DriveHistory>>,
    lagged: AtomicU64,
}

impl History {
    /// An empty history keeping `settings`.
    pub fn new(settings: HistorySettings) -> Arc<History> {
        Arc::new(History {
            settings,
            drives: Mutex::new(HashMap::new()),
            lagged: AtomicU64::new(0),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(Arc<str>, u8), DriveHistory>> {
        self.drives.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// What it keeps.
    pub fn settings(&self) -> HistorySettings {
        self.settings
    }

    /// Keeps `status` of `unit` on `bus`, read at `at`.
    pub fn record(&self, bus: &Arc<str>, unit: u8, at: SystemTime, status: Status) {
        let limits = self.settings.limits();
        self.lock()
            .entry((bus.clone(), unit))
            .or_insert_with(|| DriveHistory::new(limits))
            .push(unix_ms(at), status);
    }

    /// The points of `unit` on `bus` from `since_ms` to `until_ms`, at most
    /// `max_points` (see [`DriveHistory::query`]); empty when nothing was
    /// kept.
    pub fn query(
        &self,
        bus: &str,
        unit: u8,
        since_ms: i64,
        until_ms: i64,
        max_points: usize,
    ) -> Vec<Point> {
        let now = unix_ms(SystemTime::now());
        self.lock()
            .get(&(Arc::from(bus), unit))
            .map(|h| h.query(since_ms, until_ms, now, max_points))
            .unwrap_or_default()
    }

    /// Memory the histories take now, bytes.
    pub fn bytes(&self) -> usize {
        self.lock().values().map(DriveHistory::bytes).sum()
    }

    /// Drives with a history.
    pub fn drives(&self) -> usize {
        self.lock().len()
    }

    /// The most one drive's history takes, bytes.
    pub fn bytes_per_drive(&self) -> usize {
        self.settings.limits().bytes_per_drive()
    }

    /// Status events missed because the history's task fell behind.
    pub fn lagged(&self) -> u64 {
        self.lagged.load(Ordering::Relaxed)
    }

    /// Follows `bus`'s status events until `shutdown` fires, keeping those
    /// of the units `is_drive` says are drives (in the task every follower
    /// of the bus shares: a sample is a lock and a copy).
    pub fn follow(
        self: &Arc<Self>,
        bus: &BusHandle,
        is_drive: impl Fn(u8) -> bool + Send + Sync + 'static,
        shutdown: CancellationToken,
    ) {
        let follower = Follower {
            history: self.clone(),
            is_drive,
        };
        bus.follow(Arc::new(follower), shutdown);
    }
}

/// The history as a bus's follower.
struct Follower<F> {
    history: Arc<History>,
    is_drive: F,
}

impl<F: Fn(u8) -> bool + Send + Sync> BusFollower for Follower<F> {
    fn event(&self, event: &BusEvent) {
        if let BusEvent::Status {
            bus,
            unit,
            status,
            at,
        } = event
            && (self.is_drive)(*unit)
        {
            self.history.record(bus, *unit, *at, *status);
        }
    }

    fn lagged(&self, missed: u64) {
        self.history.lagged.fetch_add(missed, Ordering::Relaxed);
    }
}
