//! Reading the daemon's metrics in the Prometheus text format.

use crate::support::TestDaemon;

/// The value of a metric line in the `/metrics` text, 0 if absent (a
/// counter no event has created yet reads as zero).
pub fn metric(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(series).and_then(|v| v.trim().parse().ok()))
        .unwrap_or(0.0)
}

/// The value of `series` in what `d` would serve at `/metrics` now, read
/// in-process, 0 if absent.
pub fn counter(d: &TestDaemon, series: &str) -> f64 {
    metric(&d.metrics.render(), series)
}

/// The value of a series that must be exported (a gauge, a series created
/// at start-up); fails the test naming the series when it is absent.
pub fn exported(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.trim().parse().ok())
        .unwrap_or_else(|| panic!("{series} missing"))
}
