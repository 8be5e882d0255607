//! The state of the wire to each drive: its bus's port, and whether the
//! drive answers. At the bottom of the bus, so the cache, the freshness
//! judge, the handle and the scheduler all speak of it alike.

use std::time::SystemTime;

/// State of a bus's serial port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PortState {
    /// Not opened yet.
    Opening,
    /// Open and working since then.
    Up {
        /// When it opened.
        since: SystemTime,
    },
    /// Closed: failed and being reopened with backoff, or stopped for good
    /// (at shutdown, or when the bus could not start); the reason says which.
    Down {
        /// When it failed.
        since: SystemTime,
        /// Why.
        reason: String,
    },
}

/// Whether a drive answers its polls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// Not polled yet.
    Unknown,
    /// Answering.
    Online,
    /// Stopped answering; polled with backoff.
    Offline,
}

impl Link {
    /// Stable name for the API.
    pub fn name(self) -> &'static str {
        match self {
            Link::Unknown => "unknown",
            Link::Online => "online",
            Link::Offline => "offline",
        }
    }
}
