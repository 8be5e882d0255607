//! A gate the server asks before it serves a connection or creates a
//! session, so that the application decides how they are shared between
//! clients (per address, against the process's file descriptors), and how
//! the accept loop backs off when `accept` fails.

use std::{
    io,
    net::SocketAddr,
    time::{Duration, Instant},
};

use tokio_util::sync::CancellationToken;

/// A connection's admission, held by its task until the connection ends.
pub trait ConnectionPass: Send + Sync {
    /// The connection received a message now.
    fn touch(&self);
    /// Fires when the connection is to be closed to make room for others.
    fn closing(&self) -> CancellationToken;
}

/// A session as the gate sees it when another is to be created.
#[derive(Debug, Clone, Copy)]
pub struct SessionSeat {
    /// The address of the client it was last activated from, if any.
    pub peer: Option<SocketAddr>,
    /// Whether it was activated.
    pub activated: bool,
    /// When it expires unless its client asks for something.
    pub deadline: Instant,
}

/// What to do with a session about to be created.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SessionAdmission {
    /// Create it.
    Admit,
    /// Create it once the session at this index of the seats is closed.
    AdmitClosing(usize),
    /// Refuse it (`BadTooManySessions`).
    Refuse,
}

/// The application's decisions on connections and sessions.
pub trait ConnectionGate: Send + Sync {
    /// A connection from `peer` was accepted: its pass, or `None` to close
    /// it at once (the client is told `BadTcpServerTooBusy`).
    fn admit(&self, peer: SocketAddr) -> Option<Box<dyn ConnectionPass>>;
    /// A session is to be created for `peer` (the connection's address)
    /// while `seats` are open.
    fn admit_session(&self, peer: Option<SocketAddr>, seats: &[SessionSeat]) -> SessionAdmission;
    /// `accept` failed with `error`: how long to pause accepting (the
    /// gate says it in the log as it sees fit).
    fn accept_failed(&self, error: &io::Error) -> Duration;
    /// A connection was accepted after failures.
    fn accepted(&self) {}
}
