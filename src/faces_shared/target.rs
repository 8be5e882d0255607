//! A drive named by a client, resolved: its slot in the plant and its bus.

use super::problem::Problem;
use crate::bus::BusHandle;
use crate::control;
use crate::plant::{Drive, Plant};

/// A drive resolved from a name: its slot in the plant and its bus.
#[derive(Clone)]
pub struct Target {
    /// Its slot in the plant's directory (the key of leases and
    /// subscriptions).
    pub index: usize,
    /// The drive.
    pub drive: Drive,
    /// Its bus.
    pub bus: BusHandle,
}

impl Target {
    /// The drive named `key` (or, on a single bus, with that unit number).
    pub fn find(plant: &Plant, key: &str) -> Result<Target, Problem> {
        let (index, drive, bus) = plant.find(key).map_err(|e| Problem::lookup(&e))?;
        Ok(Target { index, drive, bus })
    }

    /// The drive in slot `index` of the plant, if it is still configured.
    pub fn at(plant: &Plant, index: usize) -> Option<Target> {
        let now = plant.now();
        let drive = now.drive_at(index)?;
        Some(Target {
            index,
            bus: now.handle_of(drive)?.clone(),
            drive: drive.clone(),
        })
    }

    /// Where the control core sends its writes.
    pub fn control(&self) -> control::Target {
        control::Target {
            bus: self.drive.bus,
            unit: self.drive.unit,
            drive: Some(self.index),
        }
    }
}
