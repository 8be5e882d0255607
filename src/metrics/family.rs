//! Metric families built at scrape time from values that live elsewhere
//! (the poll cache, the bus counters, the simulator's counters).
//!
//! A scrape copies the current values into fresh families instead of
//! mirroring them into registered gauges: nothing is kept twice, no update
//! path can forget a series, and a drive that stops answering loses its value
//! series at once instead of showing a frozen last value.

use std::collections::HashMap;

use prometheus::core::Desc;
use prometheus::proto::{
    Bucket, Counter, Gauge, Histogram, LabelPair, Metric, MetricFamily, MetricType,
};

use crate::bus::stats::HistogramSnapshot;

/// The Prometheus type of a family.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// A value that goes up and down.
    Gauge,
    /// A count that only goes up (name ends in `_total`).
    Counter,
    /// Observations in cumulative buckets.
    Histogram,
}

/// The definition of one family: a constant of the exporter.
#[derive(Debug)]
pub(crate) struct Spec {
    /// Full metric name.
    pub(crate) name: &'static str,
    /// HELP text.
    pub(crate) help: &'static str,
    /// Type.
    pub(crate) kind: Kind,
    /// Label names, in the order values are given to [`Family::set`].
    pub(crate) labels: &'static [&'static str],
}

impl Spec {
    /// The descriptor the registry checks for clashes at registration.
    pub(crate) fn desc(&self) -> Desc {
        Desc::new(
            self.name.to_string(),
            self.help.to_string(),
            self.labels.iter().map(|l| (*l).to_string()).collect(),
            HashMap::new(),
        )
        .unwrap_or_else(|e| invalid_definition(self.name, &e))
    }

    /// An empty family of this definition.
    pub(crate) fn family(&'static self) -> Family {
        let mut mf = MetricFamily::default();
        mf.set_name(self.name.to_string());
        mf.set_help(self.help.to_string());
        mf.set_field_type(match self.kind {
            Kind::Gauge => MetricType::GAUGE,
            Kind::Counter => MetricType::COUNTER,
            Kind::Histogram => MetricType::HISTOGRAM,
        });
        Family { spec: self, mf }
    }
}

/// Metric definitions are constants; a bad one is a bug that the unit tests
/// catch, never a runtime condition.
fn invalid_definition(name: &str, e: &prometheus::Error) -> ! {
    panic!("invalid metric definition {name}: {e}")
}

/// A family being filled during one scrape.
pub(crate) struct Family {
    spec: &'static Spec,
    mf: MetricFamily,
}

impl Family {
    fn metric(&self, values: &[&str]) -> Metric {
        debug_assert_eq!(
            values.len(),
            self.spec.labels.len(),
            "label values of {}",
            self.spec.name
        );
        let labels = self
            .spec
            .labels
            .iter()
            .zip(values)
            .map(|(name, value)| {
                let mut pair = LabelPair::default();
                pair.set_name((*name).to_string());
                pair.set_value((*value).to_string());
                pair
            })
            .collect();
        Metric::from_label(labels)
    }

    /// Adds one sample of a gauge or counter.
    pub(crate) fn set(&mut self, values: &[&str], value: f64) {
        let mut metric = self.metric(values);
        match self.spec.kind {
            Kind::Gauge => {
                let mut g = Gauge::default();
                g.set_value(value);
                metric.set_gauge(g);
            }
            Kind::Counter => {
                let mut c = Counter::default();
                c.set_value(value);
                metric.set_counter(c);
            }
            Kind::Histogram => {
                debug_assert!(false, "{} is a histogram", self.spec.name);
                return;
            }
        }
        self.mf.mut_metric().push(metric);
    }

    /// Adds a 0/1 sample.
    pub(crate) fn set_bool(&mut self, values: &[&str], on: bool) {
        self.set(values, if on { 1.0 } else { 0.0 });
    }

    /// Adds one histogram.
    pub(crate) fn set_histogram(&mut self, values: &[&str], h: &HistogramSnapshot) {
        debug_assert_eq!(self.spec.kind, Kind::Histogram, "{}", self.spec.name);
        let mut metric = self.metric(values);
        let buckets = h
            .bounds
            .iter()
            .zip(&h.cumulative)
            .map(|(bound, count)| {
                let mut b = Bucket::default();
                b.set_upper_bound(*bound);
                b.set_cumulative_count(*count);
                b
            })
            .collect();
        let mut hist = Histogram::default();
        hist.set_bucket(buckets);
        // The counters are read one by one while the bus keeps counting: the
        // count must never be below the last bucket, or the +Inf bucket would
        // go down.
        let last = h.cumulative.last().copied().unwrap_or(0);
        hist.set_sample_count(h.count.max(last));
        hist.set_sample_sum(h.sum);
        metric.set_histogram(hist);
        self.mf.mut_metric().push(metric);
    }

    /// The family, for the registry (empty families are left out of the
    /// output by the registry).
    pub(crate) fn finish(self) -> MetricFamily {
        self.mf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    static GAUGE: Spec = Spec {
        name: "drivegate_test_volts",
        help: "A test gauge.",
        kind: Kind::Gauge,
        labels: &["bus", "unit"],
    };
    static HIST: Spec = Spec {
        name: "drivegate_test_seconds",
        help: "A test histogram.",
        kind: Kind::Histogram,
        labels: &["bus"],
    };

    #[test]
    fn gauge_samples_carry_their_labels_in_order() {
        let mut f = GAUGE.family();
        f.set(&["line1", "3"], 24.0);
        let mf = f.finish();
        assert_eq!(mf.name(), "drivegate_test_volts");
        assert_eq!(mf.get_field_type(), MetricType::GAUGE);
        let m = &mf.get_metric()[0];
        let labels: Vec<(&str, &str)> = m
            .get_label()
            .iter()
            .map(|l| (l.name(), l.value()))
            .collect();
        assert_eq!(labels, [("bus", "line1"), ("unit", "3")]);
        assert_eq!(m.get_gauge().get_value(), 24.0);
    }

    #[test]
    fn histogram_count_never_below_its_last_bucket() {
        let mut f = HIST.family();
        let snap = HistogramSnapshot {
            bounds: &[0.1, 1.0],
            cumulative: vec![2, 5],
            sum: 1.5,
            count: 4, // read before an observation that the buckets include
        };
        f.set_histogram(&["line1"], &snap);
        let mf = f.finish();
        let h = mf.get_metric()[0].get_histogram();
        assert_eq!(h.get_sample_count(), 5);
        assert_eq!(h.get_bucket().len(), 2);
        assert_eq!(h.get_bucket()[1].cumulative_count(), 5);
    }
}
