//! The accept loop: checks each new client's network and the connection
//! limit, then gives it a task of its own.
//!
//! The limit is a semaphore of `max_connections` permits, each connection
//! task holding one: a client beyond the limit is closed at once rather than
//! left waiting in the backlog, so a SCADA system retrying sees the refusal
//! and the gateway never holds more sockets than it was sized for.
//! Connection tasks are tracked, so a stop waits for every one of them to
//! close (each watches the same shutdown token).

use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

use super::access::{Rights, SharedAccess};
use super::connection::{self, ConnectionSettings};
use super::gateway::{Client, Gateway};

/// What the accept loop enforces.
#[derive(Debug, Clone)]
pub struct ServerSettings {
    /// Allowed client networks, with their rights.
    pub access: SharedAccess,
    /// Connections served at once.
    pub max_connections: usize,
    /// Limits of each connection.
    pub connection: ConnectionSettings,
}

/// Accepts clients until `shutdown` fires, then waits for their connections
/// to close.
pub async fn run(
    listener: TcpListener,
    gateway: Arc<Gateway>,
    settings: ServerSettings,
    shutdown: CancellationToken,
) {
    let metrics = gateway.metrics().clone();
    let slots = Arc::new(Semaphore::new(settings.max_connections));
    let tracker = TaskTracker::new();
    loop {
        let accepted = tokio::select! {
            // A closed listener's socket fails its accepts: the stop first.
            biased;
            () = shutdown.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors, usually: let connections close
                // rather than spin on the error.
                warn!("Modbus TCP accept failed: {e}; pausing accepts for 100 ms");
                tokio::select! {
                    () = tokio::time::sleep(Duration::from_millis(100)) => continue,
                    () = shutdown.cancelled() => break,
                }
            }
        };
        let Some(rights) = settings.access.rights(peer.ip()) else {
            metrics.faces().tcp_rejected("not_allowed");
            warn!(client = %peer, "Modbus TCP connection refused: the address is in none of the networks of [modbus_tcp] allowed_networks and clients");
            continue;
        };
        let Ok(permit) = slots.clone().try_acquire_owned() else {
            metrics.faces().tcp_rejected("limit");
            warn!(client = %peer, "Modbus TCP connection refused: {} connections are open (max_connections)", settings.max_connections);
            continue;
        };
        // Replies are small and latency matters more than packet count.
        if let Err(e) = stream.set_nodelay(true) {
            debug!(client = %peer, "cannot set TCP_NODELAY: {e}");
        }
        let (gateway, metrics, shutdown) = (gateway.clone(), metrics.clone(), shutdown.clone());
        let connection = settings.connection;
        tracker.spawn(async move {
            let _slot = permit;
            let _open = metrics.faces().tcp_connection();
            debug!(client = %peer, role = rights.role.name(), "Modbus TCP client connected");
            // The connection is a session of the core: the leases of its
            // communication-loss function are held by it (news of their end
            // has nowhere to go on Modbus TCP: it is on the stream).
            let (session, _news) = gateway
                .control()
                .open_session("its Modbus TCP connection closed", rights.comm_loss);
            let client = Client::new(peer, rights, session.id());
            connection::serve(stream, client, session, gateway, connection, shutdown).await;
        });
    }
    drop(listener);
    tracker.close();
    tracker.wait().await;
    info!("Modbus TCP listener stopped");
}

/// What the Modbus/TCP Security accept loop needs beyond the plain one.
pub struct TlsSettings {
    /// The server configuration (client certificates required), reloadable.
    pub config: Arc<crate::tls::Reloadable>,
    /// The section: default role, communication loss, saves while moving.
    pub section: crate::config::ModbusTlsConfig,
    /// Every client is a viewer (`[modbus_tcp] read_only`).
    pub read_only: bool,
}

/// The role extension of Modbus/TCP Security certificates.
pub const ROLE_OID: &str = "1.3.6.1.4.1.50316.802.1";

/// The rights and name of a client from its certificate, or why it is
/// refused.
fn identify(
    certs: Option<&[rustls::pki_types::CertificateDer<'static>]>,
    tls: &TlsSettings,
) -> Result<(Rights, Option<Arc<String>>), String> {
    let leaf = certs
        .and_then(|c| c.first())
        .ok_or("no client certificate")?;
    let identity = crate::tls::peer_identity(leaf, ROLE_OID)?;
    let role = match &identity.extension {
        None => tls.section.default_role,
        Some(Ok(text)) => crate::config::ModbusTlsConfig::role_named(text).ok_or_else(|| {
            format!("the certificate's role \"{text}\" is none of viewer, operator, admin")
        })?,
        Some(Err(why)) => return Err(format!("the certificate's role extension: {why}")),
    };
    let role = if tls.read_only {
        crate::control::Role::Viewer
    } else {
        role
    };
    Ok((
        Rights {
            role,
            allow_saves_while_moving: tls.section.allow_saves_while_moving,
            comm_loss: tls.section.comm_loss().map(|l| crate::control::CommLoss {
                after: l.after,
                action: l.action,
                face: crate::control::Face::ModbusTcp,
            }),
        },
        identity.common_name.map(Arc::new),
    ))
}

/// Accepts Modbus/TCP Security clients until `shutdown` fires: the TLS
/// handshake (a client certificate of `client_ca` required) runs in the
/// connection's task within the idle timeout, then the client's role comes
/// from its certificate and it is served as a plain client of that role
/// would be. The connection limit is the plain listener's own count.
pub async fn run_tls(
    listener: TcpListener,
    gateway: Arc<Gateway>,
    settings: ServerSettings,
    tls: TlsSettings,
    shutdown: CancellationToken,
) {
    let metrics = gateway.metrics().clone();
    let slots = Arc::new(Semaphore::new(settings.max_connections));
    let tracker = TaskTracker::new();
    let tls = Arc::new(tls);
    loop {
        let accepted = tokio::select! {
            // A closed listener's socket fails its accepts: the stop first.
            biased;
            () = shutdown.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                warn!("Modbus/TCP Security accept failed: {e}; pausing accepts for 100 ms");
                tokio::select! {
                    () = tokio::time::sleep(Duration::from_millis(100)) => continue,
                    () = shutdown.cancelled() => break,
                }
            }
        };
        let Ok(permit) = slots.clone().try_acquire_owned() else {
            metrics.faces().tcp_rejected("limit");
            warn!(client = %peer, "Modbus/TCP Security connection refused: {} connections are open (max_connections)", settings.max_connections);
            continue;
        };
        if let Err(e) = stream.set_nodelay(true) {
            debug!(client = %peer, "cannot set TCP_NODELAY: {e}");
        }
        let (gateway, metrics, shutdown, tls) = (
            gateway.clone(),
            metrics.clone(),
            shutdown.clone(),
            tls.clone(),
        );
        let connection = settings.connection;
        tracker.spawn(async move {
            let _slot = permit;
            let acceptor = tokio_rustls::TlsAcceptor::from(tls.config.current());
            let handshake = tokio::select! {
                h = tokio::time::timeout(connection.idle_timeout, acceptor.accept(stream)) => h,
                () = shutdown.cancelled() => return,
            };
            let stream = match handshake {
                Ok(Ok(stream)) => stream,
                Ok(Err(e)) => {
                    metrics.security().tls_handshake_failed("modbus_tcp");
                    warn!(client = %peer, "Modbus/TCP Security handshake failed: {e}");
                    return;
                }
                Err(_) => {
                    metrics.security().tls_handshake_failed("modbus_tcp");
                    debug!(client = %peer, "Modbus/TCP Security handshake not done in time");
                    return;
                }
            };
            let (rights, name) = match identify(stream.get_ref().1.peer_certificates(), &tls) {
                Ok(found) => found,
                Err(why) => {
                    metrics.security().tls_client_refused("role");
                    warn!(client = %peer, "Modbus/TCP Security client refused: {why}");
                    return;
                }
            };
            let _open = metrics.faces().tcp_connection();
            info!(
                client = %peer,
                name = name.as_ref().map_or("(no CN)", |n| n.as_str()),
                role = rights.role.name(),
                "Modbus/TCP Security client connected"
            );
            let (session, _news) = gateway.control().open_session(
                "its Modbus/TCP Security connection closed",
                rights.comm_loss,
            );
            let client = Client::named(peer, name, rights, session.id());
            connection::serve(stream, client, session, gateway, connection, shutdown).await;
        });
    }
    drop(listener);
    tracker.close();
    tracker.wait().await;
    info!("Modbus/TCP Security listener stopped");
}
