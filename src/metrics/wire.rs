//! Per-attempt wire counters per bus and unit, and the monitor's and the
//! scope's own figures, read at scrape time from each bus's monitor.
//!
//! The transaction counters (`drivegate_bus_transactions_total`) say how
//! each transaction ended after its retries, so a retry that succeeds hides
//! the fault before it. These count every attempt: with 5 % of replies
//! corrupted, `drivegate_bus_wire_errors_total{error="crc_error"}` grows by
//! 5 % of `drivegate_bus_wire_attempts_total`, retries or not. The series of
//! every configured unit exist from start-up, at 0.

use std::sync::Arc;

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Family, Kind, Spec};
use crate::monitor::counters::WireEvent;
use crate::plant::Plant;

static ATTEMPTS: Spec = Spec {
    name: "drivegate_bus_wire_attempts_total",
    help: "Requests put on the wire, each attempt (retries included), by unit.",
    kind: Kind::Counter,
    labels: &["bus", "unit"],
};
static ERRORS: Spec = Spec {
    name: "drivegate_bus_wire_errors_total",
    help: "Failed attempts by unit and error (crc_error, timeout, bad_reply), each attempt \
           counted, so faults a successful retry hid show too.",
    kind: Kind::Counter,
    labels: &["bus", "unit", "error"],
};
static STRAY: Spec = Spec {
    name: "drivegate_bus_wire_stray_bytes_total",
    help: "Bytes that belonged to no reply, by the unit of the transaction they followed.",
    kind: Kind::Counter,
    labels: &["bus", "unit"],
};
static FRAMES: Spec = Spec {
    name: "drivegate_monitor_frames_total",
    help: "Frames the bus monitor recorded (requests, replies, timeouts, noise); 0 while \
           [monitor] is off.",
    kind: Kind::Counter,
    labels: &["bus"],
};
static LOST: Spec = Spec {
    name: "drivegate_monitor_lost_frames_total",
    help: "Frames live monitor clients lost because they read more slowly than the ring \
           turned (the bus never waits for them).",
    kind: Kind::Counter,
    labels: &["bus"],
};
static CLIENTS: Spec = Spec {
    name: "drivegate_monitor_clients",
    help: "Live bus monitor clients connected now.",
    kind: Kind::Gauge,
    labels: &["bus"],
};
static SCOPE: Spec = Spec {
    name: "drivegate_scope_running",
    help: "1 while a scope capture runs on the bus (its drives get the polls, the others \
           their floor rate).",
    kind: Kind::Gauge,
    labels: &["bus"],
};

static SPECS: [&Spec; 7] = [&ATTEMPTS, &ERRORS, &STRAY, &FRAMES, &LOST, &CLIENTS, &SCOPE];

/// Exports the wire counters and the monitor's figures of every bus.
pub(crate) struct WireCollector {
    plant: Arc<Plant>,
    descs: Vec<Desc>,
}

impl WireCollector {
    pub(crate) fn new(plant: Arc<Plant>) -> Self {
        Self {
            plant,
            descs: SPECS.iter().map(|s| s.desc()).collect(),
        }
    }
}

impl Collector for WireCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut attempts = ATTEMPTS.family();
        let mut errors = ERRORS.family();
        let mut stray = STRAY.family();
        let mut frames = FRAMES.family();
        let mut lost = LOST.family();
        let mut clients = CLIENTS.family();
        let mut scope = SCOPE.family();
        for bus in self.plant.now().buses() {
            let name = bus.handle.name();
            let monitor = bus.monitor();
            for (unit, c) in monitor.counters().snapshot(&monitor.units()) {
                let unit = unit.to_string();
                attempts.set(&[name, &unit], c.attempts as f64);
                for event in WireEvent::ALL.into_iter().filter(|e| e.is_error()) {
                    errors.set(&[name, &unit, event.name()], c.get(event) as f64);
                }
                stray.set(&[name, &unit], c.stray_bytes as f64);
            }
            frames.set(&[name], monitor.frames() as f64);
            lost.set(&[name], monitor.lost() as f64);
            clients.set(&[name], monitor.clients() as f64);
            scope.set_bool(&[name], bus.scope().is_running());
        }
        [attempts, errors, stray, frames, lost, clients, scope]
            .into_iter()
            .map(Family::finish)
            .collect()
    }
}
