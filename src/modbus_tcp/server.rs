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

use super::access::Access;
use super::connection::{self, ConnectionSettings};
use super::gateway::{Client, Gateway};

/// What the accept loop enforces.
#[derive(Debug, Clone)]
pub struct ServerSettings {
    /// Allowed client networks, with their rights.
    pub access: Access,
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
