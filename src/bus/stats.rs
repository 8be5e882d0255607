//! Counters of one bus, kept by its scheduler and read by the health API and
//! the metrics exporter. Reading them never touches the wire.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, SystemTime};

use crate::listed::listed_enum;

listed_enum! {
    /// How one transaction ended (after its retries).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
    pub enum Outcome {
        /// A valid reply (or a broadcast sent).
        Ok,
        /// The drive answered with a Modbus exception.
        Exception,
        /// No reply in time.
        Timeout,
        /// The reply's CRC was wrong.
        CrcError,
        /// A well-formed reply that did not answer the request (wrong unit,
        /// function or content) or a reply with stray bytes around it.
        BadReply,
        /// Dropped before the wire: its caller had gone or its deadline passed.
        Dropped,
        /// Not sent because the port failed.
        PortError,
    }
}

impl Outcome {
    /// Stable name for metric labels.
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Ok => "ok",
            Outcome::Exception => "exception",
            Outcome::Timeout => "timeout",
            Outcome::CrcError => "crc_error",
            Outcome::BadReply => "bad_reply",
            Outcome::Dropped => "dropped",
            Outcome::PortError => "port_error",
        }
    }
}

/// Bounds for the silence between frames: fine around t3.5 (1.75 ms above
/// 19200 baud, 2 to 4 ms at 19200 and 9600), where the master's overhead shows.
pub const IDLE_BOUNDS: &[f64] = &[
    0.0010, 0.0015, 0.00175, 0.0018, 0.00185, 0.0019, 0.00195, 0.0020, 0.0021, 0.0022, 0.0025,
    0.0030, 0.0035, 0.0040, 0.0045, 0.0050, 0.0075, 0.010, 0.020, 0.050,
];

/// Bounds for a drive's turnaround (end of request to first reply byte):
/// t3.5 at 115200 baud and up is 1.75 ms, slow drives take tens of ms.
pub const TURNAROUND_BOUNDS: &[f64] = &[
    0.0015, 0.002, 0.0025, 0.003, 0.004, 0.005, 0.0075, 0.010, 0.015, 0.020, 0.030, 0.050, 0.100,
    0.250,
];

/// The reply timing of one drive, as the master learned it.
#[derive(Debug)]
pub struct DriveTiming {
    /// The drive's reply timeout now (learned, or the ceiling).
    reply_timeout_ns: AtomicU64,
    /// Replies taken after the learned timeout.
    late_replies: AtomicU64,
    /// The silence the drive's requests get now.
    interframe_ns: AtomicU64,
    /// Times the drive's learned gap fell back to the spec.
    interframe_fallbacks: AtomicU64,
    /// Each reply's turnaround.
    pub turnaround: Histogram,
}

/// A copy of one drive's [`DriveTiming`].
#[derive(Debug, Clone, PartialEq)]
pub struct DriveTimingSnapshot {
    /// The drive's reply timeout now.
    pub reply_timeout: Duration,
    /// Replies taken after the learned timeout.
    pub late_replies: u64,
    /// The silence the drive's requests get now (t3.5, a fixed gap, or
    /// its learned one).
    pub interframe: Duration,
    /// Times its learned gap fell back to the spec.
    pub interframe_fallbacks: u64,
    /// Turnarounds of its replies.
    pub turnaround: HistogramSnapshot,
}

/// A histogram with fixed bucket bounds in seconds.
#[derive(Debug)]
pub struct Histogram {
    bounds: &'static [f64],
    buckets: Vec<AtomicU64>,
    sum_ns: AtomicU64,
    count: AtomicU64,
}

/// A point-in-time copy of a [`Histogram`].
#[derive(Debug, Clone, PartialEq)]
pub struct HistogramSnapshot {
    /// Upper bounds in seconds.
    pub bounds: &'static [f64],
    /// Cumulative counts per bound (observations <= bound).
    pub cumulative: Vec<u64>,
    /// Sum of observations in seconds.
    pub sum: f64,
    /// Number of observations.
    pub count: u64,
}

/// Bounds for transaction and latency histograms: a status poll takes 5.8 ms
/// at 115200 baud, a timeout tens of ms.
pub const DURATION_BOUNDS: &[f64] = &[
    0.002, 0.004, 0.006, 0.008, 0.010, 0.012, 0.015, 0.020, 0.030, 0.050, 0.100, 0.250, 0.500, 1.0,
    2.5,
];

impl Histogram {
    /// An empty histogram with `bounds` (ascending, seconds).
    pub fn new(bounds: &'static [f64]) -> Self {
        Self {
            bounds,
            buckets: bounds.iter().map(|_| AtomicU64::new(0)).collect(),
            sum_ns: AtomicU64::new(0),
            count: AtomicU64::new(0),
        }
    }

    /// Records one observation.
    pub fn observe(&self, d: Duration) {
        let secs = d.as_secs_f64();
        if let Some(i) = self.bounds.iter().position(|&b| secs <= b) {
            self.buckets[i].fetch_add(1, Ordering::Relaxed);
        }
        self.sum_ns.fetch_add(
            u64::try_from(d.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
        self.count.fetch_add(1, Ordering::Relaxed);
    }

    /// A consistent-enough copy for export.
    pub fn snapshot(&self) -> HistogramSnapshot {
        let mut running = 0;
        let cumulative = self
            .buckets
            .iter()
            .map(|b| {
                running += b.load(Ordering::Relaxed);
                running
            })
            .collect();
        HistogramSnapshot {
            bounds: self.bounds,
            cumulative,
            sum: self.sum_ns.load(Ordering::Relaxed) as f64 / 1e9,
            count: self.count.load(Ordering::Relaxed),
        }
    }
}

/// The counters of one bus.
#[derive(Debug)]
pub struct BusStats {
    transactions: Mutex<BTreeMap<(u8, Outcome), u64>>,
    retries: AtomicU64,
    /// Time from the first byte sent to the end of each transaction (all attempts).
    pub transaction_duration: Histogram,
    /// Time from submission to completion of each job (queue wait included).
    pub job_latency: Histogram,
    /// Silence left between the end of a frame and the next request, when
    /// that request was already waiting: t3.5 plus the master's overhead.
    pub interframe_idle: Histogram,
    busy_ns: AtomicU64,
    polls: AtomicU64,
    poll_failures: AtomicU64,
    stray_bytes: AtomicU64,
    busy_rejections: AtomicU64,
    port_open: AtomicBool,
    reopens: AtomicU64,
    port_errors: AtomicU64,
    last_port_error: Mutex<Option<(SystemTime, String)>>,
    drives: Mutex<BTreeMap<u8, std::sync::Arc<DriveTiming>>>,
}

/// A copy of a bus's counters.
#[derive(Debug, Clone, PartialEq)]
pub struct BusStatsSnapshot {
    /// Transactions by (function code, outcome).
    pub transactions: BTreeMap<(u8, Outcome), u64>,
    /// Retries made (attempts beyond the first).
    pub retries: u64,
    /// Seconds the wire was occupied by transactions and their silences.
    pub busy_seconds: f64,
    /// Status polls made.
    pub polls: u64,
    /// Status polls that failed.
    pub poll_failures: u64,
    /// Bytes received that belonged to no reply (noise, late replies).
    pub stray_bytes: u64,
    /// Submissions refused because a queue was full.
    pub busy_rejections: u64,
    /// True while the serial port is open.
    pub port_open: bool,
    /// Times the port was reopened after a failure.
    pub reopens: u64,
    /// Serial port errors seen.
    pub port_errors: u64,
    /// The last port error, with its time.
    pub last_port_error: Option<(SystemTime, String)>,
    /// Transaction durations.
    pub transaction_duration: HistogramSnapshot,
    /// Job latencies (queue + wire).
    pub job_latency: HistogramSnapshot,
    /// Silences between frames while work was waiting.
    pub interframe_idle: HistogramSnapshot,
    /// Reply timing by unit, for units that were sent a request.
    pub drives: BTreeMap<u8, DriveTimingSnapshot>,
}

impl Default for BusStats {
    fn default() -> Self {
        Self::new()
    }
}

impl BusStats {
    /// All counters at zero.
    pub fn new() -> Self {
        Self {
            transactions: Mutex::new(BTreeMap::new()),
            retries: AtomicU64::new(0),
            transaction_duration: Histogram::new(DURATION_BOUNDS),
            job_latency: Histogram::new(DURATION_BOUNDS),
            interframe_idle: Histogram::new(IDLE_BOUNDS),
            busy_ns: AtomicU64::new(0),
            polls: AtomicU64::new(0),
            poll_failures: AtomicU64::new(0),
            stray_bytes: AtomicU64::new(0),
            busy_rejections: AtomicU64::new(0),
            port_open: AtomicBool::new(false),
            reopens: AtomicU64::new(0),
            port_errors: AtomicU64::new(0),
            last_port_error: Mutex::new(None),
            drives: Mutex::new(BTreeMap::new()),
        }
    }

    /// Records what a transaction to `unit` says about its timing: the
    /// reply timeout it has now, the turnaround of the reply taken, the
    /// replies taken after the learned timeout, and the silence before its
    /// requests now with the times it fell back to the spec.
    pub fn record_timing(
        &self,
        unit: u8,
        reply_timeout: Duration,
        turnaround: Option<Duration>,
        late_replies: u8,
        interframe: (Duration, u64),
    ) {
        if unit == 0 {
            return;
        }
        let timing = {
            let mut drives = self.drives.lock().unwrap_or_else(|p| p.into_inner());
            drives
                .entry(unit)
                .or_insert_with(|| {
                    std::sync::Arc::new(DriveTiming {
                        reply_timeout_ns: AtomicU64::new(0),
                        late_replies: AtomicU64::new(0),
                        interframe_ns: AtomicU64::new(0),
                        interframe_fallbacks: AtomicU64::new(0),
                        turnaround: Histogram::new(TURNAROUND_BOUNDS),
                    })
                })
                .clone()
        };
        timing.reply_timeout_ns.store(
            u64::try_from(reply_timeout.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
        timing
            .late_replies
            .fetch_add(u64::from(late_replies), Ordering::Relaxed);
        timing.interframe_ns.store(
            u64::try_from(interframe.0.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
        timing
            .interframe_fallbacks
            .store(interframe.1, Ordering::Relaxed);
        if let Some(t) = turnaround {
            timing.turnaround.observe(t);
        }
    }

    /// Counts one finished transaction.
    pub fn record_transaction(&self, function: u8, outcome: Outcome, attempts: u8) {
        let mut map = self.transactions.lock().unwrap_or_else(|p| p.into_inner());
        *map.entry((function, outcome)).or_insert(0) += 1;
        drop(map);
        self.retries
            .fetch_add(u64::from(attempts.saturating_sub(1)), Ordering::Relaxed);
    }

    /// Adds wire occupancy.
    pub fn add_busy(&self, d: Duration) {
        self.busy_ns.fetch_add(
            u64::try_from(d.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
    }

    /// Counts a status poll and whether it worked.
    pub fn record_poll(&self, ok: bool) {
        self.polls.fetch_add(1, Ordering::Relaxed);
        if !ok {
            self.poll_failures.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Counts bytes that belonged to no reply.
    pub fn add_stray_bytes(&self, n: usize) {
        self.stray_bytes.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Counts a submission refused for a full queue.
    pub fn record_busy_rejection(&self) {
        self.busy_rejections.fetch_add(1, Ordering::Relaxed);
    }

    /// Records the port opening (`reopen` after a failure) or closing.
    pub fn set_port_open(&self, open: bool, reopen: bool) {
        self.port_open.store(open, Ordering::Relaxed);
        if open && reopen {
            self.reopens.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Records a port error.
    pub fn record_port_error(&self, error: &str) {
        self.port_errors.fetch_add(1, Ordering::Relaxed);
        *self
            .last_port_error
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some((SystemTime::now(), error.to_string()));
    }

    /// True while the port is open.
    pub fn port_open(&self) -> bool {
        self.port_open.load(Ordering::Relaxed)
    }

    /// A copy of every counter.
    pub fn snapshot(&self) -> BusStatsSnapshot {
        BusStatsSnapshot {
            transactions: self
                .transactions
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
            retries: self.retries.load(Ordering::Relaxed),
            busy_seconds: self.busy_ns.load(Ordering::Relaxed) as f64 / 1e9,
            polls: self.polls.load(Ordering::Relaxed),
            poll_failures: self.poll_failures.load(Ordering::Relaxed),
            stray_bytes: self.stray_bytes.load(Ordering::Relaxed),
            busy_rejections: self.busy_rejections.load(Ordering::Relaxed),
            port_open: self.port_open(),
            reopens: self.reopens.load(Ordering::Relaxed),
            port_errors: self.port_errors.load(Ordering::Relaxed),
            last_port_error: self
                .last_port_error
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
            transaction_duration: self.transaction_duration.snapshot(),
            job_latency: self.job_latency.snapshot(),
            interframe_idle: self.interframe_idle.snapshot(),
            drives: self
                .drives
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .iter()
                .map(|(&unit, t)| {
                    (
                        unit,
                        DriveTimingSnapshot {
                            reply_timeout: Duration::from_nanos(
                                t.reply_timeout_ns.load(Ordering::Relaxed),
                            ),
                            late_replies: t.late_replies.load(Ordering::Relaxed),
                            interframe: Duration::from_nanos(
                                t.interframe_ns.load(Ordering::Relaxed),
                            ),
                            interframe_fallbacks: t.interframe_fallbacks.load(Ordering::Relaxed),
                            turnaround: t.turnaround.snapshot(),
                        },
                    )
                })
                .collect(),
        }
    }
}

impl BusStatsSnapshot {
    /// Transactions with `outcome`, any function.
    pub fn count(&self, outcome: Outcome) -> u64 {
        self.transactions
            .iter()
            .filter(|((_, o), _)| *o == outcome)
            .map(|(_, n)| n)
            .sum()
    }

    /// All transactions that reached the wire (everything but dropped).
    pub fn on_wire(&self) -> u64 {
        self.transactions
            .iter()
            .filter(|((_, o), _)| !matches!(o, Outcome::Dropped | Outcome::PortError))
            .map(|(_, n)| n)
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_is_cumulative() {
        let h = Histogram::new(DURATION_BOUNDS);
        h.observe(Duration::from_micros(5844));
        h.observe(Duration::from_millis(60));
        h.observe(Duration::from_secs(10));
        let s = h.snapshot();
        assert_eq!(s.count, 3);
        assert_eq!(s.cumulative[1], 0); // <= 4 ms
        assert_eq!(s.cumulative[2], 1); // <= 6 ms
        assert_eq!(*s.cumulative.last().unwrap(), 2); // the 10 s one is only in +Inf
        assert!((s.sum - 10.065844).abs() < 1e-6);
    }

    #[test]
    fn counts_by_outcome() {
        let st = BusStats::new();
        st.record_transaction(0x03, Outcome::Ok, 1);
        st.record_transaction(0x03, Outcome::Ok, 2);
        st.record_transaction(0x06, Outcome::Timeout, 2);
        st.record_transaction(0x06, Outcome::Dropped, 0);
        let s = st.snapshot();
        assert_eq!(s.count(Outcome::Ok), 2);
        assert_eq!(s.on_wire(), 3);
        assert_eq!(s.retries, 2);
    }
}
