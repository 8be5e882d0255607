//! `drivegate serve`: start the plant and the faces, tell systemd, wait for
//! a signal, stop gracefully.

use std::sync::Arc;
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::config::{Config, ConfigError};
use crate::plant::{Plant, PlantError};

/// Why the daemon could not run.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// The configuration is not usable.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A bus or simulator did not start.
    #[error(transparent)]
    Plant(#[from] PlantError),
    /// A listener could not be opened.
    #[error("{0}")]
    Listen(String),
    /// Waiting for signals failed.
    #[error("cannot watch for signals: {0}")]
    Signals(std::io::Error),
}

/// Runs the daemon with `config` until SIGINT or SIGTERM.
pub async fn serve(config: Config) -> Result<(), DaemonError> {
    let plant = Arc::new(Plant::start(&config)?);
    info!(
        buses = plant.buses().len(),
        drives = plant.drives().len(),
        "drivegate {} running",
        env!("CARGO_PKG_VERSION")
    );
    let shutdown = CancellationToken::new();
    let metrics = crate::metrics::Metrics::new(plant.clone());
    let faces = crate::faces::start(&config, plant.clone(), metrics, shutdown.clone())
        .await
        .map_err(DaemonError::Listen)?;

    notify_systemd(&[sd_notify::NotifyState::Ready]);
    let watchdog = spawn_watchdog(shutdown.clone());

    wait_for_signal().await.map_err(DaemonError::Signals)?;
    info!(
        "stopping: no new work; finishing the frame on the wire and applying the safe-stop action"
    );
    notify_systemd(&[sd_notify::NotifyState::Stopping]);
    shutdown.cancel();
    if tokio::time::timeout(Duration::from_secs(5), faces.wait())
        .await
        .is_err()
    {
        warn!("some connections did not close within 5 s");
    }
    plant.shutdown(config.safety.on_shutdown).await;
    if let Some(w) = watchdog {
        w.abort();
    }
    info!("stopped");
    Ok(())
}

fn notify_systemd(states: &[sd_notify::NotifyState<'_>]) {
    if let Err(e) = sd_notify::notify(states) {
        warn!("cannot notify systemd: {e}");
    }
}

/// Pings systemd's watchdog at half its interval while the daemon runs.
fn spawn_watchdog(shutdown: CancellationToken) -> Option<tokio::task::JoinHandle<()>> {
    let interval = sd_notify::watchdog_enabled()?;
    Some(tokio::spawn(async move {
        let mut tick = tokio::time::interval(interval / 2);
        loop {
            tokio::select! {
                _ = tick.tick() => notify_systemd(&[sd_notify::NotifyState::Watchdog]),
                () = shutdown.cancelled() => break,
            }
        }
    }))
}

async fn wait_for_signal() -> std::io::Result<()> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate())?;
    let mut int = signal(SignalKind::interrupt())?;
    tokio::select! {
        _ = term.recv() => info!("SIGTERM received"),
        _ = int.recv() => info!("SIGINT received"),
    }
    Ok(())
}
