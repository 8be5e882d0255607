//! The control core's own counters, read at scrape time: the ends of the
//! leases of Modbus TCP clients' communication-loss function, per bus.
//! Every bus's series exist from start-up, at 0, so an alert on
//! `increase(...) > 0` needs no `absent()`.

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Kind, Spec};
use crate::control::Control;

static COMM_LOSS: Spec = Spec {
    name: "drivegate_modbus_tcp_comm_loss_stops_total",
    help: "Leases of Modbus TCP clients' communication-loss function that ended, each followed \
           by the network's comm_loss_action (none: nothing sent), by reason: timeout (no \
           request within comm_loss_ms) or closed (the connection closed).",
    kind: Kind::Counter,
    labels: &["bus", "reason"],
};

/// Exports the control core's counters.
pub(crate) struct ControlCollector {
    control: Control,
    descs: Vec<Desc>,
}

impl ControlCollector {
    pub(crate) fn new(control: Control) -> Self {
        Self {
            control,
            descs: vec![COMM_LOSS.desc()],
        }
    }
}

impl Collector for ControlCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut comm_loss = COMM_LOSS.family();
        for (i, bus) in self.control.plant().buses().iter().enumerate() {
            let name = bus.handle.name();
            let (timeout, closed) = self.control.comm_loss_ends(i);
            comm_loss.set(&[name, "timeout"], timeout as f64);
            comm_loss.set(&[name, "closed"], closed as f64);
        }
        vec![comm_loss.finish()]
    }
}
