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
use super::news::{AlarmNews, DriftChecked, FreshnessNews, SettingsApplied};
use super::outcome::{Failure, Outcome, WriteResult};
use crate::bus::BusError;

/// Events held for subscribers that fall behind.
const CAPACITY: usize = 4096;

/// What became of a write, as the log and the stream tell it: typed here,
/// put in words only where it is shown ([`std::fmt::Display`]).
#[derive(Debug, Clone, PartialEq)]
pub enum WriteEnd {
    /// The drive confirmed it.
    Confirmed,
    /// Sent as a broadcast: drives do not reply.
    Broadcast,
    /// Refused, not sent, refused by the drive, or not confirmed.
    Failed(Failure),
    /// Its caller went away before the drive answered (why, in words).
    CallerGone(String),
    /// Refused before it became a request the core could decide on: a
    /// value out of the drive's range, a mode it does not have, a request
    /// of the wrong shape (why, in words). Nothing was sent.
    Invalid(String),
}

impl WriteEnd {
    /// What a write's result comes to.
    pub fn of(result: &WriteResult) -> Self {
        match result {
            Ok(Outcome::Confirmed { .. }) => WriteEnd::Confirmed,
            Ok(Outcome::Broadcast) => WriteEnd::Broadcast,
            Err(f) => WriteEnd::Failed(f.clone()),
        }
    }

    /// A write the bus could not carry out (nothing sent, or not
    /// confirmed).
    pub fn bus_error(error: BusError) -> Self {
        WriteEnd::Failed(if error.not_sent() {
            Failure::NotSent(error)
        } else {
            Failure::Unknown { error, reply: None }
        })
    }

    /// True when the drive confirmed it (or it went out as a broadcast).
    pub fn is_ok(&self) -> bool {
        matches!(self, WriteEnd::Confirmed | WriteEnd::Broadcast)
    }
}

impl std::fmt::Display for WriteEnd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WriteEnd::Confirmed => f.write_str("confirmed by the drive"),
            WriteEnd::Broadcast => f.write_str("sent as a broadcast (drives do not reply)"),
            WriteEnd::Failed(failure) => write!(f, "{failure}"),
            WriteEnd::CallerGone(why) | WriteEnd::Invalid(why) => f.write_str(why),
        }
    }
}

/// A write the core carried out, or refused.
#[derive(Debug, Clone, PartialEq)]
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
    pub result: WriteEnd,
}

/// One event of the core.
#[derive(Debug, Clone, PartialEq)]
pub enum ControlEvent {
    /// News of a lease.
    Lease(LeaseEvent),
    /// A write, settled.
    Write(WriteEvent),
    /// A settings document put on a drive (its writes are events too).
    Settings(SettingsApplied),
    /// A drive compared with its declared settings.
    Drift(DriftChecked),
    /// A Modbus TCP client's communication-loss function ended its lease
    /// on `drive` (its stop follows as lease news): by silence, or
    /// `closed` by its connection closing.
    CommLoss {
        /// Drive index.
        drive: usize,
        /// True when its connection closed.
        closed: bool,
    },
    /// An alarm raised, cleared or acknowledged.
    Alarm(AlarmNews),
    /// A drive's data changed freshness (live, stale, offline, never,
    /// bus-down).
    Freshness(FreshnessNews),
}

impl ControlEvent {
    /// The drive it concerns, by index in the plant.
    pub fn drive(&self) -> Option<usize> {
        match self {
            ControlEvent::Lease(e) => Some(e.drive()),
            ControlEvent::Write(w) => w.drive,
            ControlEvent::Settings(s) => Some(s.report.drive),
            ControlEvent::Drift(d) => Some(d.drive),
            ControlEvent::CommLoss { drive, .. } => Some(*drive),
            ControlEvent::Freshness(news) => Some(news.drive),
            // Every client's business: the console's banner shows them all.
            ControlEvent::Alarm(_) => None,
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
