//! The plant: every configured bus (with its simulator, if simulated) and
//! the directory of drives by name. The faces resolve a drive here and then
//! talk to its bus through the bus's handle.

use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use tracing::{info, warn};

use crate::bus::{BusHandle, Observers};
use crate::config::{BusConfig, Config, Declared};
use crate::monitor::BusMonitor;
use crate::scope::Scope;
use crate::sim::{SimHandle, Simulator};

/// One running bus.
pub struct Bus {
    /// Its configuration.
    pub config: BusConfig,
    /// Its handle.
    pub handle: BusHandle,
    /// The built-in simulator behind it, for `port = "sim"`.
    pub sim: Option<SimHandle>,
    monitor: Arc<BusMonitor>,
    scope: Arc<Scope>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl Bus {
    /// Its monitor: the last frames on the wire, the per-attempt counters.
    pub fn monitor(&self) -> &Arc<BusMonitor> {
        &self.monitor
    }

    /// Its scope's capture slot. After arming a capture,
    /// [`wake`](BusHandle::wake) the bus so its polling follows at once.
    pub fn scope(&self) -> &Arc<Scope> {
        &self.scope
    }
}

/// One configured drive.
#[derive(Debug, Clone, PartialEq)]
pub struct Drive {
    /// Its unique name.
    pub name: String,
    /// Index of its bus in [`Plant::buses`].
    pub bus: usize,
    /// Its unit address.
    pub unit: u8,
    /// Its gearbox ratio.
    pub gear_ratio: f64,
    /// The settings it must hold (`[bus.drive.settings]`), if declared.
    pub declared: Option<Declared>,
}

/// Why the plant could not start.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    /// The simulator of a bus did not start.
    #[error("bus {bus}: cannot start the simulator: {source}")]
    Simulator {
        /// Bus name.
        bus: String,
        /// Cause.
        source: std::io::Error,
    },
    /// The bus thread did not start.
    #[error("bus {bus}: cannot start: {source}")]
    Bus {
        /// Bus name.
        bus: String,
        /// Cause.
        source: std::io::Error,
    },
}

/// Why a drive could not be found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LookupError {
    /// No drive has that name (or unit).
    #[error("no drive named \"{0}\" is configured")]
    Unknown(String),
    /// A unit number was given but several buses are configured.
    #[error("\"{0}\" is a unit number, but several buses are configured: use the drive's name")]
    Ambiguous(String),
}

/// All buses and drives of the daemon.
pub struct Plant {
    buses: Vec<Bus>,
    drives: Vec<Drive>,
}

impl Plant {
    /// Starts every bus of `config` (and its simulator).
    pub fn start(config: &Config) -> Result<Plant, PlantError> {
        let mut buses = Vec::new();
        let mut drives = Vec::new();
        for (index, bus_config) in config.buses.iter().enumerate() {
            let name = bus_config.name().to_string();
            let sim = if bus_config.is_simulated() {
                let sim = Simulator::start(bus_config.sim_config()).map_err(|source| {
                    PlantError::Simulator {
                        bus: name.clone(),
                        source,
                    }
                })?;
                info!(bus = %name, pty = %sim.port_path().display(), "built-in simulator running");
                Some(sim)
            } else {
                None
            };
            let port = match &sim {
                Some(sim) => sim.port_path().display().to_string(),
                None => bus_config.port.get_ref().clone(),
            };
            let mut settings = bus_config.settings(&port);
            let units: Vec<u8> = bus_config.drives.iter().map(|d| d.unit()).collect();
            let line = settings.master.line;
            let monitor = Arc::new(BusMonitor::new(
                config.monitor.settings(),
                line,
                units.clone(),
            ));
            let scope = Arc::new(Scope::new(config.scope.settings(), line, units));
            settings.observers = Observers {
                wire: vec![monitor.clone(), scope.clone()],
                steering: Some(scope.clone()),
            };
            let (handle, thread) =
                crate::bus::scheduler::spawn(settings).map_err(|source| PlantError::Bus {
                    bus: name.clone(),
                    source,
                })?;
            for d in &bus_config.drives {
                drives.push(Drive {
                    name: d.name().to_string(),
                    bus: index,
                    unit: d.unit(),
                    gear_ratio: d.gear_ratio,
                    declared: d.declared(),
                });
            }
            buses.push(Bus {
                config: bus_config.clone(),
                handle,
                sim,
                monitor,
                scope,
                thread: Mutex::new(Some(thread)),
            });
        }
        Ok(Plant { buses, drives })
    }

    /// Every bus, in configuration order.
    pub fn buses(&self) -> &[Bus] {
        &self.buses
    }

    /// The bus with this name.
    pub fn bus(&self, name: &str) -> Option<&Bus> {
        self.buses.iter().find(|b| b.handle.name() == name)
    }

    /// Every drive, in configuration order.
    pub fn drives(&self) -> &[Drive] {
        &self.drives
    }

    /// A drive by name or, with a single bus, by unit number.
    pub fn drive(&self, key: &str) -> Result<(&Drive, &BusHandle), LookupError> {
        if let Some(d) = self.drives.iter().find(|d| d.name == key) {
            return Ok((d, &self.buses[d.bus].handle));
        }
        if let Ok(unit) = key.parse::<u8>() {
            if self.buses.len() > 1 {
                return Err(LookupError::Ambiguous(key.to_string()));
            }
            if let Some(d) = self.drives.iter().find(|d| d.unit == unit) {
                return Ok((d, &self.buses[d.bus].handle));
            }
        }
        Err(LookupError::Unknown(key.to_string()))
    }

    /// The handle of a drive's bus.
    pub fn handle_of(&self, drive: &Drive) -> &BusHandle {
        &self.buses[drive.bus].handle
    }

    /// Takes no new work on any bus (the first step of the shutdown stop,
    /// `crate::control::shutdown`).
    pub fn close(&self) {
        for bus in &self.buses {
            bus.handle.close();
        }
    }

    /// Stops every bus once it finished the frame on the wire, and waits
    /// (at most 5 s a bus) for its thread.
    pub async fn stop(&self) {
        for bus in &self.buses {
            bus.handle.stop();
        }
        for bus in &self.buses {
            let thread = bus.thread.lock().unwrap_or_else(|p| p.into_inner()).take();
            if let Some(thread) = thread {
                let name = bus.handle.name().to_string();
                let joined = tokio::task::spawn_blocking(move || thread.join());
                match tokio::time::timeout(Duration::from_secs(5), joined).await {
                    Ok(Ok(Ok(()))) => {}
                    _ => warn!(bus = %name, "bus thread did not stop cleanly"),
                }
            }
        }
    }
}
