//! The OPC UA server's connection gate (`opcua::server::gate`, added to
//! the vendored crate for it): its connections and sessions are shared by
//! the budget every listener uses (`crate::connections`), and its accepts
//! back off after failures like every listener's.
//!
//! A connection carries one secure channel, and every channel holds a file
//! descriptor until it closes: one address opening channels without end
//! (HEL, OPN, nothing more) would take every file of the process, and HTTP
//! and Modbus TCP with them. So a connection gets a place in the book at
//! accept (`[opcua] max_connections`, the file reserve), and a session one
//! among the open sessions (`[opcua] max_sessions`): addresses share every
//! free slot, and near the limit the heaviest address gives way first, so
//! an operator from another address always finds a session.

use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use opcua::server::ServerHandle;
use opcua::server::gate::{ConnectionGate, ConnectionPass, SessionAdmission, SessionSeat};
use tokio_util::sync::CancellationToken;

use crate::config::OpcUaConfig;
use crate::connections::accept::AcceptErrors;
use crate::connections::words::{OPCUA, OPCUA_SESSIONS};
use crate::connections::{Limits, Listener, Seat, Ticket};
use crate::metrics::Metrics;

/// The gate of one server.
pub struct Gate {
    connections: Arc<Listener>,
    sessions: Arc<Listener>,
    errors: Mutex<AcceptErrors>,
}

impl Gate {
    /// The gate of `section`'s limits for the server bound at `bound`, its
    /// listeners exported in `metrics`.
    pub fn new(section: &OpcUaConfig, bound: SocketAddr, metrics: &Metrics) -> Self {
        let gate = Gate {
            connections: metrics.listeners().listener(
                OPCUA,
                Limits {
                    max: section.max_connections,
                    per_address: section.max_connections_per_address.map(|n| n.0),
                },
            ),
            sessions: metrics.listeners().listener(
                OPCUA_SESSIONS,
                Limits {
                    max: section.max_sessions,
                    per_address: section.max_sessions_per_address.map(|n| n.0),
                },
            ),
            errors: Mutex::new(AcceptErrors::new(OPCUA)),
        };
        gate.connections.set_bound(bound);
        gate.sessions.set_bound(bound);
        gate
    }

    /// Tells the sessions' listener of the server's sessions every second
    /// (they end without asking the gate), until `stop`.
    pub fn follow(&self, handle: ServerHandle, stop: CancellationToken) {
        let sessions = self.sessions.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tokio::select! {
                    _ = tick.tick() => {}
                    () = stop.cancelled() => return,
                }
                let peers = handle.session_manager().read().peer_addresses();
                sessions.set_seats(peers.into_iter().map(|p| p.map(|p| p.ip())));
            }
        });
    }

    fn errors(&self) -> std::sync::MutexGuard<'_, AcceptErrors> {
        self.errors.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A connection's place in the book.
struct Pass(Ticket);

impl ConnectionPass for Pass {
    fn touch(&self) {
        self.0.touch();
    }

    fn closing(&self) -> CancellationToken {
        self.0.closing().clone()
    }
}

impl ConnectionGate for Gate {
    fn admit(&self, peer: SocketAddr) -> Option<Box<dyn ConnectionPass>> {
        let ticket = self.connections.admit(peer.ip()).ok()?;
        Some(Box::new(Pass(ticket)))
    }

    fn admit_session(&self, peer: Option<SocketAddr>, seats: &[SessionSeat]) -> SessionAdmission {
        // The session closest to its timeout is the quietest.
        let seats: Vec<Seat> = seats
            .iter()
            .map(|s| Seat {
                address: s.peer.map(|p| p.ip()),
                active: s.activated,
                last: s.deadline,
            })
            .collect();
        let admission = match self.sessions.admit_seat(peer.map(|p| p.ip()), &seats) {
            Ok(None) => SessionAdmission::Admit,
            Ok(Some(i)) => SessionAdmission::AdmitClosing(i),
            Err(_) => return SessionAdmission::Refuse,
        };
        let closed = match admission {
            SessionAdmission::AdmitClosing(i) => Some(i),
            _ => None,
        };
        let held = seats
            .iter()
            .enumerate()
            .filter(|(i, _)| Some(*i) != closed)
            .map(|(_, s)| s.address)
            .chain(std::iter::once(peer.map(|p| p.ip())));
        self.sessions.set_seats(held);
        admission
    }

    fn accept_failed(&self, error: &io::Error) -> Duration {
        self.errors().failed(error)
    }

    fn accepted(&self) {
        self.errors().accepted();
    }
}
