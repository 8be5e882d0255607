//! One drive's status history, pure: time passed in (Unix ms), no I/O.
//!
//! Two rings of fixed-size records, each with a fixed capacity, so the
//! memory of a drive's history is known before it fills:
//!
//! - the recent samples at full rate, as polled ([`Sample`], 24 bytes):
//!   `full_rate_samples` of them;
//! - one-second buckets over the whole window ([`Bucket`], 48 bytes): the
//!   number of samples, the minimum, maximum and mean of each field kept
//!   ([`KEPT`]), and the flags seen (OR), `window_ms / 1000` of them.
//!
//! A query answers from the full-rate ring as far back as it reaches and
//! from the buckets before that, oldest first, as [`Point`]s.

use std::collections::VecDeque;

use crate::drive::{Status, StatusField};

/// A bucket's width, ms.
pub const BUCKET_MS: i64 = 1000;

/// The fields kept, in the order of a record's arrays: the status
/// block's measurements but `turns`, a counter that wraps (its minimum,
/// maximum and mean would mean nothing).
pub const KEPT: [StatusField; FIELDS] = [
    StatusField::SpeedRpm,
    StatusField::CurrentA,
    StatusField::VoltageV,
    StatusField::TemperatureC,
    StatusField::AngleDeg,
];

/// Fields per record.
pub const FIELDS: usize = 5;

/// Where `field` is in a record's arrays, if it is kept.
pub fn slot(field: StatusField) -> Option<usize> {
    KEPT.iter().position(|f| *f == field)
}

/// The register of `field` in a status, as a record keeps it (a voltage
/// past 32767 V kept as 32767).
fn raw_of(field: StatusField, s: &Status) -> i16 {
    field
        .counts(s)
        .map_or(0, |c| i16::try_from(c).unwrap_or(i16::MAX))
}

/// One status as polled: 24 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    /// When it was read, Unix ms.
    pub t_ms: i64,
    /// The status.
    pub status: Status,
}

/// One second of a drive's statuses: 48 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bucket {
    /// Its start, Unix ms (a multiple of [`BUCKET_MS`]).
    pub t_ms: i64,
    /// Samples in it.
    pub n: u16,
    /// Every STATUS flag seen in it (OR).
    pub flags_any: u16,
    /// Minimum of each field, raw.
    pub min: [i16; FIELDS],
    /// Maximum of each field, raw.
    pub max: [i16; FIELDS],
    /// Mean of each field, raw, rounded.
    pub mean: [i16; FIELDS],
}

/// A bucket being filled.
#[derive(Debug, Clone, Copy)]
struct Filling {
    t_ms: i64,
    n: u32,
    flags_any: u16,
    min: [i16; FIELDS],
    max: [i16; FIELDS],
    sum: [i64; FIELDS],
}

impl Filling {
    fn new(t_ms: i64, s: &Status) -> Self {
        let raw = KEPT.map(|f| raw_of(f, s));
        Filling {
            t_ms,
            n: 1,
            flags_any: s.flags,
            min: raw,
            max: raw,
            sum: raw.map(i64::from),
        }
    }

    fn add(&mut self, s: &Status) {
        self.n += 1;
        self.flags_any |= s.flags;
        for (i, f) in KEPT.into_iter().enumerate() {
            let v = raw_of(f, s);
            self.min[i] = self.min[i].min(v);
            self.max[i] = self.max[i].max(v);
            self.sum[i] += i64::from(v);
        }
    }

    fn bucket(&self) -> Bucket {
        let n = i64::from(self.n.max(1));
        Bucket {
            t_ms: self.t_ms,
            n: u16::try_from(self.n).unwrap_or(u16::MAX),
            flags_any: self.flags_any,
            min: self.min,
            max: self.max,
            mean: self
                .sum
                .map(|s| i16::try_from((2 * s + n).div_euclid(2 * n)).unwrap_or(0)),
        }
    }
}

/// What a history keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Samples kept at full rate.
    pub full_rate_samples: usize,
    /// One-second buckets kept (the window, in seconds).
    pub buckets: usize,
}

impl Limits {
    /// The most a drive's history takes, bytes.
    pub fn bytes_per_drive(&self) -> usize {
        self.full_rate_samples * std::mem::size_of::<Sample>()
            + self.buckets * std::mem::size_of::<Bucket>()
    }

    fn window_ms(&self) -> i64 {
        i64::try_from(self.buckets).unwrap_or(i64::MAX / BUCKET_MS) * BUCKET_MS
    }
}

/// A point of a query's answer: one sample (`span_ms` 0) or one bucket.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// Its time (a bucket's start), Unix ms.
    pub t_ms: i64,
    /// The time it covers, ms (0: one sample).
    pub span_ms: i64,
    /// Samples in it.
    pub n: u32,
    /// Every STATUS flag seen in it.
    pub flags_any: u16,
    /// Minimum of each field, raw.
    pub min: [i16; FIELDS],
    /// Maximum of each field, raw.
    pub max: [i16; FIELDS],
    /// Mean of each field, raw.
    pub mean: [f64; FIELDS],
}

impl Point {
    /// `field`'s lowest value in this point, in its unit (`None`: a field
    /// not kept).
    pub fn min_of(&self, field: StatusField) -> Option<f64> {
        slot(field).map(|i| field.from_counts(f64::from(self.min[i])))
    }

    /// `field`'s highest value in this point, in its unit.
    pub fn max_of(&self, field: StatusField) -> Option<f64> {
        slot(field).map(|i| field.from_counts(f64::from(self.max[i])))
    }

    /// The mean of `field` over this point's samples, in its unit.
    pub fn mean_of(&self, field: StatusField) -> Option<f64> {
        slot(field).map(|i| field.from_counts(self.mean[i]))
    }

    fn of_sample(s: &Sample) -> Self {
        let raw = KEPT.map(|f| raw_of(f, &s.status));
        Point {
            t_ms: s.t_ms,
            span_ms: 0,
            n: 1,
            flags_any: s.status.flags,
            min: raw,
            max: raw,
            mean: raw.map(f64::from),
        }
    }

    fn of_bucket(b: &Bucket) -> Self {
        Point {
            t_ms: b.t_ms,
            span_ms: BUCKET_MS,
            n: u32::from(b.n),
            flags_any: b.flags_any,
            min: b.min,
            max: b.max,
            mean: b.mean.map(f64::from),
        }
    }

    /// Points merged into one: the extremes of their extremes, the mean of
    /// their samples.
    fn merge(points: &[Point]) -> Option<Point> {
        let (first, last) = (points.first()?, points.last()?);
        let mut out = *first;
        out.span_ms = last.t_ms + last.span_ms - first.t_ms;
        let mut sums = first.mean.map(|m| m * f64::from(first.n));
        for p in &points[1..] {
            out.n += p.n;
            out.flags_any |= p.flags_any;
            for (i, sum) in sums.iter_mut().enumerate() {
                out.min[i] = out.min[i].min(p.min[i]);
                out.max[i] = out.max[i].max(p.max[i]);
                *sum += p.mean[i] * f64::from(p.n);
            }
        }
        let n = f64::from(out.n.max(1));
        out.mean = sums.map(|s| s / n);
        Some(out)
    }
}

/// A ring of at most `cap` records that grows as it fills, never past
/// `cap`.
#[derive(Debug, Clone)]
struct Ring<T> {
    items: VecDeque<T>,
    cap: usize,
}

impl<T> Ring<T> {
    fn new(cap: usize) -> Self {
        Ring {
            items: VecDeque::new(),
            cap: cap.max(1),
        }
    }

    fn push(&mut self, item: T) {
        if self.items.len() == self.cap {
            self.items.pop_front();
        } else if self.items.len() == self.items.capacity() {
            // Grow by doubling, but never past the cap.
            let more = self.items.len().max(16).min(self.cap - self.items.len());
            self.items.reserve_exact(more);
        }
        self.items.push_back(item);
    }

    fn bytes(&self) -> usize {
        self.items.capacity() * std::mem::size_of::<T>()
    }
}

/// One drive's history.
#[derive(Debug, Clone)]
pub struct DriveHistory {
    limits: Limits,
    samples: Ring<Sample>,
    buckets: Ring<Bucket>,
    filling: Option<Filling>,
}

impl DriveHistory {
    /// An empty history keeping `limits`.
    pub fn new(limits: Limits) -> Self {
        DriveHistory {
            limits,
            samples: Ring::new(limits.full_rate_samples),
            buckets: Ring::new(limits.buckets),
            filling: None,
        }
    }

    /// Keeps a status read at `t_ms`.
    pub fn push(&mut self, t_ms: i64, status: Status) {
        self.samples.push(Sample { t_ms, status });
        let start = t_ms.div_euclid(BUCKET_MS) * BUCKET_MS;
        match &mut self.filling {
            // A clock stepped back: the sample joins the bucket being filled.
            Some(f) if start <= f.t_ms => f.add(&status),
            Some(f) => {
                let done = f.bucket();
                self.buckets.push(done);
                self.filling = Some(Filling::new(start, &status));
            }
            None => self.filling = Some(Filling::new(start, &status)),
        }
        // Buckets older than the window go, also across a gap in polling.
        let oldest = t_ms - self.limits.window_ms();
        while self
            .buckets
            .items
            .front()
            .is_some_and(|b| b.t_ms + BUCKET_MS <= oldest)
        {
            self.buckets.items.pop_front();
        }
    }

    /// The points from `since_ms` to `until_ms` (both included), oldest
    /// first: full-rate samples as far back as they reach, buckets before
    /// that, nothing older than the window before `now_ms`; merged down to
    /// at most `max_points` when there are more.
    pub fn query(
        &self,
        since_ms: i64,
        until_ms: i64,
        now_ms: i64,
        max_points: usize,
    ) -> Vec<Point> {
        let since = since_ms.max(now_ms - self.limits.window_ms());
        // Buckets end and samples begin at the oldest sample, or, once the
        // ring has let older samples go, at the first bucket boundary after
        // it: that bucket holds the reads the ring let go, so every read is
        // counted once, in its bucket or as a sample.
        let full_from = match self.samples.items.front() {
            None => i64::MAX,
            Some(s) if self.samples.items.len() < self.samples.cap => s.t_ms,
            Some(s) => (s.t_ms + BUCKET_MS - 1).div_euclid(BUCKET_MS) * BUCKET_MS,
        };
        let mut points: Vec<Point> = self
            .buckets
            .items
            .iter()
            .chain(self.filling.as_ref().map(Filling::bucket).as_ref())
            .filter(|b| b.t_ms > since - BUCKET_MS && b.t_ms <= until_ms)
            .filter(|b| b.t_ms + BUCKET_MS <= full_from)
            .map(Point::of_bucket)
            .collect();
        points.extend(
            self.samples
                .items
                .iter()
                .filter(|s| s.t_ms >= since.max(full_from) && s.t_ms <= until_ms)
                .map(Point::of_sample),
        );
        merge_to(points, max_points)
    }

    /// Memory taken now, bytes (at most [`Limits::bytes_per_drive`]).
    pub fn bytes(&self) -> usize {
        self.samples.bytes() + self.buckets.bytes()
    }

    /// Samples at full rate held.
    pub fn samples(&self) -> usize {
        self.samples.items.len()
    }

    /// Buckets held.
    pub fn buckets(&self) -> usize {
        self.buckets.items.len()
    }
}

/// `points` merged in runs of equal length so that at most `max` remain.
fn merge_to(points: Vec<Point>, max: usize) -> Vec<Point> {
    let max = max.max(1);
    if points.len() <= max {
        return points;
    }
    let per = points.len().div_ceil(max);
    points.chunks(per).filter_map(Point::merge).collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn status(speed: i16, temp: i16, flags: u16) -> Status {
        Status {
            speed_rpm: speed,
            temperature_c: temp,
            voltage_v: 24,
            current_counts: 128,
            flags,
            ..Status::default()
        }
    }

    const HOUR: Limits = Limits {
        full_rate_samples: 6000,
        buckets: 3600,
    };

    #[test]
    fn records_have_the_sizes_the_memory_bound_is_stated_with() {
        assert_eq!(std::mem::size_of::<Sample>(), 24);
        assert_eq!(std::mem::size_of::<Bucket>(), 48);
        assert_eq!(HOUR.bytes_per_drive(), 6000 * 24 + 3600 * 48);
    }

    #[test]
    fn an_hour_at_fifty_hertz_is_served_whole_within_its_bound() {
        let mut h = DriveHistory::new(HOUR);
        let start = 1_790_000_000_000_i64;
        // 65 minutes at 50 Hz: speed ramps 0..=999 every 1000 samples
        // (20 s), temperature a step each minute; a stall flag in minute 30.
        let n = 65 * 60 * 50;
        for i in 0..n {
            let t = start + i * 20;
            let minute = i / 3000;
            let flags = if minute == 30 { 0x20 } else { 0x80 };
            h.push(t, status((i % 1000) as i16, 30 + minute as i16, flags));
            assert!(h.bytes() <= HOUR.bytes_per_drive());
        }
        let now = start + (n - 1) * 20;
        assert_eq!(h.samples(), 6000);
        assert_eq!(h.buckets(), 3600);
        assert_eq!(h.bytes(), HOUR.bytes_per_drive());

        let points = h.query(i64::MIN, i64::MAX, now, usize::MAX);
        // The last 2 minutes at full rate, the hour's rest in buckets.
        let full: Vec<_> = points.iter().filter(|p| p.span_ms == 0).collect();
        let buckets: Vec<_> = points.iter().filter(|p| p.span_ms == BUCKET_MS).collect();
        assert_eq!(full.len(), 6000);
        assert_eq!(full[0].t_ms, now - 5999 * 20);
        assert!(
            buckets.len() >= 3600 - 121 && buckets.len() <= 3600,
            "{}",
            buckets.len()
        );
        // Oldest first, and nothing older than the hour.
        assert!(points.windows(2).all(|w| w[0].t_ms < w[1].t_ms));
        assert!(points[0].t_ms >= now - 3_600_000 - BUCKET_MS);
        assert!(buckets.last().unwrap().t_ms + BUCKET_MS <= full[0].t_ms);
        // A bucket holds 50 samples of a 0..999 ramp's stretch: min, max
        // and mean as they were.
        let b = buckets[100];
        assert_eq!(b.n, 50);
        let speed = slot(StatusField::SpeedRpm).unwrap();
        assert_eq!(i32::from(b.max[speed]) - i32::from(b.min[speed]), 49);
        let mid = (f64::from(b.min[speed]) + f64::from(b.max[speed])) / 2.0;
        assert!((b.mean[speed] - mid).abs() <= 0.5, "{b:?}");
        assert_eq!(b.mean_of(StatusField::CurrentA), Some(1.0));
        assert_eq!(b.mean_of(StatusField::Turns), None);
        // The stall of minute 30 is in its buckets' flags.
        let stall_minute = start + 30 * 60_000;
        assert!(
            buckets
                .iter()
                .filter(|p| p.t_ms >= stall_minute && p.t_ms < stall_minute + 60_000)
                .all(|p| p.flags_any & 0x20 != 0)
        );
    }

    #[test]
    fn a_query_takes_its_range_and_merges_down_to_max_points() {
        let mut h = DriveHistory::new(Limits {
            full_rate_samples: 100,
            buckets: 600,
        });
        let start = 1_000_000;
        for i in 0..3000 {
            // 10 Hz for 300 s.
            h.push(start + i * 100, status(i as i16, 40, 0));
        }
        let now = start + 2999 * 100;
        // The last 10 s are at full rate.
        let last = h.query(now - 9_900, now, now, 1000);
        assert_eq!(last.len(), 100);
        assert!(last.iter().all(|p| p.span_ms == 0));
        // A minute in the middle: 60 buckets of 10 samples.
        let minute = h.query(start + 60_000, start + 119_999, now, 1000);
        assert_eq!(minute.len(), 60);
        assert!(minute.iter().all(|p| p.n == 10));
        // Merged to 6 points of 10 s each.
        let merged = h.query(start + 60_000, start + 119_999, now, 6);
        assert_eq!(merged.len(), 6);
        assert!(merged.iter().all(|p| p.n == 100 && p.span_ms == 10_000));
        let s = slot(StatusField::SpeedRpm).unwrap();
        assert_eq!((merged[0].min[s], merged[0].max[s]), (600, 699));
        assert!((merged[0].mean[s] - 649.5).abs() < 0.6);
        // Outside what is kept: nothing.
        assert!(h.query(0, start - 1, now, 10).is_empty());
    }

    #[test]
    fn every_read_is_counted_once_as_the_full_rate_ring_moves_on() {
        // 1.5 s at full rate: the ring's oldest sample is mostly inside a
        // bucket, whose other reads the ring has let go.
        let mut h = DriveHistory::new(Limits {
            full_rate_samples: 15,
            buckets: 600,
        });
        let start = 1_000_050;
        let mut counted = 0;
        for i in 0..80 {
            let now = start + i * 100;
            h.push(now, status(i as i16, 40, 0));
            let points = h.query(i64::MIN, i64::MAX, now, usize::MAX);
            let n: u32 = points.iter().map(|p| p.n).sum();
            assert_eq!(i64::from(n), i + 1, "after read {i}: {points:?}");
            assert!(
                points
                    .windows(2)
                    .all(|w| w[0].t_ms + w[0].span_ms <= w[1].t_ms)
            );
            counted = n;
        }
        assert_eq!(counted, 80);
    }

    #[test]
    fn a_gap_in_polling_and_a_clock_stepping_back_are_handled() {
        let mut h = DriveHistory::new(Limits {
            full_rate_samples: 10,
            buckets: 60,
        });
        h.push(1_000, status(1, 20, 0));
        h.push(2_000, status(2, 20, 0));
        // Offline for two minutes: the old buckets fall out of the window.
        h.push(200_000, status(3, 20, 0));
        assert_eq!(h.buckets(), 0);
        // The clock steps back half a second: same bucket, no panic.
        h.push(199_500, status(4, 20, 0));
        h.push(201_000, status(5, 20, 0));
        // Samples older than the window are not served, though still held.
        let points = h.query(0, i64::MAX, 201_000, 100);
        assert_eq!(points.iter().filter(|p| p.span_ms == 0).count(), 3);
        assert_eq!(h.samples(), 5);
    }
}
