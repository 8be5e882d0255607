//! Starts the network faces (HTTP API with metrics, Modbus TCP) and waits
//! for them to finish after shutdown.

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::control::Control;
use crate::metrics::Metrics;
use crate::plant::Plant;

/// The running faces.
pub struct Faces {
    /// Where the HTTP API (REST, WebSocket, metrics) listens.
    pub http: SocketAddr,
    /// Where Modbus TCP listens, if enabled.
    pub modbus_tcp: Option<SocketAddr>,
    /// Where Modbus/TCP Security listens, if configured.
    pub modbus_tls: Option<SocketAddr>,
    /// The control core every face writes through.
    pub control: Control,
    tasks: Vec<JoinHandle<()>>,
}

impl Faces {
    /// Waits until every face has stopped (after the shutdown token fired).
    pub async fn wait(self) {
        for task in self.tasks {
            let _ = task.await;
        }
        // Stops of leases still on the wire finish (the daemon's safe stop
        // follows).
        let _ = tokio::time::timeout(std::time::Duration::from_secs(2), self.control.wait()).await;
    }
}

/// Loads the certificates, keys and client CAs of every configured TLS
/// listener, as a start would (for `check-config`): an error names the
/// file and what is wrong with it.
pub fn check_tls(config: &Config) -> Result<(), String> {
    if let Some(files) = &config.http.tls {
        crate::tls::server_config(files, crate::tls::ClientAuth::IfConfigured, &[])
            .map_err(|e| format!("[http.tls]: {e}"))?;
    }
    if let Some(section) = &config.modbus_tcp.tls {
        crate::tls::server_config(&section.files(), crate::tls::ClientAuth::Required, &[])
            .map_err(|e| format!("[modbus_tcp.tls]: {e}"))?;
    }
    Ok(())
}

/// Starts the control core, binds every configured listener (so a taken
/// port fails the start) and serves them until `shutdown` fires.
pub async fn start(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> Result<Faces, String> {
    let control = Control::start(plant.clone(), &config.safety, shutdown.clone());
    // The running configuration, which the faces follow for their sections.
    control.set_config(Arc::new(config.clone()));
    metrics.faces().tcp_outcomes(
        crate::modbus_tcp::outcome::Outcome::ALL
            .iter()
            .map(|o| o.label()),
    );
    metrics.watch_control(&control);
    let history = crate::history::History::new(config.history.settings());
    {
        let (history, directory, stop) = (history.clone(), plant.clone(), shutdown.clone());
        plant.each_bus(shutdown.clone(), move |index, bus| {
            // Asked at each status: drives configured later are kept too.
            let directory = directory.clone();
            history.follow(
                &bus.handle,
                move |unit| {
                    directory
                        .now()
                        .drives()
                        .any(|d| d.bus == index && d.unit == unit)
                },
                stop.clone(),
            );
        });
    }
    metrics.watch_history(&history);
    // What the last process owed the motors, before any client is taken.
    control.replay().await;
    let (http, task) = crate::api::start(
        config,
        plant.clone(),
        metrics.clone(),
        control.clone(),
        history,
        crate::console::router(),
        shutdown.clone(),
    )
    .await?;
    tracing::info!(addr = %http, "HTTP API listening");
    let mut tasks = vec![task];
    let modbus_tls = match crate::modbus_tcp::start_tls(
        config,
        plant.clone(),
        metrics.clone(),
        control.clone(),
        shutdown.clone(),
    )
    .await?
    {
        Some((addr, task)) => {
            tracing::info!(addr = %addr, "Modbus/TCP Security listening");
            tasks.push(task);
            Some(addr)
        }
        None => None,
    };
    let modbus_tcp = if config.modbus_tcp.enabled {
        let (addr, task) =
            crate::modbus_tcp::start(config, plant, metrics, control.clone(), shutdown).await?;
        tracing::info!(addr = %addr, "Modbus TCP listening");
        tasks.push(task);
        Some(addr)
    } else {
        None
    };
    Ok(Faces {
        http,
        modbus_tcp,
        modbus_tls,
        control,
        tasks,
    })
}
