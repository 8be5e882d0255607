//! What the core's parts work with, below them all: the plant, the lease
//! driver, the events and `[safety]`'s lease settings, with what a part
//! asks of them (a target's bus, a drive's name). [`super::Control`] holds
//! one and hands it to the write path, settings documents, drift and
//! reloads, so that none of them stands on the handle above it.

use std::sync::{Arc, RwLock};
use std::time::Duration;

use tokio::sync::broadcast;

use super::events::{Events, Published};
use super::leases::Leases;
use super::request::Target;
use super::rules::LeaseBounds;
use crate::bus::{BusError, BusHandle};
use crate::control::stop_action::SafetyConfig;
use crate::plant::Plant;

/// `[safety]`'s settings of leases, which a reload may change.
#[derive(Debug, Clone, Copy)]
struct Settings {
    jog_lease: Duration,
    lease_bounds: LeaseBounds,
}

impl Settings {
    fn of(safety: &SafetyConfig) -> Self {
        Settings {
            jog_lease: Duration::from_millis(safety.jog_lease_ms),
            lease_bounds: LeaseBounds {
                min: Duration::from_millis(safety.lease_min_ms),
                max: Duration::from_millis(safety.lease_max_ms),
            },
        }
    }
}

/// The parts every write and every reload goes through.
pub(super) struct Parts {
    plant: Arc<Plant>,
    leases: Arc<Leases>,
    events: Arc<Events>,
    /// `[safety]`'s lease settings, as last loaded.
    settings: RwLock<Settings>,
}

impl Parts {
    pub(super) fn new(
        plant: Arc<Plant>,
        leases: Arc<Leases>,
        events: Arc<Events>,
        safety: &SafetyConfig,
    ) -> Self {
        Parts {
            plant,
            leases,
            events,
            settings: RwLock::new(Settings::of(safety)),
        }
    }

    /// Buses and drives.
    pub(super) fn plant(&self) -> &Arc<Plant> {
        &self.plant
    }

    /// The lease driver.
    pub(super) fn leases(&self) -> &Arc<Leases> {
        &self.leases
    }

    /// The core's events.
    pub(super) fn events(&self) -> &Arc<Events> {
        &self.events
    }

    /// Every future event of the core.
    pub(super) fn subscribe(&self) -> broadcast::Receiver<Published> {
        self.events.subscribe()
    }

    fn settings(&self) -> Settings {
        *self.settings.read().unwrap_or_else(|p| p.into_inner())
    }

    /// The lease a console jog asks for (`[safety] jog_lease_ms`).
    pub(super) fn jog_lease(&self) -> Duration {
        self.settings().jog_lease
    }

    /// The shortest and longest lease a setpoint may ask for.
    pub(super) fn lease_bounds(&self) -> LeaseBounds {
        self.settings().lease_bounds
    }

    /// Applies `[safety]`'s lease bounds, jog lease and lease-expiry action
    /// to leases granted from now on.
    pub(super) fn set_safety(&self, safety: &SafetyConfig) {
        *self.settings.write().unwrap_or_else(|p| p.into_inner()) = Settings::of(safety);
        self.leases
            .with(|book, _| (book.set_action(safety.on_lease_expiry), Vec::new()));
    }

    /// The bus a write to `target` goes on.
    pub(super) fn bus(&self, target: Target) -> Result<BusHandle, BusError> {
        self.plant
            .now()
            .bus_at(target.bus)
            .map(|b| b.handle.clone())
            .ok_or_else(|| BusError::Invalid(format!("no bus at index {}", target.bus)))
    }

    /// The drive at `target` in words: `drive "lift"` or `unit 7 on bus line1`.
    pub(super) fn name(&self, target: Target) -> String {
        let now = self.plant.now();
        match target.drive.and_then(|d| now.drive_at(d)) {
            Some(d) => format!("drive \"{}\"", d.name),
            None => {
                let bus = now.bus_at(target.bus).map_or("?", |b| b.handle.name());
                format!("unit {} on bus {bus}", target.unit)
            }
        }
    }

    /// `unit` on bus `bus` (0: a broadcast), configured or not.
    pub(super) fn unit_target(&self, bus: usize, unit: u8) -> Target {
        let drive = (unit != 0)
            .then(|| {
                self.plant
                    .now()
                    .indexed_drives()
                    .find(|(_, d)| d.bus == bus && d.unit == unit)
                    .map(|(i, _)| i)
            })
            .flatten();
        Target { bus, unit, drive }
    }

    /// The name of drive `drive` (empty when it is not configured).
    pub(super) fn drive_name(&self, drive: usize) -> String {
        self.plant
            .now()
            .drive_at(drive)
            .map_or_else(String::new, |d| d.name.clone())
    }
}
