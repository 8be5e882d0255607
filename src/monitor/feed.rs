//! A live monitor client's place in the ring: it reads behind the bus
//! thread at its own pace and counts the frames it lost by reading too
//! slowly (overwritten before it got to them). Frames its filter leaves
//! out are not lost.

use std::sync::Arc;

use super::BusMonitor;
use super::filter::FrameFilter;
use super::record::FrameRecord;

/// What one poll brought.
#[derive(Debug, Default)]
pub struct Batch {
    /// New frames that passed the filter, in order.
    pub frames: Vec<FrameRecord>,
    /// Frames lost since the last poll (overwritten before they were read).
    pub lost: u64,
}

/// A live client of one bus's monitor; counted as connected while it lives.
pub struct Feed {
    monitor: Arc<BusMonitor>,
    cursor: u64,
    filter: FrameFilter,
    scratch: Vec<FrameRecord>,
}

impl Feed {
    /// A client that starts with the last `backlog` frames, then gets every
    /// new one that passes `filter`.
    pub fn new(monitor: Arc<BusMonitor>, filter: FrameFilter, backlog: usize) -> Self {
        monitor.client_joined();
        let head = monitor.ring().map_or(0, |r| r.head());
        Self {
            cursor: head.saturating_sub(backlog as u64),
            monitor,
            filter,
            scratch: Vec::new(),
        }
    }

    /// Replaces the filter (from the next frame on).
    pub fn set_filter(&mut self, filter: FrameFilter) {
        self.filter = filter;
    }

    /// The monitor it reads.
    pub fn monitor(&self) -> &Arc<BusMonitor> {
        &self.monitor
    }

    /// The filter in force.
    pub fn filter(&self) -> &FrameFilter {
        &self.filter
    }

    /// Sequence number of the next frame this client reads.
    pub fn cursor(&self) -> u64 {
        self.cursor
    }

    /// Reads up to `max` new frames (before filtering).
    pub fn poll(&mut self, max: usize) -> Batch {
        let Some(ring) = self.monitor.ring() else {
            return Batch::default();
        };
        self.scratch.clear();
        let report = ring.read(&mut self.cursor, max, &mut self.scratch);
        if report.lost > 0 {
            self.monitor.add_lost(report.lost);
        }
        Batch {
            frames: self
                .scratch
                .drain(..)
                .filter(|r| self.filter.accepts(r))
                .collect(),
            lost: report.lost,
        }
    }

    /// True when frames are waiting.
    pub fn has_news(&self) -> bool {
        self.monitor.ring().is_some_and(|r| r.head() > self.cursor)
    }
}

impl Drop for Feed {
    fn drop(&mut self) {
        self.monitor.client_left();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::timing::LineTiming;
    use crate::monitor::MonitorSettings;

    #[test]
    fn a_client_that_reads_too_slowly_loses_the_oldest_and_is_told() {
        let monitor = Arc::new(BusMonitor::new(
            MonitorSettings {
                enabled: true,
                ring_frames: 8,
            },
            LineTiming::new_8n1(115_200),
            vec![1, 2],
        ));
        let ring = monitor.ring().unwrap();
        for i in 0..4u8 {
            ring.push(|r| r.unit = 1 + i % 2);
        }
        let filter = FrameFilter {
            units: vec![2],
            ..FrameFilter::default()
        };
        let mut feed = Feed::new(monitor.clone(), filter, 4);
        assert_eq!(monitor.clients(), 1);
        let batch = feed.poll(100);
        assert_eq!(batch.frames.len(), 2, "the backlog, filtered: units 2 only");
        assert_eq!(batch.lost, 0);
        // It stops reading while 20 frames go by: 12 of them are lost.
        for i in 0..20u8 {
            ring.push(|r| r.unit = 1 + i % 2);
        }
        assert!(feed.has_news());
        let batch = feed.poll(100);
        assert_eq!(batch.lost, 12);
        assert_eq!(batch.frames.len(), 4);
        assert_eq!(monitor.lost(), 12);
        drop(feed);
        assert_eq!(monitor.clients(), 0);
    }
}
