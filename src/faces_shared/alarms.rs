//! An alarm as JSON, as `GET /api/v1/alarms` lists it, the stream's
//! alarm messages carry it and the MQTT face's JSON format publishes it.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::control::alarms::Alarm;
use crate::control::journal::format::from_unix_ms;
use crate::timestamp::rfc3339;

/// One alarm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AlarmView {
    /// Its number (for the acknowledgement), unique for the life of the
    /// state directory.
    pub id: u64,
    /// What it is about: `fault`, `stall`, `offline`, `never-answered`
    /// (not answered once since its bus opened), `bus-down`, `comm-loss` (a Modbus TCP client's communication-loss stop),
    /// `stop-failed` (a lease's stop not confirmed), `refused-write` (a
    /// write refused by a safety rule) or `unknown-state` (a drive found
    /// moving at start while the safety journal could not say who owned it).
    pub kind: String,
    /// The bus.
    pub bus: String,
    /// The drive; `null` for a bus-wide alarm (`bus-down`, a refused
    /// broadcast).
    pub drive: Option<String>,
    /// The drive's fault code 1..7 for a `fault` (manual 1.7), else 0.
    pub code: u16,
    /// What happened, in words.
    pub text: String,
    /// What it means and what to check, from the drive's manual.
    pub help: String,
    /// When it was raised (RFC 3339, UTC).
    pub raised_at: String,
    /// True while its condition lasts (a fault, a stall, an offline drive,
    /// a drive never heard, a bus down, a stop not confirmed). An event (`comm-loss`,
    /// `refused-write`, `unknown-state`) is never active: it is over when it is raised.
    pub active: bool,
    /// When its condition ended (for an event: when it was raised);
    /// `null` while active.
    pub cleared_at: Option<String>,
    /// True once an operator acknowledged it.
    pub acknowledged: bool,
    /// Who acknowledged it (token name, or client address without tokens).
    pub acknowledged_by: Option<String>,
    /// When (RFC 3339, UTC).
    pub acknowledged_at: Option<String>,
    /// Times it happened: an event that came again before it was
    /// acknowledged counts up here instead of raising a new alarm.
    pub count: u32,
    /// When it last happened (RFC 3339, UTC).
    pub last_at: String,
}

impl From<&Alarm> for AlarmView {
    fn from(a: &Alarm) -> Self {
        let at = |ms: u64| rfc3339(from_unix_ms(ms));
        AlarmView {
            id: a.id,
            kind: a.kind.name().to_string(),
            bus: a.bus.clone(),
            drive: a.drive.clone(),
            code: a.code,
            text: a.text.clone(),
            help: a.help.clone(),
            raised_at: at(a.raised_ms),
            active: a.active(),
            cleared_at: a.cleared_ms.map(at),
            acknowledged: a.ack.is_some(),
            acknowledged_by: a.ack.as_ref().map(|k| k.by.clone()),
            acknowledged_at: a.ack.as_ref().map(|k| at(k.at_ms)),
            count: a.count,
            last_at: at(a.last_ms),
        }
    }
}
