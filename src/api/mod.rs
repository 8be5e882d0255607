//! The REST + WebSocket face (`/api/v1`), with its OpenAPI document.

pub mod config;

use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::faces::Listening;
use crate::metrics::Metrics;
use crate::plant::Plant;

/// Binds the HTTP listener and serves the API until `shutdown` fires.
pub async fn start(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> Result<Listening, String> {
    let listener = tokio::net::TcpListener::bind(config.http.listen)
        .await
        .map_err(|e| format!("cannot listen for HTTP on {}: {e}", config.http.listen))?;
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    let _ = (plant, metrics);
    let task = tokio::spawn(async move {
        let app = axum::Router::new().route("/healthz", axum::routing::get(|| async { "ok" }));
        let _ = axum::serve(listener, app)
            .with_graceful_shutdown(async move { shutdown.cancelled().await })
            .await;
    });
    Ok(Listening { addr, task })
}
