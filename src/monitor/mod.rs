//! The bus monitor: every frame on the wire of a bus, with its time,
//! direction, bytes, meaning, CRC, outcome, turnaround and who caused it.
//!
//! - [`tap`] is the monitor's side of the bus's wire tap (on the bus
//!   thread): it fills a record and counts,
//! - [`record`] is one frame, fixed size; [`ring`] keeps the last N,
//! - [`counters`] counts faults per attempt and unit, for `/metrics`,
//! - [`decode`] says what a frame means (the drive's message or generic
//!   Modbus); [`view`] renders a frame for the API and CSV; [`pcap`] writes
//!   a capture Wireshark decodes; [`filter`] selects frames; [`feed`] is a
//!   live client's cursor, which counts what it lost.
//!
//! The bus thread never waits for a monitor client and never allocates for
//! one: it copies each frame into a slot of a ring allocated on its first lap,
//! and clients read behind it at their own pace. A client that falls more
//! than the ring behind loses the oldest frames, is told how many, and the
//! bus does not notice. With no client, monitoring costs one copy of about
//! 160 bytes per frame.

pub mod counters;
pub mod decode;
pub mod feed;
pub mod filter;
pub mod pcap;
pub mod record;
pub mod ring;
pub mod tap;
pub mod view;

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Instant, SystemTime};

use counters::WireCounters;
use record::FrameRecord;
use ring::Ring;
use view::WallClock;

use crate::modbus::timing::LineTiming;

/// `[monitor]` settings of one bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MonitorSettings {
    /// Keep the frames (the per-attempt counters run regardless).
    pub enabled: bool,
    /// Frames the ring keeps.
    pub ring_frames: usize,
}

impl Default for MonitorSettings {
    fn default() -> Self {
        Self {
            enabled: true,
            ring_frames: 10_000,
        }
    }
}

/// The monitor of one bus.
pub struct BusMonitor {
    ring: Option<Ring>,
    counters: WireCounters,
    /// The line's timing, for the drives' turnaround.
    line: LineTiming,
    epoch: Instant,
    clock: WallClock,
    units: std::sync::Mutex<Vec<u8>>,
    clients: AtomicUsize,
    lost: AtomicU64,
}

impl BusMonitor {
    /// A monitor for a line with `line` timing whose configured drives are
    /// `units` (their counters exist from the start, at zero).
    pub fn new(settings: MonitorSettings, line: LineTiming, units: Vec<u8>) -> Self {
        Self {
            ring: settings
                .enabled
                .then(|| Ring::new(settings.ring_frames.max(1))),
            counters: WireCounters::new(),
            line,
            epoch: Instant::now(),
            clock: WallClock {
                epoch: SystemTime::now(),
                char_ns: u64::try_from(line.char_time().as_nanos()).unwrap_or(u64::MAX),
            },
            units: std::sync::Mutex::new(units),
            clients: AtomicUsize::new(0),
            lost: AtomicU64::new(0),
        }
    }

    /// True when frames are kept.
    pub fn enabled(&self) -> bool {
        self.ring.is_some()
    }

    /// The ring, when frames are kept.
    pub fn ring(&self) -> Option<&Ring> {
        self.ring.as_ref()
    }

    /// The per-attempt wire counters.
    pub fn counters(&self) -> &WireCounters {
        &self.counters
    }

    /// The configured units.
    pub fn units(&self) -> Vec<u8> {
        self.units.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The configured units are now `units` (a reload added or removed
    /// drives on the running bus).
    pub fn set_units(&self, units: Vec<u8>) {
        *self.units.lock().unwrap_or_else(|p| p.into_inner()) = units;
    }

    /// Time a frame of `bytes` takes on this monitor's line.
    pub fn wire_time(&self, bytes: usize) -> std::time::Duration {
        self.line.wire_time(bytes)
    }

    /// ns since the monitor started, of `at`.
    pub fn ns_since_start(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_nanos()).unwrap_or(u64::MAX)
    }

    /// Converts record times to wall-clock times.
    pub fn clock(&self) -> &WallClock {
        &self.clock
    }

    /// Frames the ring keeps when full (0 when disabled).
    pub fn capacity(&self) -> usize {
        self.ring.as_ref().map_or(0, Ring::capacity)
    }

    /// Frames seen since start-up.
    pub fn frames(&self) -> u64 {
        self.ring.as_ref().map_or(0, Ring::head)
    }

    /// Memory the ring takes, in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.ring.as_ref().map_or(0, Ring::memory_bytes)
    }

    /// The last `n` frames.
    pub fn last(&self, n: usize) -> Vec<FrameRecord> {
        self.ring.as_ref().map_or_else(Vec::new, |r| r.last(n))
    }

    /// Live clients connected now.
    pub fn clients(&self) -> usize {
        self.clients.load(Ordering::Relaxed)
    }

    /// Frames live clients lost (they read too slowly), in all.
    pub fn lost(&self) -> u64 {
        self.lost.load(Ordering::Relaxed)
    }

    pub(crate) fn client_joined(&self) {
        self.clients.fetch_add(1, Ordering::Relaxed);
    }

    pub(crate) fn client_left(&self) {
        self.clients.fetch_sub(1, Ordering::Relaxed);
    }

    pub(crate) fn add_lost(&self, n: u64) {
        self.lost.fetch_add(n, Ordering::Relaxed);
    }
}
