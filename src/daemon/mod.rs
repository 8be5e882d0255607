//! `drivegate serve`: start the plant and the faces, tell systemd, wait for
//! a signal, stop gracefully.

pub mod certificates;
mod face_watch;
mod listen;
pub mod reloader;
pub mod supervisor;
pub(crate) mod systemd;

use std::path::PathBuf;
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

/// What the start brought up.
struct Started {
    plant: Arc<Plant>,
    faces: crate::daemon::supervisor::Faces,
    reloader: Option<tokio::task::JoinHandle<()>>,
}

/// Runs the daemon with `config` (read from `path`, if given: then
/// SIGHUP and `POST /api/v1/config/reload` apply its changes) until SIGINT
/// or SIGTERM.
///
/// A stop asked for during the start is honoured: the start runs in a task
/// of its own while this one listens for the signals, and every step of it
/// is bounded (the state files are read within bounds, see
/// `crate::control::journal::tail`), so the start finishes its step and
/// the daemon stops as after a start, with its safe stop; a start that
/// does not finish within [`START_STOP_LIMIT`] of the signal is left, and
/// the process ends without it.
pub async fn serve(config: Config, path: Option<PathBuf>) -> Result<(), DaemonError> {
    // Catch the signals from the start: a stop asked for while the buses open
    // is then a graceful stop right after, not an abrupt kill.
    let mut signals = StopSignals::new().map_err(DaemonError::Signals)?;
    let shutdown = CancellationToken::new();
    let mut starting = tokio::spawn(start(config.clone(), path, shutdown.clone()));
    let started = tokio::select! {
        started = &mut starting => started,
        () = signals.recv() => {
            info!("a stop was asked for during the start: drivegate stops once the step under way is done");
            return stop_during_start(starting, config.safety.on_shutdown, shutdown).await;
        }
    };
    let started = started.map_err(|e| DaemonError::Listen(format!("the start failed: {e}")))??;
    signals.reload_with(started.faces.control.clone());
    if started.plant.now().bus_count() == 0 {
        // The package's configuration as shipped: `systemctl status` says
        // what to do first.
        tracing::warn!("{}", crate::api::health::NO_BUS);
    }
    let summary = crate::daemon::systemd::status_line(&started.plant, Some(started.faces.http));
    notify_systemd(&[
        sd_notify::NotifyState::Ready,
        sd_notify::NotifyState::Status(&summary),
    ]);
    // The watchdog keeps pinging through the stop: a safe stop that takes a
    // few seconds must not be mistaken for a hang.
    let watchdog = Watchdog::start();
    signals.recv().await;
    // `[safety] on_shutdown` as the last reload left it.
    let on_shutdown = started
        .faces
        .control
        .follow_config()
        .borrow()
        .as_ref()
        .map_or(config.safety.on_shutdown, |c| c.safety.on_shutdown);
    stop(started, on_shutdown, shutdown).await;
    watchdog.stop().await;
    Ok(())
}

/// How long a start under way gets to finish its step after a stop signal.
const START_STOP_LIMIT: Duration = Duration::from_millis(1500);

/// Starts the plant, the core and the faces.
async fn start(
    config: Config,
    path: Option<PathBuf>,
    shutdown: CancellationToken,
) -> Result<Started, DaemonError> {
    let plant = Arc::new(Plant::start(&config)?);
    info!(
        buses = plant.now().bus_count(),
        drives = plant.now().drive_count(),
        "drivegate {} running",
        env!("CARGO_PKG_VERSION")
    );
    let metrics = crate::metrics::Metrics::new(plant.clone());
    let faces = crate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
        .await
        .map_err(DaemonError::Listen)?;
    let reloader = path.as_deref().map(|path| {
        crate::daemon::reloader::Reloader::start(
            path,
            Arc::new(config.clone()),
            plant.clone(),
            faces.control.clone(),
            faces.running(),
            shutdown.clone(),
        )
    });
    Ok(Started {
        plant,
        faces,
        reloader,
    })
}

/// A stop signal came while `starting` ran: once it is done (within
/// [`START_STOP_LIMIT`]), what it brought up stops as after a start.
async fn stop_during_start(
    starting: tokio::task::JoinHandle<Result<Started, DaemonError>>,
    on_shutdown: crate::control::stop_action::StopAction,
    shutdown: CancellationToken,
) -> Result<(), DaemonError> {
    notify_systemd(&[sd_notify::NotifyState::Stopping]);
    match tokio::time::timeout(START_STOP_LIMIT, starting).await {
        Ok(Ok(Ok(started))) => {
            stop(started, on_shutdown, shutdown).await;
            Ok(())
        }
        Ok(Ok(Err(e))) => {
            warn!("the start failed while stopping: {e}");
            Ok(())
        }
        Ok(Err(e)) => {
            warn!("the start failed while stopping: {e}");
            Ok(())
        }
        Err(_) => {
            warn!(
                "the start did not finish within {} ms of the stop signal: drivegate ends without its safe stop (nothing was served yet)",
                START_STOP_LIMIT.as_millis()
            );
            Ok(())
        }
    }
}

/// The graceful stop: no new work, the faces closed, the safe stop of
/// every drive (`on_shutdown`), the plant stopped.
async fn stop(
    started: Started,
    on_shutdown: crate::control::stop_action::StopAction,
    shutdown: CancellationToken,
) {
    info!(
        "stopping: no new work; finishing the frame on the wire and applying the safe-stop action ({})",
        on_shutdown.name()
    );
    notify_systemd(&[
        sd_notify::NotifyState::Stopping,
        sd_notify::NotifyState::Status("stopping: applying the safe-stop action"),
    ]);
    shutdown.cancel();
    if let Some(reloader) = started.reloader {
        // A reload under way finishes first: the plant is whole for the stop.
        let _ = reloader.await;
    }
    if tokio::time::timeout(FACES_STOP_LIMIT, started.faces.wait())
        .await
        .is_err()
    {
        warn!(
            "some connections did not close within {} s",
            FACES_STOP_LIMIT.as_secs()
        );
    }
    crate::control::shutdown(&started.plant, on_shutdown).await;
    info!("stopped");
}

/// systemd's watchdog, pinged while it runs.
struct Watchdog {
    stop: CancellationToken,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl Watchdog {
    fn start() -> Self {
        let stop = CancellationToken::new();
        let task = spawn_watchdog(stop.clone());
        Watchdog { stop, task }
    }

    async fn stop(self) {
        self.stop.cancel();
        if let Some(task) = self.task {
            let _ = task.await;
        }
    }
}

/// How long open connections get to finish after a stop signal; the unit
/// file's `TimeoutStopSec` leaves room for this plus the safe stop (each bus
/// step is bounded to 5 s in [`crate::control::shutdown`]).
const FACES_STOP_LIMIT: Duration = Duration::from_secs(5);

use crate::daemon::systemd::notify as notify_systemd;

/// Pings systemd's watchdog (`WatchdogSec=`) at half its interval until
/// `stop` fires. The pings come from the runtime that serves the faces and
/// drives the stop, so a wedged runtime gets the daemon restarted.
fn spawn_watchdog(stop: CancellationToken) -> Option<tokio::task::JoinHandle<()>> {
    let interval = sd_notify::watchdog_enabled()?;
    info!(
        "systemd watchdog every {:?}; pinging at half that",
        interval
    );
    let period = (interval / 2).max(Duration::from_millis(1));
    Some(tokio::spawn(async move {
        let mut tick = tokio::time::interval(period);
        loop {
            tokio::select! {
                _ = tick.tick() => notify_systemd(&[sd_notify::NotifyState::Watchdog]),
                () = stop.cancelled() => break,
            }
        }
    }))
}

/// SIGTERM (systemd's stop) and SIGINT (Ctrl-C); SIGHUP (systemd's
/// reload) is taken here too, so that it never ends the daemon: it reloads
/// the configuration file through the core (`crate::daemon::reloader`), and the TLS
/// listeners watch it themselves and reload their certificates
/// ([`crate::tls::reload_on_hangup`]).
struct StopSignals {
    term: tokio::signal::unix::Signal,
    int: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
    control: Option<crate::control::Control>,
    /// A SIGHUP came before the start was done: its reload is made then.
    reload_pending: bool,
}

impl StopSignals {
    fn new() -> std::io::Result<Self> {
        use tokio::signal::unix::{SignalKind, signal};
        Ok(Self {
            term: signal(SignalKind::terminate())?,
            int: signal(SignalKind::interrupt())?,
            hup: signal(SignalKind::hangup())?,
            control: None,
            reload_pending: false,
        })
    }

    /// From now on SIGHUP reloads the configuration through `control`;
    /// one that came during the start reloads now.
    fn reload_with(&mut self, control: crate::control::Control) {
        if std::mem::take(&mut self.reload_pending) {
            Self::reload(control.clone());
        }
        self.control = Some(control);
    }

    /// Reloads in its own task: its result is logged and audited by the
    /// reloader, and a stop signal meanwhile is not kept waiting.
    fn reload(control: crate::control::Control) {
        tokio::spawn(async move {
            let result = control.reload_as("SIGHUP".to_string(), None).await;
            crate::control::audit::reload("SIGHUP", &result);
        });
    }

    async fn recv(&mut self) {
        loop {
            tokio::select! {
                _ = self.term.recv() => return info!("SIGTERM received"),
                _ = self.int.recv() => return info!("SIGINT received"),
                _ = self.hup.recv() => match self.control.clone() {
                    Some(control) => {
                        info!("SIGHUP received: reloading the configuration; TLS listeners reload their certificates");
                        Self::reload(control);
                    }
                    None => {
                        // A `systemctl reload` while the buses open is not
                        // lost: the file is read again once they are.
                        info!("SIGHUP received during the start: the configuration is reloaded once the start is done");
                        self.reload_pending = true;
                    }
                },
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_sighup_during_the_start_is_kept_for_when_the_start_is_done() {
        let mut signals = StopSignals::new().expect("signal handlers");
        // Before the core is there (the buses are opening), a reload asked
        // for by `systemctl reload` is remembered, not dropped; the process
        // lives on (the handler is in place).
        nix::sys::signal::raise(nix::sys::signal::Signal::SIGHUP).expect("raise");
        let waited = tokio::time::timeout(Duration::from_secs(5), async {
            while !signals.reload_pending {
                let _ = tokio::time::timeout(Duration::from_millis(10), signals.recv()).await;
            }
        })
        .await;
        assert!(waited.is_ok(), "the SIGHUP was not kept");
        assert!(signals.control.is_none());
    }
}
