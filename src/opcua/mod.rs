//! The OPC UA face: the drives in the language of SCADA, MES and PLCs with
//! an OPC UA client, on async-opcua (server feature, pure-Rust crypto).
//!
//! Floors of the room, from the bottom:
//! - [`spec`]: the address space as data (namespace, `DriveType`'s
//!   variables with their units and ranges, methods, bus variables, node
//!   ids), pure;
//! - [`values`] (a drive's values as data values, with the poll's source
//!   timestamp and the freshness's status code), [`outcome`] (the core's
//!   refusals as status codes), both pure; [`pki`] (the Part 12 layout,
//!   the server's certificate, trust without a restart);
//! - [`users`] (user names and tokens, user certificates, anonymous),
//!   [`sessions`] (each OPC UA session a session of the core, its leases
//!   ended when it closes or times out), [`address`] (the nodes),
//!   [`history`] (`HistoryRead`);
//! - [`nodes`] (reads of what a drive holds, writes and method calls
//!   through the core), [`alarms`] (the alarm book as
//!   `AlarmConditionType` events), [`conditions`] (acknowledgement and
//!   `ConditionRefresh`);
//! - [`render`] (the plant in the address space, at every poll),
//!   [`server`] (the server built from `[opcua]`, its connections and
//!   sessions shared out by [`gate`], as every listener's are);
//! - here, [`start`]: on the socket `faces.rs` bound, with a stop token of
//!   its own, as every face.
//!
//! Like every face it decides nothing about the motors: writes and calls
//! go to [`crate::control`] with the session's caller (face `opcua`), and
//! its answers are rendered as status codes with the core's words. See
//! `docs/opcua.md`.

pub mod address;
pub mod alarms;
pub mod conditions;
pub mod gate;
pub mod history;
pub mod nodes;
pub mod outcome;
pub mod pki;
pub mod render;
pub mod server;
pub mod sessions;
pub mod spec;
pub mod users;
pub mod values;

use crate::faces_shared::start::FaceStart;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use opcua::server::ServerHandle;
use opcua::types::{VariableId, Variant};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::OpcUaConfig;
use crate::control::Control;
use crate::history::History;
use crate::metrics::{Metrics, ServerCounts};
use nodes::DriveManager;
use pki::{Own, Pki};

/// Starts the OPC UA face of `config` on `listener` (bound by
/// `faces.rs`), until `stop`: its certificate is made at the first start
/// in a blocking task (RSA key generation: the other faces start
/// meanwhile, and clients wait in the listener's backlog), then the server
/// runs. Returns where it listens and its task.
pub(crate) fn start(
    start: FaceStart,
    listener: TcpListener,
) -> Result<(SocketAddr, JoinHandle<()>), String> {
    let FaceStart {
        config,
        control,
        metrics,
        history,
        stop,
        ..
    } = start;
    let config = &config;
    let section = config.opcua.clone().ok_or("no [opcua] section")?;
    let bound = listener.local_addr().map_err(|e| e.to_string())?;
    let (root, temporary) = match section.pki_dir(config.safety.state_dir().as_deref()) {
        Some(dir) => (dir, false),
        None => (temporary_pki(), true),
    };
    let pki = Pki::new(root);
    pki.prepare().map_err(|e| format!("[opcua] pki_dir: {e}"))?;
    if temporary {
        tracing::warn!(
            target: "drivegate::opcua",
            pki = %pki.root().display(),
            "OPC UA: no [opcua] pki_dir and no state directory: the server's certificate is made \
             anew at each start, and clients must trust it again"
        );
    }
    metrics.opcua().started(bound.to_string());
    let caps = server::caps(&section);
    metrics.opcua().limits(&[
        ("subscriptions_per_session", caps.subscriptions_per_session),
        (
            "monitored_items_per_session",
            caps.monitored_items_per_session,
        ),
        ("monitored_items", caps.monitored_items),
        ("queue_size", caps.queue_size),
        ("event_queue_size", caps.event_queue_size),
        ("queued_values", caps.queued_values),
    ]);
    let face = Face {
        section,
        bound,
        pki,
        temporary,
        control,
        metrics,
        history,
    };
    Ok((bound, tokio::spawn(face.run(listener, stop))))
}

/// A PKI directory of this process's own, when none is configured.
fn temporary_pki() -> PathBuf {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    std::env::temp_dir().join(format!(
        "drivegate-opcua-pki-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    ))
}

/// The host's name, as its kernel says it.
fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".to_string())
}

/// The face, before it runs.
struct Face {
    section: OpcUaConfig,
    bound: SocketAddr,
    pki: Pki,
    temporary: bool,
    control: Control,
    metrics: Arc<Metrics>,
    history: Arc<History>,
}

impl Face {
    async fn run(self, listener: TcpListener, stop: CancellationToken) {
        let host = host_name();
        if let Err(why) = self.certificate(&host).await {
            tracing::error!(target: "drivegate::opcua", "OPC UA not started: {why}");
            self.metrics.opcua().failed(why);
            return;
        }
        if !stop.is_cancelled() {
            if let Err(why) = self.serve(listener, host, &stop).await {
                tracing::error!(target: "drivegate::opcua", "OPC UA not started: {why}");
                self.metrics.opcua().failed(why);
            } else {
                self.metrics.opcua().stopped(true);
            }
        }
        if self.temporary {
            let _ = std::fs::remove_dir_all(self.pki.root());
        }
    }

    /// The server's certificate, made now if `own/` has none.
    async fn certificate(&self, host: &str) -> Result<(), String> {
        let pki = self.pki.clone();
        let uri = server::application_uri(host);
        let host = host.to_string();
        let addresses = if self.bound.ip().is_unspecified() {
            Vec::new()
        } else {
            vec![self.bound.ip().to_string()]
        };
        let made = tokio::task::spawn_blocking(move || {
            pki.ensure_own_certificate(&uri, &host, &addresses)
        })
        .await
        .map_err(|e| format!("making its certificate: {e}"))?
        .map_err(|e| format!("its certificate in {}: {e}", self.pki.root().display()))?;
        if made == Own::Made {
            tracing::info!(
                target: "drivegate::opcua",
                certificate = %self.pki.cert_path().display(),
                "OPC UA: the server's certificate was made (clients trust it once)"
            );
        }
        Ok(())
    }

    /// Builds the server and serves `listener` until `stop`: built when its
    /// first client knocks, not before (see [`first_client`]).
    async fn serve(
        &self,
        listener: TcpListener,
        host: String,
        stop: &CancellationToken,
    ) -> Result<(), String> {
        self.metrics.opcua().serving();
        tracing::info!(
            target: "drivegate::opcua",
            addr = %self.bound,
            endpoints = ?self.section.endpoints().iter().map(|s| s.name()).collect::<Vec<_>>(),
            "OPC UA serving"
        );
        let users = Arc::new(users::Users::new(
            self.control.follow_config(),
            &self.section,
            self.pki.clone(),
            self.metrics.clone(),
        ));
        let sessions = Arc::new(sessions::Sessions::new(
            self.control.clone(),
            self.section.comm_loss_action,
            self.section.session_timeout_max(),
        ));
        let gate = Arc::new(gate::Gate::new(&self.section, self.bound, &self.metrics));
        let parts = || server::Parts {
            section: self.section.clone(),
            bound: self.bound,
            host: host.clone(),
            pki: self.pki.clone(),
            control: self.control.clone(),
            history: self.history.clone(),
            metrics: self.metrics.clone(),
            users: users.clone(),
            sessions: sessions.clone(),
            stop: stop.clone(),
            gate: gate.clone(),
        };
        // A section the server would refuse is refused now, not at the
        // first client.
        server::prepare(parts())?;
        let Some(listener) = first_client(listener, stop).await? else {
            return Ok(());
        };
        let built = server::build(parts())?;
        let manager = built
            .handle
            .node_managers()
            .get_of_type::<DriveManager>()
            .ok_or("the server has no node manager for the drives")?;
        let aux = stop.child_token();
        let render = render::Render {
            nodes: manager.inner().nodes(),
            space: manager.address_space().clone(),
            subscriptions: built.handle.subscriptions().clone(),
            control: self.control.clone(),
            metrics: self.metrics.clone(),
        };
        let shown = render.begin();
        tokio::spawn(Arc::new(render).run(shown, aux.clone()));
        tokio::spawn(sessions.run(aux.clone()));
        tokio::spawn(alarms::run(
            built.events,
            self.control.clone(),
            built.handle.subscriptions().clone(),
            self.metrics.clone(),
            aux.clone(),
        ));
        tokio::spawn(mirror(self.pki.clone(), self.metrics.clone(), aux.clone()));
        tokio::spawn(counts(
            built.handle.clone(),
            self.metrics.clone(),
            aux.clone(),
        ));
        tracing::debug!(target: "drivegate::opcua", "OPC UA: address space built");
        let served = built.server.run_with(listener).await;
        aux.cancel();
        served
    }
}

/// Waits until a client knocks on `listener` (a connection waits in its
/// backlog, not accepted yet) or `stop`; then the listener, to the server,
/// which accepts it. Until then nothing of the server exists: the core
/// namespace's thousands of nodes (about 10 MB, and 5 MB of code touched to
/// make them), its subscription tick every 10 ms, each poll's values
/// written into the address space. A daemon nobody reads over OPC UA pays
/// none of it; the first client waits for the build (a fraction of a
/// second), in the backlog.
///
/// The wait is a `poll` of the listener and of an event the stop writes,
/// on a blocking thread: it sleeps until one of them, with no timer.
async fn first_client(
    listener: TcpListener,
    stop: &CancellationToken,
) -> Result<Option<TcpListener>, String> {
    use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
    use nix::sys::eventfd::{EfdFlags, EventFd};
    use std::os::fd::AsFd;

    let listener = listener.into_std().map_err(|e| e.to_string())?;
    let stopped = Arc::new(
        EventFd::from_flags(EfdFlags::EFD_CLOEXEC)
            .map_err(|e| format!("waiting for a client: {e}"))?,
    );
    let event = stopped.clone();
    let mut waiting = tokio::task::spawn_blocking(move || {
        let knocked = loop {
            let mut fds = [
                PollFd::new(listener.as_fd(), PollFlags::POLLIN),
                PollFd::new(event.as_fd(), PollFlags::POLLIN),
            ];
            match poll(&mut fds, PollTimeout::NONE) {
                Ok(_) => break fds[0].any().unwrap_or(false),
                Err(nix::errno::Errno::EINTR) => {}
                Err(e) => return Err(format!("waiting for a client: {e}")),
            }
        };
        Ok(knocked.then_some(listener))
    });
    let waited = tokio::select! {
        waited = &mut waiting => waited,
        () = stop.cancelled() => {
            let _ = stopped.write(1);
            // The listener is closed before the face says it stopped: a
            // restart binds the same port.
            let _ = waiting.await;
            return Ok(None);
        }
    };
    match waited.map_err(|e| format!("waiting for a client: {e}"))?? {
        Some(listener) => TcpListener::from_std(listener)
            .map(Some)
            .map_err(|e| e.to_string()),
        None => Ok(None),
    }
}

/// Keeps the crate's store in step with the PKI directory every second
/// (see [`pki`]), counting and logging the certificates it refused.
async fn mirror(pki: Pki, metrics: Arc<Metrics>, stop: CancellationToken) {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = stop.cancelled() => return,
        }
        let p = pki.clone();
        let rejected = tokio::task::spawn_blocking(move || p.sync())
            .await
            .unwrap_or_default();
        for name in &rejected {
            tracing::warn!(
                target: "drivegate::opcua",
                certificate = %name,
                dir = %pki.rejected().display(),
                "OPC UA client certificate refused (not trusted): move it to trusted/certs to trust it"
            );
        }
        metrics.opcua().rejected_certificates(rejected.len());
    }
}

/// Copies the server's own counts (sessions, subscriptions, timeouts) to
/// the metrics every second.
async fn counts(handle: ServerHandle, metrics: Arc<Metrics>, stop: CancellationToken) {
    use VariableId as V;
    let read = |id: VariableId| match handle.info().summary().get(id).and_then(|v| v.value) {
        Some(Variant::UInt32(n)) => n,
        _ => 0,
    };
    let (mut sessions_seen, mut timeouts_seen) = (0u32, 0u32);
    // The crate's count is the process's: from what it was at the start.
    let mut notifications_seen = opcua::server::notifications_sent();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = stop.cancelled() => break,
        }
        let cumulated =
            read(V::Server_ServerDiagnostics_ServerDiagnosticsSummary_CumulatedSessionCount);
        let timeouts =
            read(V::Server_ServerDiagnostics_ServerDiagnosticsSummary_SessionTimeoutCount);
        let notifications = opcua::server::notifications_sent();
        metrics.opcua().server_counts(ServerCounts {
            sessions: read(
                V::Server_ServerDiagnostics_ServerDiagnosticsSummary_CurrentSessionCount,
            ),
            subscriptions: read(
                V::Server_ServerDiagnostics_ServerDiagnosticsSummary_CurrentSubscriptionCount,
            ),
            new_sessions: cumulated.saturating_sub(sessions_seen),
            new_timeouts: timeouts.saturating_sub(timeouts_seen),
            new_notifications: notifications.saturating_sub(notifications_seen),
        });
        notifications_seen = notifications;
        (sessions_seen, timeouts_seen) = (cumulated, timeouts);
    }
    metrics.opcua().server_counts(ServerCounts::default());
}
