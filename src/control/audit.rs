//! The write log: every write the core carries out or refuses is logged
//! with the face, who sent it, what was written and what came of it, under
//! the target `drivegate::audit` so it can be routed or filtered on its
//! own. One wording for every face. The news of leases (their end, with
//! why and what their stop did) is logged here too.

use super::events::WriteEnd;
use super::lease_book::LeaseEvent;
use super::news::{DecisionKind, ReloadResult, RestartNote, SettingsError, SettingsReport};
use super::request::Write;
use crate::drive::wanted::Difference;

/// Logs one write: `who` is a token name or a client address, `what` the
/// request in words, `result` the drive's answer or why it failed.
pub fn write(face: &str, who: &str, bus: &str, unit: u8, what: &str, result: &WriteEnd) {
    if result.is_ok() {
        tracing::info!(target: "drivegate::audit", face, who, bus, unit, what, answer = %result, "write confirmed")
    } else {
        tracing::warn!(target: "drivegate::audit", face, who, bus, unit, what, error = %result, "write failed")
    }
}

/// Logs a write its face refused before it reached the core's rules (a
/// Modbus TCP request for no configured bus, or of the wrong shape), in
/// the wording of every other write.
pub fn refused_by_face(face: &str, who: &str, bus: &str, unit: u8, write: &Write, why: &str) {
    self::write(
        face,
        who,
        bus,
        unit,
        &write.describe(),
        &WriteEnd::Invalid(why.to_string()),
    );
}

/// Logs a sign-in refused on `face` from `client` (its address), with why
/// (a wrong or paused secret, a password sent in clear, a certificate
/// without trust or role): never the secret itself. Like every audit line
/// it names who: nobody, since the sign-in failed.
pub fn sign_in_refused(face: &str, client: &str, why: &str) {
    tracing::warn!(target: "drivegate::audit", face, who = "not signed in", client, why, "sign-in refused");
}

/// Logs a message a face dropped unread because it is larger than its
/// configuration takes (`limit` bytes): who sent it is known only as far
/// as the face knows (MQTT: the broker's login), its topic says what it
/// was for.
pub fn message_too_large(
    face: &str,
    who: &str,
    topic: &str,
    bytes: u64,
    limit: u64,
    retained: bool,
) {
    tracing::warn!(
        target: "drivegate::audit",
        face,
        who,
        topic,
        bytes,
        limit,
        retained,
        "message dropped: larger than the face takes"
    )
}

/// Logs a command refused because it did not come live from its sender
/// (`what` in words, for `subject`, a drive or the node): "a retained
/// command was ignored", with who sent it and why.
pub fn not_live(face: &str, who: &str, subject: &str, what: &str, ignored: &str, why: &str) {
    tracing::warn!(
        target: "drivegate::audit",
        face,
        who,
        drive = subject,
        what,
        why,
        "{ignored}"
    );
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

/// Logs an address setting confirmed by a status read at the new address
/// (the broadcast itself is logged by [`write`]).
pub fn address_verified(face: &str, who: &str, bus: &str, address: u8) {
    tracing::info!(
        target: "drivegate::audit",
        face,
        who,
        bus,
        address,
        "drive address set and verified"
    );
}

/// Logs the start, end or abandonment of a drive replacement (its writes
/// are logged by [`write`] as they happen).
pub fn replacement(face: &str, who: &str, drive: &str, event: &str, detail: &str) {
    tracing::info!(
        target: "drivegate::audit",
        face,
        who,
        drive,
        detail,
        "drive replacement {event}"
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

/// Logs an alarm acknowledged by `who` (the alarm's own raising and
/// clearing are logged under `drivegate::alarms`).
pub fn alarm_acknowledged(face: &str, who: &str, id: u64, kind: &str, drive: &str, text: &str) {
    tracing::info!(
        target: "drivegate::audit",
        face,
        who,
        alarm = id,
        kind,
        drive,
        "alarm acknowledged: {text}"
    );
}

/// Logs news of a lease on drive `drive`: its end (why, and what its stop
/// did), or how a stop that failed at first ended. `who` is its holder.
pub fn lease(drive: &str, event: &LeaseEvent) {
    match event {
        LeaseEvent::Ended { owner, reason, .. } => tracing::info!(
            target: "drivegate::audit",
            who = %owner,
            drive,
            reason = %reason,
            "lease ended without a stop"
        ),
        LeaseEvent::Expired {
            owner,
            reason,
            action,
            sent,
            ok,
            result,
            retrying,
            ..
        } => {
            let sent = sent.as_deref().unwrap_or("nothing");
            if *ok {
                tracing::warn!(
                    target: "drivegate::audit",
                    who = %owner,
                    drive,
                    reason = %reason,
                    action = action.name(),
                    sent,
                    result = %result,
                    "lease ended with its stop"
                );
            } else {
                tracing::warn!(
                    target: "drivegate::audit",
                    who = %owner,
                    drive,
                    reason = %reason,
                    action = action.name(),
                    sent,
                    error = %result,
                    retrying,
                    "lease ended; its stop failed"
                );
            }
        }
        LeaseEvent::StopSettled {
            owner,
            action,
            stopped,
            attempts,
            result,
            ..
        } => tracing::warn!(
            target: "drivegate::audit",
            who = %owner,
            drive,
            action = action.name(),
            stopped,
            attempts,
            result = %result,
            "stop of an ended lease settled"
        ),
    }
}

/// A decision of the start-up replay of the safety journal.
pub fn restart(note: &RestartNote) {
    let (drive, decision, text) = (
        note.drive.as_str(),
        note.decision.name(),
        note.text.as_str(),
    );
    let who = note.who.as_deref().unwrap_or("drivegate");
    if note.decision == DecisionKind::LeaseKept {
        tracing::info!(target: "drivegate::audit", face = "restart", drive, who, decision, "restart: {text}")
    } else {
        tracing::warn!(target: "drivegate::audit", face = "restart", drive, who, decision, "restart: {text}")
    }
}

/// Logs a reload of the configuration: who asked, and what it changed or
/// why it was refused.
pub fn reload(by: &str, result: &ReloadResult) {
    match result {
        Ok(applied) => tracing::info!(
            target: "drivegate::audit",
            who = by,
            changes = %applied.changes.join("; "),
            "configuration reloaded"
        ),
        Err(refused) => tracing::warn!(
            target: "drivegate::audit",
            who = by,
            why = %refused,
            "configuration reload refused"
        ),
    }
}
/// Logs a change of the configuration file asked for by `by` (the
/// console's editor, a token made or revoked): `what` in words, `diff` the
/// file's lines as a unified diff, and what came of it (written and
/// reloaded, or refused and nothing written).
pub fn config_written(by: &str, what: &str, diff: &str, result: &ReloadResult) {
    match result {
        Ok(applied) => tracing::info!(
            target: "drivegate::audit",
            who = by,
            what,
            diff,
            changes = %applied.changes.join("; "),
            "configuration file changed"
        ),
        Err(refused) => tracing::warn!(
            target: "drivegate::audit",
            who = by,
            what,
            diff,
            why = %refused,
            "configuration file change refused; nothing was written"
        ),
    }
}

/// Logs a certificate trusted, removed or renewed by `by` (or the
/// refusal): `action` in words, the certificate by its subject and
/// SHA-1 thumbprint, and `result`.
pub fn certificate(
    by: &str,
    action: &str,
    subject: &str,
    thumbprint: &str,
    result: Result<&str, &str>,
) {
    match result {
        Ok(done) => tracing::info!(
            target: "drivegate::audit",
            who = by,
            action,
            subject,
            thumbprint,
            done,
            "certificate {action}"
        ),
        Err(why) => tracing::warn!(
            target: "drivegate::audit",
            who = by,
            action,
            subject,
            thumbprint,
            why,
            "certificate not {action}"
        ),
    }
}

/// Logs a settings document refused whole: nothing was written.
pub fn settings_refused(face: &str, who: &str, drive: &str, error: &SettingsError) {
    let why = match error {
        SettingsError::Invalid(refused) => refused
            .iter()
            .map(|r| format!("{}: {}", r.setting.key(), r.detail))
            .collect::<Vec<_>>()
            .join("; "),
        SettingsError::Failed(failure) => failure.to_string(),
    };
    tracing::warn!(target: "drivegate::audit", face, who, drive, error = %why, "settings document refused; nothing was written");
}

/// Logs a settings document put on a drive: every setting that changed
/// (or failed), in one line beside the lines of its writes.
pub fn settings_applied(face: &str, who: &str, drive: &str, report: &SettingsReport) {
    let what = report.words();
    if report.complete() && report.read_back_error.is_none() {
        tracing::info!(target: "drivegate::audit", face, who, drive, what, "settings document applied");
    } else {
        let read_back = report.read_back_error.as_deref().unwrap_or("done");
        tracing::warn!(target: "drivegate::audit", face, who, drive, what, read_back, "settings document failed part-way");
    }
}

/// Logs the comparison of a drive that came online with its declared
/// settings.
pub fn settings_checked(drive: &str, drift: &[Difference], apply: &str) {
    if drift.is_empty() {
        tracing::info!(target: "drivegate::audit", face = "internal", who = "declared-settings", drive, "the drive holds its declared settings");
    } else {
        let what = drift
            .iter()
            .map(Difference::words)
            .collect::<Vec<_>>()
            .join(", ");
        tracing::warn!(target: "drivegate::audit", face = "internal", who = "declared-settings", drive, what, apply_settings = apply, "settings drift: the drive does not hold its declared settings");
    }
}

/// Logs why a drive's settings could not be compared or applied.
pub fn settings_trouble(drive: &str, why: &str) {
    tracing::warn!(target: "drivegate::audit", face = "internal", who = "declared-settings", drive, error = why, "declared settings");
}
