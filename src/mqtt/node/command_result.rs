//! What a DCMD's task reports back to the node: below the node and its
//! DCMD handling, which both name it.

use crate::mqtt::metric::{Value, Writable};

/// What a command's task reports.
pub(super) struct CommandResult {
    pub(super) device: String,
    pub(super) metric: Writable,
    /// The value the drive confirmed, or the failure in words.
    pub(super) outcome: Result<Value, String>,
}
