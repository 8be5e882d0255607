//! The alarm list as a bus's follower: a drive's fault, a drive that
//! stops answering, a port that fails, raised and cleared from the bus's
//! events in the task every follower of the bus shares.

use std::sync::Arc;

use super::Alarms;
use crate::bus::{BusEvent, BusFollower};
use crate::plant::Plant;

/// The alarm list as a bus's follower: each event raises or clears what it
/// says, in the task every follower of the bus shares.
pub(super) struct Follower {
    pub(super) alarms: Arc<Alarms>,
    pub(super) plant: Arc<Plant>,
    pub(super) index: usize,
}

impl BusFollower for Follower {
    fn event(&self, event: &BusEvent) {
        self.alarms.bus_event(&self.plant, self.index, event);
    }

    fn lagged(&self, missed: u64) {
        tracing::warn!("the alarm list fell {missed} bus events behind");
    }
}
