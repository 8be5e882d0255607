//! The write log: every command that changes a drive is logged with who sent
//! it, what was written and what the drive answered, under the target
//! `drivegate::audit` so it can be routed or filtered on its own; the same
//! record goes to the bus's event subscribers (the stream's `write`
//! messages), so whoever watches live sees every write of every face.

use std::fmt::Display;
use std::time::SystemTime;

use crate::bus::BusHandle;
use crate::bus::cache::WriteRecord;

/// Logs one write to `bus`: `who` is a token name or a client address,
/// `what` the request in words, `result` the drive's answer or the error.
pub fn write<E: Display>(
    who: &str,
    bus: &BusHandle,
    unit: u8,
    what: &str,
    result: &Result<String, E>,
) {
    let (ok, answer) = log(who, bus.name(), unit, what, result);
    bus.report_write(WriteRecord {
        bus: bus.name_arc(),
        unit,
        who: who.to_string(),
        what: what.to_string(),
        ok,
        answer,
        at: SystemTime::now(),
    });
}

/// Logs a write refused before it was routed to a bus (a Modbus TCP unit no
/// bus serves, or a broadcast to every bus, `bus="all"`): no bus's watchers
/// are told.
pub fn write_unrouted<E: Display>(who: &str, unit: u8, what: &str, result: &Result<String, E>) {
    let bus = if unit == 0 { "all" } else { "-" };
    log(who, bus, unit, what, result);
}

fn log<E: Display>(
    who: &str,
    bus: &str,
    unit: u8,
    what: &str,
    result: &Result<String, E>,
) -> (bool, String) {
    match result {
        Ok(answer) => {
            tracing::info!(target: "drivegate::audit", who, bus, unit, what, answer = %answer, "write confirmed");
            (true, answer.clone())
        }
        Err(e) => {
            tracing::warn!(target: "drivegate::audit", who, bus, unit, what, error = %e, "write failed");
            (false, e.to_string())
        }
    }
}
