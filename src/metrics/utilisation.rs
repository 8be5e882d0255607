//! Bus utilisation: the fraction of wall time the wire was busy over the
//! last [`WINDOW`].
//!
//! Each bus counts the seconds its wire is occupied (frames, silences,
//! waits for replies). Prometheus can take the rate of that counter over its
//! own range, but a scrape every 15-60 s hides short saturations; so the
//! daemon also samples the counter every [`SAMPLE_PERIOD`] and exports the
//! ratio over the last 10 s as a gauge. Scrapes add samples too, so the
//! ratio exists even where no sampler runs (a daemon without a tokio
//! runtime, unit tests).

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::plant::Plant;

/// How far back the utilisation ratio looks.
pub const WINDOW: Duration = Duration::from_secs(10);
/// How often the sampler reads each bus's busy counter.
pub const SAMPLE_PERIOD: Duration = Duration::from_secs(1);
/// A ratio over less time than this says little: none is exported.
const MIN_SPAN: Duration = Duration::from_millis(500);

/// Samples of one bus's busy-seconds counter over the last [`WINDOW`].
#[derive(Debug, Default)]
pub(crate) struct BusyWindow {
    samples: Mutex<VecDeque<(Instant, f64)>>,
}

impl BusyWindow {
    /// Records the counter's value at `now`; keeps exactly one sample at or
    /// beyond the window's start, so the span measured is the full window
    /// once the daemon has run that long.
    pub(crate) fn record(&self, now: Instant, busy_seconds: f64) {
        let mut samples = self.samples.lock().unwrap_or_else(|p| p.into_inner());
        samples.push_back((now, busy_seconds));
        let start = now.checked_sub(WINDOW);
        while samples.len() > 1 && start.is_some_and(|start| samples[1].0 <= start) {
            samples.pop_front();
        }
    }

    /// The busy fraction between the oldest sample kept and `now`, clamped
    /// to 0..1 (a transaction's time is counted when it ends, so a window
    /// edge can cut one in two); `None` until the span is long enough.
    pub(crate) fn ratio(&self, now: Instant, busy_seconds: f64) -> Option<f64> {
        let samples = self.samples.lock().unwrap_or_else(|p| p.into_inner());
        let &(then, busy_then) = samples.front()?;
        let span = now.checked_duration_since(then)?;
        if span < MIN_SPAN {
            return None;
        }
        Some(((busy_seconds - busy_then) / span.as_secs_f64()).clamp(0.0, 1.0))
    }
}

/// The utilisation windows of every bus of the plant, following it: a bus
/// a reload adds gets a window, one it reopens a new one (its counters
/// start again), one it removes loses its own.
#[derive(Debug, Default)]
pub(crate) struct Utilisation {
    /// By bus slot: the bus it measures and its window.
    windows: Mutex<std::collections::HashMap<usize, Measured>>,
}

/// A running bus (its handle) and its window.
type Measured = (crate::bus::BusHandle, Arc<BusyWindow>);

impl Utilisation {
    /// Windows for the buses of `plant`.
    pub(crate) fn new(plant: &Plant) -> Self {
        let u = Self::default();
        u.sample(plant);
        u
    }

    /// Reads every bus's busy counter (never the wire) into its window.
    pub(crate) fn sample(&self, plant: &Plant) {
        let now = Instant::now();
        let directory = plant.now();
        let mut windows = self.windows.lock().unwrap_or_else(|p| p.into_inner());
        windows.retain(|i, (bus, _)| directory.bus_at(*i).is_some_and(|b| b.handle.is(bus)));
        for (index, bus) in directory.indexed_buses() {
            let (_, window) = windows
                .entry(index)
                .or_insert_with(|| (bus.handle.clone(), Arc::new(BusyWindow::default())));
            window.record(now, bus.handle.stats().busy_seconds);
        }
    }

    /// The window of the bus in slot `index`.
    pub(crate) fn window(&self, index: usize) -> Option<Arc<BusyWindow>> {
        let windows = self.windows.lock().unwrap_or_else(|p| p.into_inner());
        windows.get(&index).map(|(_, w)| w.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ratio_over_the_window() {
        let w = BusyWindow::default();
        let t0 = Instant::now();
        assert_eq!(w.ratio(t0, 0.0), None, "no sample yet");
        w.record(t0, 0.0);
        assert_eq!(
            w.ratio(t0 + Duration::from_millis(100), 0.05),
            None,
            "span too short"
        );
        // Half busy for 4 s.
        for s in 1..=4 {
            w.record(t0 + Duration::from_secs(s), 0.5 * s as f64);
        }
        let r = w.ratio(t0 + Duration::from_secs(4), 2.0).unwrap();
        assert!((r - 0.5).abs() < 1e-9, "{r}");
    }

    #[test]
    fn old_samples_leave_the_window() {
        let w = BusyWindow::default();
        let t0 = Instant::now();
        // Busy all the time for 20 s, then idle for 10 s.
        for s in 0..=20 {
            w.record(t0 + Duration::from_secs(s), s as f64);
        }
        for s in 21..=30 {
            w.record(t0 + Duration::from_secs(s), 20.0);
        }
        let now = t0 + Duration::from_secs(30);
        assert_eq!(
            w.ratio(now, 20.0),
            Some(0.0),
            "the busy time is older than the window"
        );
        assert!(w.samples.lock().unwrap().len() <= 11);
    }

    #[test]
    fn clamped_to_one() {
        let w = BusyWindow::default();
        let t0 = Instant::now();
        w.record(t0, 0.0);
        // A long transaction counted at its end, just after the window start.
        assert_eq!(w.ratio(t0 + Duration::from_secs(1), 1.2), Some(1.0));
    }
}
