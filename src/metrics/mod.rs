//! Prometheus metrics (`GET /metrics`).
//!
//! - [`faces`]: counters the HTTP, WebSocket and Modbus TCP faces update,
//! - `face_health`: each face serving, or down after a crash, and its
//!   restarts,
//! - `security`: the browser-origin guards, token failures and TLS,
//! - `mqtt`: the MQTT face's messages, commands and broker link,
//! - `opcua`: the OPC UA face's sessions, subscriptions, monitored items,
//!   values and events, sign-ins and refused certificates,
//! - `drives`: per-drive series read from the poll cache at scrape time,
//! - `buses`: per-bus series read from the bus counters, queues and port
//!   state (and the simulator's wire counters) at scrape time,
//! - `wire`: per-attempt wire errors per bus and unit, the bus monitor's
//!   and the scope's figures,
//! - `control`: the control core's counters (communication-loss lease ends,
//!   the safety journal, the alarms),
//! - `history`: the memory the trends take,
//! - `utilisation`: the sampler behind `drivegate_bus_utilisation_ratio`,
//! - `connections`: the listeners' connections, limits and refusals,
//!   per address within bounds, and the file-descriptor reserve,
//! - `process`: build information and the process's own resources,
//! - `family`: the plumbing that turns those values into families.
//!
//! Drive and bus values are copied from memory the bus threads already keep,
//! so a scrape never puts a frame on the wire nor waits for one.

mod buses;
mod connections;
mod control_core;
mod drives;
mod face_health;
mod faces;
mod family;
mod history;
mod mqtt;
mod opcua;
mod process;
mod security;
mod utilisation;
mod wire;

use std::sync::{Arc, Weak};

use prometheus::{Encoder, Registry, TextEncoder};

pub use connections::Listeners;
pub use face_health::{Down as FaceDown, FaceHealth, FaceState};
pub use faces::{FaceMetrics, WsClientGuard};
pub use mqtt::{LinkState as MqttLink, MqttMetrics};
pub use opcua::{FaceState as OpcUaState, OpcUaMetrics, SIGN_IN_KINDS, ServerCounts};
pub use security::{OpenConnection, SecurityMetrics};
pub use utilisation::{SAMPLE_PERIOD, WINDOW as UTILISATION_WINDOW};

use crate::plant::Plant;
use utilisation::Utilisation;

/// Every metric the daemon exports.
pub struct Metrics {
    registry: Registry,
    faces: FaceMetrics,
    face_health: FaceHealth,
    security: SecurityMetrics,
    mqtt: MqttMetrics,
    opcua: OpcUaMetrics,
    listeners: Arc<Listeners>,
    plant: Arc<Plant>,
    utilisation: Arc<Utilisation>,
}

impl Metrics {
    /// Metrics of `plant`, with the faces' counters registered. Called
    /// inside a tokio runtime, it also starts the utilisation sampler, which
    /// ends when the metrics are dropped.
    pub fn new(plant: Arc<Plant>) -> Arc<Self> {
        let registry = Registry::new();
        let faces = FaceMetrics::register(&registry);
        let face_health = FaceHealth::register(&registry);
        let security = SecurityMetrics::register(&registry);
        let mqtt = MqttMetrics::register(&registry);
        let opcua = OpcUaMetrics::register(&registry);
        let utilisation = Arc::new(Utilisation::new(&plant));
        let collectors: [Box<dyn prometheus::core::Collector>; 3] = [
            Box::new(drives::DriveCollector::new(plant.clone())),
            Box::new(buses::BusCollector::new(plant.clone(), utilisation.clone())),
            Box::new(wire::WireCollector::new(plant.clone())),
        ];
        for collector in collectors {
            if let Err(e) = registry.register(collector) {
                tracing::warn!("some metrics are not exported: {e}");
            }
        }
        process::register(&registry);
        let listeners = Arc::new(Listeners::new(crate::connections::Book::process()));
        if let Err(e) = registry.register(Box::new(connections::ListenersCollector::new(
            listeners.clone(),
        ))) {
            tracing::warn!("the listeners' metrics are not exported: {e}");
        }
        let metrics = Arc::new(Self {
            registry,
            faces,
            face_health,
            security,
            mqtt,
            opcua,
            listeners,
            plant,
            utilisation,
        });
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            runtime.spawn(sample_utilisation(Arc::downgrade(&metrics)));
        }
        metrics
    }

    /// Exports the counters of `control`, the core every face writes
    /// through (started after the metrics, with the faces).
    pub fn watch_control(&self, control: &crate::control::Control) {
        if let Err(e) = self
            .registry
            .register(Box::new(control_core::ControlCollector::new(
                control.clone(),
            )))
        {
            tracing::warn!("the control core's metrics are not exported: {e}");
        }
    }

    /// Exports the memory the trends take.
    pub fn watch_history(&self, history: &Arc<crate::history::History>) {
        if let Err(e) = self
            .registry
            .register(Box::new(history::HistoryCollector::new(history.clone())))
        {
            tracing::warn!("the history's metrics are not exported: {e}");
        }
    }

    /// Each face serving, or down after a crash, for the supervisor to say
    /// and `/readyz` to show.
    pub fn face_health(&self) -> &FaceHealth {
        &self.face_health
    }

    /// The faces' counters, for the HTTP and Modbus TCP code to update.
    pub fn faces(&self) -> &FaceMetrics {
        &self.faces
    }

    /// The transport's defences' counters (guards, tokens, TLS).
    pub fn security(&self) -> &SecurityMetrics {
        &self.security
    }

    /// The MQTT face's counters and the state of its link.
    pub fn mqtt(&self) -> &MqttMetrics {
        &self.mqtt
    }

    /// The OPC UA face's counters and state.
    pub fn opcua(&self) -> &OpcUaMetrics {
        &self.opcua
    }

    /// The listeners' connections: each listener takes its place in the
    /// process's book here, and is exported while it lives.
    pub fn listeners(&self) -> &Arc<Listeners> {
        &self.listeners
    }

    /// The share of the last [`UTILISATION_WINDOW`] the wire of the bus in
    /// slot `bus` was busy (0 to 1); `None` until the window is long
    /// enough.
    pub fn bus_utilisation(&self, bus: usize) -> Option<f64> {
        let handle = self.plant.now().bus_at(bus)?.handle.clone();
        self.utilisation
            .window(bus)?
            .ratio(std::time::Instant::now(), handle.stats().busy_seconds)
    }

    /// The plant the drive and bus metrics are read from.
    pub fn plant(&self) -> &Arc<Plant> {
        &self.plant
    }

    /// The text exposition format (`GET /metrics`, content type
    /// [`CONTENT_TYPE`]).
    pub fn render(&self) -> String {
        let families = self.registry.gather();
        let mut out = Vec::new();
        if let Err(e) = TextEncoder::new().encode(&families, &mut out) {
            tracing::warn!("cannot encode metrics: {e}");
        }
        String::from_utf8(out).unwrap_or_default()
    }
}

/// Content type of [`Metrics::render`]'s output.
pub const CONTENT_TYPE: &str = prometheus::TEXT_FORMAT;

/// Reads every bus's busy counter each [`SAMPLE_PERIOD`] until the metrics
/// are dropped (or the runtime stops).
async fn sample_utilisation(metrics: Weak<Metrics>) {
    let mut tick = tokio::time::interval(SAMPLE_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let Some(m) = metrics.upgrade() else { break };
        m.utilisation.sample(&m.plant);
    }
}
