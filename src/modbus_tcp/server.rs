//! The accept loop: checks each new client's network, then asks the
//! listener's budget (`crate::connections`) for a place, then gives it a
//! task of its own.
//!
//! The budget shares every free slot while there is room (a SCADA with a
//! connection per drive takes as many as it needs); near `max_connections`
//! or the process's file limit the heaviest address gives way first: its
//! new connections are refused, and once the listener is full a quiet one
//! of its connections is closed for a client of a lighter address, so
//! idle sockets from one host never lock the PLCs out.
//! `max_connections_per_address`, when set, is a hard cap. A client
//! refused is closed at once rather than left waiting in the backlog, so a
//! SCADA retrying sees the refusal. Refusals are counted per address and
//! logged once per address and second at most. Accept errors (out of file
//! descriptors) back off. Connection tasks are tracked, so a stop waits for
//! every one of them to close (each watches the same shutdown token).

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Instant;

use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

use super::access::{Rights, SharedAccess};
use super::connection::{self, ConnectionSettings};
use super::gateway::{Client, Gateway};
use super::refusals::NotAllowedLog;
use crate::connections::accept::AcceptErrors;
use crate::connections::repeats::Shared;
use crate::connections::{Face, Guarded, Limits, Listener, Ticket, host_key};
use crate::metrics::Metrics;

/// What the accept loop enforces.
#[derive(Debug, Clone)]
pub struct ServerSettings {
    /// Allowed client networks, with their rights.
    pub access: SharedAccess,
    /// Connections served at once; `None`: twice the drives plus 32, at
    /// least 64, as the plant is now.
    pub max_connections: Option<usize>,
    /// A hard cap per address, when configured.
    pub max_connections_per_address: Option<usize>,
    /// Limits of each connection.
    pub connection: ConnectionSettings,
}

impl ServerSettings {
    /// The limits now, with the plant's drives now.
    fn limits(&self, metrics: &Metrics) -> Limits {
        Limits {
            max: self.max_connections.unwrap_or_else(|| {
                crate::config::modbus_tcp::default_connection_limit(
                    metrics.plant().now().drives().count(),
                )
            }),
            per_address: self.max_connections_per_address,
        }
    }
}

/// One listener's place in the budget, and the log of what it refused.
struct Admission {
    settings: ServerSettings,
    listener: Arc<Listener>,
    errors: AcceptErrors,
    strangers: NotAllowedLog,
    metrics: Arc<Metrics>,
}

impl Admission {
    fn new(
        face: Face,
        bound: Option<SocketAddr>,
        settings: ServerSettings,
        metrics: Arc<Metrics>,
    ) -> Self {
        let listener = metrics
            .listeners()
            .listener(face, settings.limits(&metrics));
        if let Some(bound) = bound {
            listener.set_bound(bound);
        }
        Admission {
            settings,
            listener,
            errors: AcceptErrors::new(face),
            strangers: NotAllowedLog::default(),
            metrics,
        }
    }

    /// The next connection `listener` accepts, with its place (refused
    /// ones closed, counted and logged), or `None` once `shutdown` fires.
    async fn next(
        &mut self,
        listener: &TcpListener,
        shutdown: &CancellationToken,
        allowed: bool,
    ) -> Option<(Guarded<TcpStream>, SocketAddr, Option<Rights>)> {
        loop {
            let accepted = tokio::select! {
                // A closed listener's socket fails its accepts: the stop first.
                biased;
                () = shutdown.cancelled() => return None,
                accepted = listener.accept() => accepted,
            };
            let (stream, peer) = match accepted {
                Ok(a) => a,
                Err(e) => {
                    let pause = self.errors.failed(&e);
                    tokio::select! {
                        () = tokio::time::sleep(pause) => continue,
                        () = shutdown.cancelled() => return None,
                    }
                }
            };
            self.errors.accepted();
            let rights = if allowed {
                None
            } else {
                match self.settings.access.rights(peer.ip()) {
                    Some(r) => Some(r),
                    None => {
                        self.metrics.faces().tcp_rejected("not_allowed");
                        self.strangers
                            .refused(self.listener.face(), peer, Instant::now());
                        continue;
                    }
                }
            };
            let Some(ticket) = self.place(peer) else {
                continue;
            };
            // Replies are small and latency matters more than packet count.
            if let Err(e) = stream.set_nodelay(true) {
                debug!(client = %peer, "cannot set TCP_NODELAY: {e}");
            }
            return Some((Guarded::new(stream, ticket), peer, rights));
        }
    }

    /// A place for a client at `peer`, or `None` (counted and logged).
    fn place(&self, peer: SocketAddr) -> Option<Ticket> {
        self.listener
            .set_limits(self.settings.limits(&self.metrics));
        match self.listener.admit(peer.ip()) {
            Ok(ticket) => Some(ticket),
            Err(reason) => {
                self.metrics.faces().tcp_rejected(reason.label());
                None
            }
        }
    }
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
    let connection = settings.connection;
    let mut admission = Admission::new(
        crate::connections::words::MODBUS_TCP,
        listener.local_addr().ok(),
        settings,
        metrics.clone(),
    );
    let tracker = TaskTracker::new();
    while let Some((stream, peer, rights)) = admission.next(&listener, &shutdown, false).await {
        let Some(rights) = rights else {
            continue;
        };
        let (gateway, metrics, shutdown) = (gateway.clone(), metrics.clone(), shutdown.clone());
        tracker.spawn(async move {
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
pub const ROLE_OID: &str = crate::config::ROLE_EXTENSION;

/// The rights and name of a client from its certificate (signed by
/// `client_ca`: the handshake checked it), or why it is refused: its role
/// from the core ([`crate::control::identity`]), under the running
/// configuration.
fn identify(
    certs: Option<&[rustls::pki_types::CertificateDer<'static>]>,
    tls: &TlsSettings,
    config: Option<&crate::config::Config>,
) -> Result<(Rights, Option<Arc<String>>), String> {
    use crate::control::identity::{Credential, Vouched};
    let leaf = certs
        .and_then(|c| c.first())
        .ok_or("no client certificate")?;
    let config = config.ok_or("no configuration")?;
    let identity = crate::control::identity::identify(
        config,
        crate::control::Face::ModbusTcp,
        Credential::Certificate {
            der: leaf,
            vouched: Vouched::RoleCa,
        },
    )?;
    let name = crate::tls::peer_identity(leaf, ROLE_OID)?.common_name;
    Ok((
        Rights {
            role: identity.role,
            allow_saves_while_moving: tls.section.allow_saves_while_moving,
            comm_loss: tls.section.comm_loss().map(|l| crate::control::CommLoss {
                after: l.after,
                action: l.action,
                face: crate::control::Face::ModbusTcp,
            }),
        },
        name.map(Arc::new),
    ))
}

/// Accepts Modbus/TCP Security clients until `shutdown` fires: the TLS
/// handshake (a client certificate of `client_ca` required) runs in the
/// connection's task within the idle timeout, then the client's role comes
/// from its certificate and it is served as a plain client of that role
/// would be. The connection limits are the plain listener's, counted on
/// their own.
pub async fn run_tls(
    listener: TcpListener,
    gateway: Arc<Gateway>,
    settings: ServerSettings,
    tls: TlsSettings,
    shutdown: CancellationToken,
) {
    let metrics = gateway.metrics().clone();
    let connection = settings.connection;
    let mut admission = Admission::new(
        crate::connections::words::MODBUS_TLS,
        listener.local_addr().ok(),
        settings,
        metrics.clone(),
    );
    let tracker = TaskTracker::new();
    let tls = Arc::new(tls);
    // Handshakes and identities that fail, said once per address, cause
    // and second at most: a scanner or a plain-text client in a loop
    // writes a few lines, not one per connection.
    let noisy: Arc<Shared<(IpAddr, &'static str)>> = Arc::default();
    while let Some((stream, peer, _)) = admission.next(&listener, &shutdown, true).await {
        let (gateway, metrics, shutdown, tls, noisy) = (
            gateway.clone(),
            metrics.clone(),
            shutdown.clone(),
            tls.clone(),
            noisy.clone(),
        );
        let from = host_key(peer.ip());
        tracker.spawn(async move {
            let acceptor = tokio_rustls::TlsAcceptor::from(tls.config.current());
            let handshake = tokio::select! {
                h = tokio::time::timeout(connection.idle_timeout, acceptor.accept(stream)) => h,
                () = shutdown.cancelled() => return,
            };
            let stream = match handshake {
                Ok(Ok(stream)) => stream,
                Ok(Err(e)) => {
                    metrics.security().tls_handshake_failed("modbus_tcp");
                    if let Some(more) = noisy.due((from, "handshake")) {
                        warn!(client = %peer, "Modbus/TCP Security handshake failed: {e}. Counted in drivegate_tls_handshake_failures_total{{face=\"modbus_tcp\"}}; logged once per address and second at most{more}");
                    }
                    return;
                }
                Err(_) => {
                    metrics.security().tls_handshake_failed("modbus_tcp");
                    debug!(client = %peer, "Modbus/TCP Security handshake not done in time");
                    return;
                }
            };
            let config = gateway.control().follow_config().borrow().clone();
            let (rights, name) = match identify(
                stream.get_ref().1.peer_certificates(),
                &tls,
                config.as_deref(),
            ) {
                Ok(found) => found,
                Err(why) => {
                    metrics.security().tls_client_refused("role");
                    if let Some(more) = noisy.due((from, "role")) {
                        warn!(client = %peer, "Modbus/TCP Security client refused: {why}{more}");
                    }
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
