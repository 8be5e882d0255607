//! What an operator deploys and watches: the command line, the Debian
//! package, the systemd unit, logs, the graceful stop, the Prometheus
//! exposition with promtool and a real Prometheus server, the Grafana
//! dashboard; and the metrics scrape benchmark (ignored by `cargo test`).
//!
//! A new test of packaging, service, logging or monitoring goes into the
//! module of its part here.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod attack_matrix;
mod cli;
mod config_ranges;
mod docs;
mod face_crash;
mod graceful_stop;
mod grafana;
mod logs;
mod manifest;
mod metrics;
mod metrics_bus_idle;
mod metrics_scrape_cost;
mod package;
mod prometheus;
mod reference;
mod reload;
mod reload_in_place;
mod reload_listeners;
mod restart;
mod systemd;
mod vendor;
