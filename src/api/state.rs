//! What every handler shares: the plant, the control core, the metrics,
//! the tokens, the stream hub, and the shutdown signal; and the lookups of
//! what a request names (a drive, a bus, a bus's monitor), each refused
//! with a problem that lists what there is.

use std::collections::HashMap;
use std::ops::Deref;
use std::sync::{Arc, Mutex};

use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::auth::Tokens;
use super::hub::Hub;
use super::problem_response::{Kind, Problem};
use crate::bus::SourceId;
use crate::config::HttpConfig;
use crate::control::Control;
use crate::history::History;
use crate::metrics::Metrics;
use crate::monitor::BusMonitor;
use crate::plant::{Bus, Plant};

/// The handlers' state; cheap to clone.
#[derive(Clone)]
pub struct ApiState(Arc<Shared>);

/// The shared part of [`ApiState`].
pub struct Shared {
    /// Buses and drives.
    pub plant: Arc<Plant>,
    /// Counters (`/metrics`).
    pub metrics: Arc<Metrics>,
    /// The `[http]` section.
    pub config: HttpConfig,
    /// Configured tokens.
    pub tokens: Tokens,
    /// The control core: every write goes through it.
    pub control: Control,
    /// Every drive's status over the last minutes (the trends).
    pub history: Arc<History>,
    /// The stream's fan-out of bus and lease events.
    pub hub: Arc<Hub>,
    /// Fires when the daemon stops.
    pub shutdown: CancellationToken,
    /// WebSocket sessions, which the HTTP server does not track once upgraded.
    pub sessions: TaskTracker,
    sources: Mutex<HashMap<String, SourceId>>,
}

impl Deref for ApiState {
    type Target = Shared;

    fn deref(&self) -> &Shared {
        &self.0
    }
}

pub use crate::faces_shared::target::Target;

impl ApiState {
    /// The state of a starting API.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        plant: Arc<Plant>,
        metrics: Arc<Metrics>,
        config: HttpConfig,
        tokens: Tokens,
        control: Control,
        history: Arc<History>,
        hub: Arc<Hub>,
        shutdown: CancellationToken,
    ) -> Self {
        ApiState(Arc::new(Shared {
            plant,
            metrics,
            config,
            tokens,
            control,
            history,
            hub,
            shutdown,
            sessions: TaskTracker::new(),
            sources: Mutex::new(HashMap::new()),
        }))
    }

    /// The queue source of a token name (or client address): stable, so a
    /// client's requests share one fair turn on the bus.
    pub fn source_for(&self, key: &str) -> SourceId {
        let mut sources = self.sources.lock().unwrap_or_else(|p| p.into_inner());
        *sources
            .entry(key.to_string())
            .or_insert_with(SourceId::new_unique)
    }

    /// The drive named `key` (or, on a single bus, with that unit number).
    pub fn target(&self, key: &str) -> Result<Target, Problem> {
        Target::find(&self.plant, key)
    }

    /// The drive in slot `index` of the plant, if it is still configured.
    pub fn target_at(&self, index: usize) -> Option<Target> {
        Target::at(&self.plant, index)
    }

    /// The bus named `name`, or an `unknown-bus` problem listing the buses.
    pub fn bus(&self, name: &str) -> Result<Arc<Bus>, Problem> {
        let now = self.plant.now();
        now.bus(name).cloned().ok_or_else(|| {
            let names: Vec<&str> = now.buses().map(|b| b.handle.name()).collect();
            Problem::new(
                Kind::UnknownBus,
                format!(
                    "no bus named \"{name}\" is configured: configured buses are {}",
                    names.join(", ")
                ),
            )
        })
    }
}

/// The bus's monitor, or the problem that it keeps no frames.
pub fn monitor_of(bus: &Bus) -> Result<&Arc<BusMonitor>, Problem> {
    let monitor = bus.monitor();
    if monitor.enabled() {
        Ok(monitor)
    } else {
        Err(Problem::new(
            Kind::MonitorOff,
            format!(
                "the bus monitor is off ([monitor] enabled = false): no frames of bus \"{}\" are kept; the per-attempt counters are in GET /api/v1/buses/{}/monitor and /metrics",
                bus.handle.name(),
                bus.handle.name()
            ),
        ))
    }
}
