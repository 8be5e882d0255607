//! The alarm list as a bus's follower: a drive's fault, a drive that
//! stops answering, a port that fails, raised and cleared from the bus's
//! events in the task every follower of the bus shares. It is handed what
//! to do with each event (the alarm list's `bus_event`), so it stands
//! below the list and names nothing of it.

use crate::bus::{BusEvent, BusFollower};

/// Calls its function at each event of the bus.
pub(super) struct Follower<F>(pub(super) F);

impl<F: Fn(&BusEvent) + Send + Sync> BusFollower for Follower<F> {
    fn event(&self, event: &BusEvent) {
        (self.0)(event);
    }

    fn lagged(&self, missed: u64) {
        tracing::warn!("the alarm list fell {missed} bus events behind");
    }
}
