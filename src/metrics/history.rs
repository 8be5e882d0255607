//! The trends' memory, read at scrape time: what the histories take and
//! the most one drive's may take (`[history]`).

use std::sync::Arc;

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Kind, Spec};
use crate::history::History;

static BYTES: Spec = Spec {
    name: "drivegate_history_bytes",
    help: "Memory the drives' status histories (the trends) take now, bytes: at most \
           drivegate_history_drive_limit_bytes for each drive with a history.",
    kind: Kind::Gauge,
    labels: &[],
};

static LIMIT: Spec = Spec {
    name: "drivegate_history_drive_limit_bytes",
    help: "The most one drive's status history takes, bytes ([history] full_rate_s x 100 \
           samples of 24 bytes, plus [history] minutes x 60 one-second buckets of 48 bytes).",
    kind: Kind::Gauge,
    labels: &[],
};

static DRIVES: Spec = Spec {
    name: "drivegate_history_drives",
    help: "Drives with a status history.",
    kind: Kind::Gauge,
    labels: &[],
};

/// Exports the history's figures.
pub(crate) struct HistoryCollector {
    history: Arc<History>,
    descs: Vec<Desc>,
}

impl HistoryCollector {
    pub(crate) fn new(history: Arc<History>) -> Self {
        Self {
            history,
            descs: vec![BYTES.desc(), LIMIT.desc(), DRIVES.desc()],
        }
    }
}

impl Collector for HistoryCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut bytes = BYTES.family();
        bytes.set(&[], self.history.bytes() as f64);
        let mut limit = LIMIT.family();
        limit.set(&[], self.history.bytes_per_drive() as f64);
        let mut drives = DRIVES.family();
        drives.set(&[], self.history.drives() as f64);
        vec![bytes.finish(), limit.finish(), drives.finish()]
    }
}
