//! What the core tells whoever listens: lease news and every write it
//! carried out or refused. The WebSocket stream, an event log or a trigger
//! subscribe here; nothing in the core knows who they are.
//!
//! The end of a lease also goes straight to the session that held it, on a
//! channel of its own that is never skipped for a slow reader (see
//! [`super::Control::open_session`]); the published copy then names that
//! session, so it can skip it.

use std::sync::Arc;
use std::time::SystemTime;

use tokio::sync::broadcast;

use super::caller::{Face, SessionId};
use super::lease_book::LeaseEvent;

/// Events held for subscribers that fall behind.
const CAPACITY: usize = 4096;

/// A write the core carried out, or refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WriteEvent {
    /// When it was settled.
    pub at: SystemTime,
    /// The face it came through.
    pub face: Face,
    /// Who sent it.
    pub who: Arc<str>,
    /// The bus.
    pub bus: Arc<str>,
    /// The unit (0: a broadcast).
    pub unit: u8,
    /// The configured drive, by index in the plant, if it is one.
    pub drive: Option<usize>,
    /// What was written, in words.
    pub what: String,
    /// What the drive confirmed, or why it failed or was refused.
    pub result: Result<String, String>,
}

/// One event of the core.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ControlEvent {
    /// News of a lease.
    Lease(LeaseEvent),
    /// A write, settled.
    Write(WriteEvent),
}

impl ControlEvent {
    /// The drive it concerns, by index in the plant.
    pub fn drive(&self) -> Option<usize> {
        match self {
            ControlEvent::Lease(e) => Some(e.drive()),
            ControlEvent::Write(w) => w.drive,
        }
    }
}

/// One published event.
#[derive(Debug, Clone)]
pub struct Published {
    /// The event.
    pub event: Arc<ControlEvent>,
    /// The session that got it directly already (it held the lease).
    pub delivered_to: Option<SessionId>,
}

/// The broadcast of the core's events.
pub struct Events {
    tx: broadcast::Sender<Published>,
}

impl Default for Events {
    fn default() -> Self {
        Events {
            tx: broadcast::channel(CAPACITY).0,
        }
    }
}

impl Events {
    /// Publishes `event`, which `delivered_to` (if any) got directly.
    pub fn publish(&self, event: Arc<ControlEvent>, delivered_to: Option<SessionId>) {
        // Nobody listening is not an error.
        let _ = self.tx.send(Published {
            event,
            delivered_to,
        });
    }

    /// A receiver of every future event.
    pub fn subscribe(&self) -> broadcast::Receiver<Published> {
        self.tx.subscribe()
    }
}
