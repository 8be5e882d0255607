//! The edge node's births and deaths follow the core's freshness of each
//! drive's data ([`crate::control::freshness`]): a host must not hold a
//! value as good that the daemon does not have. A drive that stops
//! answering, that never answered, or whose bus's port is gone gets a
//! DDEATH; a drive whose data is live again gets its DBIRTH (with the
//! status just read). `stale` (polls missing, not yet offline) changes
//! nothing at the host: the DDEATH follows if the drive goes offline.

use tokio::sync::broadcast::error::RecvError;

use super::{Connection, Kind, Node};
use crate::bus::freshness::Freshness;
use crate::control::{ControlEvent, Published};

impl Node {
    /// The core's news: freshness changes are followed; a lagging
    /// receiver looks at every drive again.
    pub(super) fn on_control(
        &mut self,
        c: Option<&Connection>,
        published: Result<Published, RecvError>,
    ) {
        match published {
            Ok(p) => {
                if let ControlEvent::Freshness(news) = p.event.as_ref() {
                    self.follow_freshness(c, news.drive);
                }
            }
            Err(RecvError::Lagged(_)) => {
                let slots = self.control.plant().now().drive_slots();
                for drive in 0..slots {
                    self.follow_freshness(c, drive);
                }
            }
            Err(RecvError::Closed) => {}
        }
    }

    /// True while the data of `unit` on bus `bus` is live.
    pub(super) fn is_live(&self, bus: &str, unit: u8) -> bool {
        self.control
            .plant()
            .bus(bus)
            .and_then(|b| b.handle.freshness(unit))
            .is_some_and(|v| v.freshness.is_live())
    }

    /// Births or kills the device of drive slot `drive` as its data's
    /// freshness is now (not as the news said: the news may be older than
    /// the statuses already handled).
    fn follow_freshness(&mut self, c: Option<&Connection>, drive: usize) {
        let plant = self.control.plant().now();
        let Some(d) = plant.drive_at(drive) else {
            return;
        };
        let Some(handle) = plant.handle_of(d) else {
            return;
        };
        let name = d.name.clone();
        let freshness = handle
            .freshness(d.unit)
            .map_or(Freshness::Never, |v| v.freshness);
        let born = self.devices.get(&name).is_some_and(|dev| dev.born);
        match freshness {
            Freshness::Live => {
                if !born
                    && self.born
                    && let Some(c) = c
                    && let Some(status) = handle.drive(d.unit).and_then(|s| s.status)
                {
                    self.device_birth(c, &name, Some(&status));
                }
            }
            Freshness::Stale => {}
            Freshness::Offline | Freshness::Never | Freshness::BusDown => {
                if !born {
                    return;
                }
                if let Some(c) = c
                    && self.born
                {
                    let payload = self.payload(Vec::new());
                    let topic = self.topics.device_topic(Kind::DDeath, &name);
                    let _ = self.publish(c, topic, payload, Kind::DDeath);
                }
                if let Some(dev) = self.devices.get_mut(&name) {
                    dev.born = false;
                }
            }
        }
    }
}
