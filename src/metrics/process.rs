//! Process series: build information, and the standard process metrics
//! (start time, CPU, memory, file descriptors, threads) under the
//! `drivegate_` prefix, so that a leak over months shows on a dashboard.

use prometheus::process_collector::ProcessCollector;
use prometheus::{IntGaugeVec, Opts, Registry};

/// Registers `drivegate_build_info` and the `drivegate_process_*` series.
pub(crate) fn register(registry: &Registry) {
    match IntGaugeVec::new(
        Opts::new(
            "drivegate_build_info",
            "Always 1; the label carries the running version.",
        ),
        &["version"],
    ) {
        Ok(info) => {
            info.with_label_values(&[env!("CARGO_PKG_VERSION")]).set(1);
            if let Err(e) = registry.register(Box::new(info)) {
                tracing::warn!("cannot export the build information: {e}");
            }
        }
        Err(e) => tracing::warn!("cannot export the build information: {e}"),
    }
    // The collector reads /proc/<pid> at each scrape; where that is not
    // possible it exports nothing rather than failing the scrape.
    match i32::try_from(std::process::id()) {
        Ok(pid) => {
            if let Err(e) = registry.register(Box::new(ProcessCollector::new(pid, "drivegate"))) {
                tracing::warn!("cannot export the process metrics: {e}");
            }
        }
        Err(_) => tracing::warn!("process id out of range: no process metrics"),
    }
}
