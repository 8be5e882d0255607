//! The accept loop: checks each new client's network, the per-address cap
//! and the connection limit, then gives it a task of its own.
//!
//! The limit is a semaphore of `max_connections` permits, each connection
//! task holding one: a client beyond the limit is closed at once rather than
//! left waiting in the backlog, so a SCADA system retrying sees the refusal
//! and the gateway never holds more sockets than it was sized for. One
//! address holds at most `max_connections_per_address` of them
//! ([`Addresses`]), so idle sockets from one host cannot lock the others
//! out. Refusals are counted, and logged once per address and burst
//! ([`RefusalLog`]). Connection tasks are tracked, so a stop waits for every
//! one of them to close (each watches the same shutdown token).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::net::TcpListener;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

use super::access::{Rights, SharedAccess};
use super::addresses::{AddressSlot, Addresses};
use super::connection::{self, ConnectionSettings};
use super::gateway::{Client, Gateway};
use super::refusals::{QUIET, RefusalLog, Refused, Report};
use crate::metrics::Metrics;

/// What the accept loop enforces.
#[derive(Debug, Clone)]
pub struct ServerSettings {
    /// Allowed client networks, with their rights.
    pub access: SharedAccess,
    /// Connections served at once.
    pub max_connections: usize,
    /// Connections one address may hold at once.
    pub max_connections_per_address: usize,
    /// Limits of each connection.
    pub connection: ConnectionSettings,
}

/// A connection's places: one of the listener's, one of its address's.
struct Admitted {
    _slot: OwnedSemaphorePermit,
    _address: AddressSlot,
}

/// The limits of one listener, and the log of what they refused.
struct Admission {
    /// "Modbus TCP" or "Modbus/TCP Security", for the log.
    face: &'static str,
    slots: Arc<Semaphore>,
    max_connections: usize,
    addresses: Arc<Addresses>,
    log: RefusalLog,
    metrics: Arc<Metrics>,
}

impl Admission {
    fn new(face: &'static str, settings: &ServerSettings, metrics: Arc<Metrics>) -> Self {
        Admission {
            face,
            slots: Arc::new(Semaphore::new(settings.max_connections)),
            max_connections: settings.max_connections,
            addresses: Addresses::new(settings.max_connections_per_address),
            log: RefusalLog::default(),
            metrics,
        }
    }

    /// Places for a client at `peer`: its address's first, so that one
    /// host's surplus is refused as such, then the listener's.
    fn admit(&mut self, peer: SocketAddr) -> Option<Admitted> {
        let Some(address) = self.addresses.take(peer.ip()) else {
            self.refuse(peer, Refused::PerAddress);
            return None;
        };
        let Ok(slot) = self.slots.clone().try_acquire_owned() else {
            self.refuse(peer, Refused::Limit);
            return None;
        };
        Some(Admitted {
            _slot: slot,
            _address: address,
        })
    }

    /// Counts a refusal, and logs it if it is the first of its address's
    /// burst.
    fn refuse(&mut self, peer: SocketAddr, reason: Refused) {
        self.metrics.faces().tcp_rejected(reason.label());
        let before = match self.log.refused(peer.ip(), reason, Instant::now()) {
            Report::Quiet => return,
            Report::Log { before } => before,
            Report::LogMany => {
                warn!(
                    "{} connections refused from more than {} addresses at once ({}); further refusals of addresses not yet logged are counted in drivegate_modbus_tcp_connections_rejected_total, not logged",
                    self.face,
                    super::refusals::CAPACITY,
                    reason.label()
                );
                return;
            }
        };
        let why = match reason {
            Refused::NotAllowed => "the address is in none of the networks of [modbus_tcp] allowed_networks (not set: loopback only) and [[modbus_tcp.clients]]; to let it in, add a [[modbus_tcp.clients]] entry with its network and a role".to_string(),
            Refused::PerAddress => format!(
                "the address holds {} connections already, the most one address may ([modbus_tcp] max_connections_per_address)",
                self.addresses.limit()
            ),
            Refused::Limit => format!(
                "{} connections are open ([modbus_tcp] max_connections)",
                self.max_connections
            ),
        };
        let last = if before > 1 {
            format!(" Its last burst: {before} refused.")
        } else {
            String::new()
        };
        warn!(
            client = %peer,
            "{} connection refused: {why}. Further refusals of this address are counted (drivegate_modbus_tcp_connections_rejected_total{{reason=\"{}\"}}), not logged, until it has been quiet for {} s.{last}",
            self.face,
            reason.label(),
            QUIET.as_secs()
        );
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
    let mut admission = Admission::new("Modbus TCP", &settings, metrics.clone());
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
            admission.refuse(peer, Refused::NotAllowed);
            continue;
        };
        let Some(permit) = admission.admit(peer) else {
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
    let mut admission = Admission::new("Modbus/TCP Security", &settings, metrics.clone());
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
        let Some(permit) = admission.admit(peer) else {
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
            let config = gateway.control().follow_config().borrow().clone();
            let (rights, name) = match identify(
                stream.get_ref().1.peer_certificates(),
                &tls,
                config.as_deref(),
            ) {
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
