//! Per-bus series, read from each bus's counters, queue and port state at
//! scrape time (and, for a simulated bus, from the simulator's wire
//! counters). Every series carries `bus`.

use std::sync::Arc;
use std::time::Instant;

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Family, Kind, Spec};
use super::utilisation::Utilisation;
use crate::bus::Priority;
use crate::bus::stats::{BusStatsSnapshot, Outcome};
use crate::plant::{Bus, Plant};

const BUS: &[&str] = &["bus"];

static INFO: Spec = Spec {
    name: "drivegate_bus_info",
    help: "Always 1; labels: the bus's configured port (\"sim\" for the built-in simulator) \
           and baud rate.",
    kind: Kind::Gauge,
    labels: &["bus", "port", "baud"],
};
static PORT_OPEN: Spec = Spec {
    name: "drivegate_bus_port_open",
    help: "1 while the bus's serial port is open, 0 while it is down and being reopened.",
    kind: Kind::Gauge,
    labels: BUS,
};
static TRANSACTIONS: Spec = Spec {
    name: "drivegate_bus_transactions_total",
    help: "Transactions by function code and outcome (ok, exception, timeout, crc_error, \
           bad_reply, dropped before the wire, port_error), retries included in one.",
    kind: Kind::Counter,
    labels: &["bus", "function", "outcome"],
};
static RETRIES: Spec = Spec {
    name: "drivegate_bus_retries_total",
    help: "Attempts beyond the first (after a timeout or a corrupted reply).",
    kind: Kind::Counter,
    labels: BUS,
};
static DURATION: Spec = Spec {
    name: "drivegate_bus_transaction_duration_seconds",
    help: "Time from the first byte sent to the end of each transaction, all attempts.",
    kind: Kind::Histogram,
    labels: BUS,
};
static LATENCY: Spec = Spec {
    name: "drivegate_bus_job_latency_seconds",
    help: "Time from submission to completion of each job, queue wait included.",
    kind: Kind::Histogram,
    labels: BUS,
};
static IDLE: Spec = Spec {
    name: "drivegate_bus_interframe_idle_seconds",
    help: "Silence the master left between the end of a frame (the last reply byte received) \
           and its next request, counted when that request was already waiting: t3.5 (1.75 ms \
           above 19200 baud) plus the gateway's own overhead.",
    kind: Kind::Histogram,
    labels: BUS,
};
static BUSY: Spec = Spec {
    name: "drivegate_bus_busy_seconds_total",
    help: "Seconds the wire was occupied by frames, silences and waits for replies.",
    kind: Kind::Counter,
    labels: BUS,
};
static UTILISATION: Spec = Spec {
    name: "drivegate_bus_utilisation_ratio",
    help: "Fraction of the last 10 s the wire was busy (0 to 1), sampled every second.",
    kind: Kind::Gauge,
    labels: BUS,
};
static POLLS: Spec = Spec {
    name: "drivegate_bus_polls_total",
    help: "Status polls made.",
    kind: Kind::Counter,
    labels: BUS,
};
static POLL_FAILURES: Spec = Spec {
    name: "drivegate_bus_poll_failures_total",
    help: "Status polls that got no valid status.",
    kind: Kind::Counter,
    labels: BUS,
};
static STRAY: Spec = Spec {
    name: "drivegate_bus_stray_bytes_total",
    help: "Bytes received that belonged to no reply (noise, late replies).",
    kind: Kind::Counter,
    labels: BUS,
};
static REJECTIONS: Spec = Spec {
    name: "drivegate_bus_queue_rejections_total",
    help: "Jobs refused with \"busy\" because their queue was full.",
    kind: Kind::Counter,
    labels: BUS,
};
static QUEUE: Spec = Spec {
    name: "drivegate_bus_queue_depth",
    help: "Jobs waiting, by priority class (emergency, command, poll).",
    kind: Kind::Gauge,
    labels: &["bus", "priority"],
};
static REOPENS: Spec = Spec {
    name: "drivegate_bus_reopens_total",
    help: "Times the serial port was reopened after a failure.",
    kind: Kind::Counter,
    labels: BUS,
};
static PORT_ERRORS: Spec = Spec {
    name: "drivegate_bus_port_errors_total",
    help: "Serial port errors (open failures, read/write errors, unplugged adapter).",
    kind: Kind::Counter,
    labels: BUS,
};
static REPLY_TIMEOUT: Spec = Spec {
    name: "drivegate_bus_reply_timeout_seconds",
    help: "How long the bus waits now for the first byte of a drive's reply: learned from its \
           turnarounds (smoothed + 4 x variation + margin, at least reply_timeout_floor_ms), \
           doubled after each timeout, never more than response_timeout_ms, which it is until \
           the drive has answered. A reply that starts in the guard after it is still taken.",
    kind: Kind::Gauge,
    labels: &["bus", "unit"],
};
static TURNAROUND: Spec = Spec {
    name: "drivegate_bus_turnaround_seconds",
    help: "Each drive's turnaround: from the end of a request on the wire to the first byte of \
           the reply taken (t3.5 + the drive's processing time + the adapter's latency).",
    kind: Kind::Histogram,
    labels: &["bus", "unit"],
};
static LATE_REPLIES: Spec = Spec {
    name: "drivegate_bus_late_replies_total",
    help: "Replies that came after the drive's learned reply timeout but before anything else \
           was sent to it (in the guard after the timeout, or answering its retry): taken, and \
           each raises the drive's timeout.",
    kind: Kind::Counter,
    labels: &["bus", "unit"],
};
static INTERFRAME_GAP: Spec = Spec {
    name: "drivegate_bus_interframe_gap_seconds",
    help: "The silence each drive's requests get now: t3.5 (1.75 ms above 19200 baud) with \
           interframe = \"spec\", the fixed value, or with \"auto\" the drive's learned gap \
           (twice the shortest silence it answered, at least 3.5 characters and the adapter's \
           latency; the spec again after any fault, until relearned).",
    kind: Kind::Gauge,
    labels: &["bus", "unit"],
};
static INTERFRAME_FALLBACKS: Spec = Spec {
    name: "drivegate_bus_interframe_fallbacks_total",
    help: "Times a drive's learned gap (interframe = \"auto\") was dropped for the spec's t3.5 \
           after a fault: a drive that turned strict (replaced), or a noisy line.",
    kind: Kind::Counter,
    labels: &["bus", "unit"],
};
static SIM_REQUESTS: Spec = Spec {
    name: "drivegate_sim_requests_total",
    help: "Simulated bus only: requests the simulated drives received with a good CRC.",
    kind: Kind::Counter,
    labels: BUS,
};
static SIM_GAPS: Spec = Spec {
    name: "drivegate_sim_gap_violations_total",
    help: "Simulated bus only: requests that began less than 3.5 characters (t3.5) after the \
           previous frame; 0 on a correct master.",
    kind: Kind::Counter,
    labels: BUS,
};
static SIM_STALLED: Spec = Spec {
    name: "drivegate_sim_stalled_replies_total",
    help: "Simulated bus only: replies the simulator did not send because the machine kept it \
           from running past the response timeout; the master saw them as lost. Above 0, the \
           machine is too busy for the simulated timing.",
    kind: Kind::Counter,
    labels: BUS,
};
static SIM_INJECTED: Spec = Spec {
    name: "drivegate_sim_injected_faults_total",
    help: "Simulated bus only: wire faults injected by the simulator, by kind (dropped, \
           corrupted, late, noise).",
    kind: Kind::Counter,
    labels: &["bus", "kind"],
};

static SPECS: [&Spec; 24] = [
    &INFO,
    &PORT_OPEN,
    &TRANSACTIONS,
    &RETRIES,
    &DURATION,
    &LATENCY,
    &IDLE,
    &BUSY,
    &UTILISATION,
    &POLLS,
    &POLL_FAILURES,
    &STRAY,
    &REJECTIONS,
    &QUEUE,
    &REOPENS,
    &PORT_ERRORS,
    &REPLY_TIMEOUT,
    &TURNAROUND,
    &LATE_REPLIES,
    &INTERFRAME_GAP,
    &INTERFRAME_FALLBACKS,
    &SIM_REQUESTS,
    &SIM_GAPS,
    &SIM_INJECTED,
];

/// Function codes the drives use (read holding registers, write single,
/// write multiple): always exported, at 0 until used, so that `rate()` and
/// `increase()` see the first timeout. Other codes appear once seen.
const DRIVE_FUNCTIONS: [u8; 3] = [0x03, 0x06, 0x10];

/// Exports every bus's counters.
pub(crate) struct BusCollector {
    plant: Arc<Plant>,
    utilisation: Arc<Utilisation>,
    descs: Vec<Desc>,
}

impl BusCollector {
    pub(crate) fn new(plant: Arc<Plant>, utilisation: Arc<Utilisation>) -> Self {
        let descs = SPECS.iter().map(|s| s.desc()).collect();
        Self {
            plant,
            utilisation,
            descs,
        }
    }
}

/// The families of one scrape.
struct Families {
    info: Family,
    port_open: Family,
    transactions: Family,
    retries: Family,
    duration: Family,
    latency: Family,
    idle: Family,
    busy: Family,
    utilisation: Family,
    polls: Family,
    poll_failures: Family,
    stray: Family,
    rejections: Family,
    queue: Family,
    reopens: Family,
    port_errors: Family,
    reply_timeout: Family,
    turnaround: Family,
    late_replies: Family,
    interframe_gap: Family,
    interframe_fallbacks: Family,
    sim_requests: Family,
    sim_gaps: Family,
    sim_stalled: Family,
    sim_injected: Family,
}

impl Families {
    fn new() -> Self {
        Self {
            info: INFO.family(),
            port_open: PORT_OPEN.family(),
            transactions: TRANSACTIONS.family(),
            retries: RETRIES.family(),
            duration: DURATION.family(),
            latency: LATENCY.family(),
            idle: IDLE.family(),
            busy: BUSY.family(),
            utilisation: UTILISATION.family(),
            polls: POLLS.family(),
            poll_failures: POLL_FAILURES.family(),
            stray: STRAY.family(),
            rejections: REJECTIONS.family(),
            queue: QUEUE.family(),
            reopens: REOPENS.family(),
            port_errors: PORT_ERRORS.family(),
            reply_timeout: REPLY_TIMEOUT.family(),
            turnaround: TURNAROUND.family(),
            late_replies: LATE_REPLIES.family(),
            interframe_gap: INTERFRAME_GAP.family(),
            interframe_fallbacks: INTERFRAME_FALLBACKS.family(),
            sim_requests: SIM_REQUESTS.family(),
            sim_gaps: SIM_GAPS.family(),
            sim_stalled: SIM_STALLED.family(),
            sim_injected: SIM_INJECTED.family(),
        }
    }

    fn bus(&mut self, bus: &Bus, stats: &BusStatsSnapshot, utilisation: Option<f64>) {
        let name = bus.handle.name();
        let l = [name];
        let baud = bus.config.baud.to_string();
        self.info
            .set(&[name, bus.config.port.get_ref(), &baud], 1.0);
        self.port_open.set_bool(&l, stats.port_open);
        self.transactions(name, stats);
        self.retries.set(&l, stats.retries as f64);
        self.duration.set_histogram(&l, &stats.transaction_duration);
        self.latency.set_histogram(&l, &stats.job_latency);
        self.idle.set_histogram(&l, &stats.interframe_idle);
        self.busy.set(&l, stats.busy_seconds);
        if let Some(ratio) = utilisation {
            self.utilisation.set(&l, ratio);
        }
        self.polls.set(&l, stats.polls as f64);
        self.poll_failures.set(&l, stats.poll_failures as f64);
        self.stray.set(&l, stats.stray_bytes as f64);
        self.rejections.set(&l, stats.busy_rejections as f64);
        let depths = bus.handle.queue_depths();
        // `queue_depths` lists the classes in `Priority::ALL` order.
        for (priority, depth) in Priority::ALL.iter().zip(depths) {
            self.queue.set(&[name, priority.name()], depth as f64);
        }
        self.reopens.set(&l, stats.reopens as f64);
        self.port_errors.set(&l, stats.port_errors as f64);
        for (unit, timing) in &stats.drives {
            let unit = unit.to_string();
            let l = [name, unit.as_str()];
            self.reply_timeout
                .set(&l, timing.reply_timeout.as_secs_f64());
            self.turnaround.set_histogram(&l, &timing.turnaround);
            self.late_replies.set(&l, timing.late_replies as f64);
        }
        // Every configured drive's gap from start: its starting one until
        // it was sent a request.
        let start = bus.config.starting_interframe();
        for drive in &bus.config.drives {
            let unit = drive.unit();
            let timing = stats.drives.get(&unit);
            let gap = timing.map_or(start, |t| t.interframe);
            let fallbacks = timing.map_or(0, |t| t.interframe_fallbacks);
            let unit = unit.to_string();
            let l = [name, unit.as_str()];
            self.interframe_gap.set(&l, gap.as_secs_f64());
            self.interframe_fallbacks.set(&l, fallbacks as f64);
        }
        if let Some(sim) = &bus.sim {
            let s = sim.stats();
            self.sim_requests.set(&l, s.requests as f64);
            self.sim_gaps.set(&l, s.gap_violations as f64);
            self.sim_stalled.set(&l, s.stalled as f64);
            for (kind, n) in [
                ("dropped", s.dropped),
                ("corrupted", s.corrupted),
                ("late", s.late),
                ("noise", s.noise_bursts),
            ] {
                self.sim_injected.set(&[name, kind], n as f64);
            }
        }
    }

    fn transactions(&mut self, bus: &str, stats: &BusStatsSnapshot) {
        let mut functions: Vec<u8> = DRIVE_FUNCTIONS.to_vec();
        functions.extend(stats.transactions.keys().map(|(f, _)| *f));
        functions.sort_unstable();
        functions.dedup();
        for function in functions {
            let code = format!("0x{function:02x}");
            for outcome in Outcome::ALL {
                let n = stats
                    .transactions
                    .get(&(function, outcome))
                    .copied()
                    .unwrap_or(0);
                self.transactions
                    .set(&[bus, &code, outcome.name()], n as f64);
            }
        }
    }

    fn finish(self) -> Vec<MetricFamily> {
        [
            self.info,
            self.port_open,
            self.transactions,
            self.retries,
            self.duration,
            self.latency,
            self.idle,
            self.busy,
            self.utilisation,
            self.polls,
            self.poll_failures,
            self.stray,
            self.rejections,
            self.queue,
            self.reopens,
            self.port_errors,
            self.reply_timeout,
            self.turnaround,
            self.late_replies,
            self.interframe_gap,
            self.interframe_fallbacks,
            self.sim_requests,
            self.sim_gaps,
            self.sim_stalled,
            self.sim_injected,
        ]
        .into_iter()
        .map(Family::finish)
        .collect()
    }
}

impl Collector for BusCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut f = Families::new();
        let now = Instant::now();
        for (index, bus) in self.plant.now().indexed_buses() {
            let stats = bus.handle.stats();
            let utilisation = self.utilisation.window(index).and_then(|w| {
                let ratio = w.ratio(now, stats.busy_seconds);
                w.record(now, stats.busy_seconds);
                ratio
            });
            f.bus(bus, &stats, utilisation);
        }
        f.finish()
    }
}
