//! The priority classes of bus jobs: a leaf, shared by the queue, the
//! jobs and the errors that name a class.

use std::fmt;

use crate::listed::listed_enum;

listed_enum! {
    /// Priority classes, served strictly in this order (with a share kept for
    /// polling, see the scheduler).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
    pub enum Priority {
        /// Emergency brake and safe-stop actions: next on the wire, always.
        Emergency,
        /// Setpoints, configuration, passthrough and fresh reads.
        Command,
        /// Background status polling.
        Poll,
    }
}

impl Priority {
    /// Stable name for logs and metric labels.
    pub fn name(self) -> &'static str {
        match self {
            Priority::Emergency => "emergency",
            Priority::Command => "command",
            Priority::Poll => "poll",
        }
    }

    /// Index into per-class arrays.
    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Priority {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}
