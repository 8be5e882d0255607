//! The write log: every command that changes a drive is logged with who sent
//! it, what was written and what the drive answered, under the target
//! `drivegate::audit` so it can be routed or filtered on its own.

use std::fmt::Display;

/// Logs one write: `who` is a token name or a client address, `what` the
/// request in words, `result` the drive's answer or the error.
pub fn write<E: Display>(who: &str, bus: &str, unit: u8, what: &str, result: &Result<String, E>) {
    match result {
        Ok(answer) => {
            tracing::info!(target: "drivegate::audit", who, bus, unit, what, answer = %answer, "write confirmed")
        }
        Err(e) => {
            tracing::warn!(target: "drivegate::audit", who, bus, unit, what, error = %e, "write failed")
        }
    }
}
