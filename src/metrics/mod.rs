//! Prometheus metrics: the faces' counters live here; drive and bus values
//! are read from the poll cache and the bus counters at scrape time, so a
//! scrape never touches the bus.

mod faces;

use std::sync::Arc;

use prometheus::{Encoder, Registry, TextEncoder};

pub use faces::{FaceMetrics, WsClientGuard};

use crate::plant::Plant;

/// Every metric the daemon exports.
pub struct Metrics {
    registry: Registry,
    faces: FaceMetrics,
    plant: Arc<Plant>,
}

impl Metrics {
    /// Metrics of `plant`, with the faces' counters registered.
    pub fn new(plant: Arc<Plant>) -> Arc<Self> {
        let registry = Registry::new();
        let faces = FaceMetrics::register(&registry);
        Arc::new(Self {
            registry,
            faces,
            plant,
        })
    }

    /// The faces' counters, for the HTTP and Modbus TCP code to update.
    pub fn faces(&self) -> &FaceMetrics {
        &self.faces
    }

    /// The plant the drive and bus metrics are read from.
    pub fn plant(&self) -> &Arc<Plant> {
        &self.plant
    }

    /// The text exposition format (`GET /metrics`).
    pub fn render(&self) -> String {
        let families = self.registry.gather();
        let mut out = Vec::new();
        if let Err(e) = TextEncoder::new().encode(&families, &mut out) {
            tracing::warn!("cannot encode metrics: {e}");
        }
        String::from_utf8(out).unwrap_or_default()
    }
}
