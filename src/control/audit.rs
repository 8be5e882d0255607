//! The write log: every write the core carries out or refuses is logged
//! with the face, who sent it, what was written and what came of it, under
//! the target `drivegate::audit` so it can be routed or filtered on its
//! own. One wording for every face.

/// Logs one write: `who` is a token name or a client address, `what` the
/// request in words, `result` the drive's answer or why it failed.
pub fn write(
    face: &str,
    who: &str,
    bus: &str,
    unit: u8,
    what: &str,
    result: &Result<String, String>,
) {
    match result {
        Ok(answer) => {
            tracing::info!(target: "drivegate::audit", face, who, bus, unit, what, answer = %answer, "write confirmed")
        }
        Err(e) => {
            tracing::warn!(target: "drivegate::audit", face, who, bus, unit, what, error = %e, "write failed")
        }
    }
}

/// Logs a write sent while the motor turns, as its caller's override
/// allowed.
pub fn forced(face: &str, who: &str, drive: &str, what: &str, speed_rpm: i16) {
    tracing::warn!(
        target: "drivegate::audit",
        face,
        who,
        drive,
        speed_rpm,
        "{what} while the motor turns, as the override allowed"
    );
}

/// Logs a lease released without a stop.
pub fn released(face: &str, who: &str, drive: &str) {
    tracing::info!(
        target: "drivegate::audit",
        face,
        who,
        drive,
        "lease released: the motor keeps its setpoint without a lease"
    );
}
