//! The JSON messages about one drive that a face sends beside its
//! replies: the drive answering again or not, the news of the
//! motor-safety lease on it and its alarms, how fresh its data is, in the shape the WebSocket stream gives them
//! (`{"type": "online", ...}`, `{"type": "lease-expired", ...}`), and the
//! reply to a command message. The MQTT face publishes them on a drive's
//! `event` and `reply` topics; the stream sends them as they are, beside
//! messages of its own (`api::stream_messages`).

use serde::Serialize;
use serde_json::Value;
use utoipa::ToSchema;

use super::alarms::AlarmView;
use super::problem::{Problem, ProblemDetails};
use super::status::FreshnessView;
use crate::control::LeaseEvent;
use crate::control::alarms::AlarmNews;
use crate::control::freshness::FreshnessNews;
use crate::plant::Plant;

/// A message about one drive. Its texts are those of the stream's
/// document (`ServerMessage`, of which these are a part).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum DriveMessage {
    /// A drive answers (again).
    Online {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
    },
    /// A drive stopped answering its polls.
    Offline {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// The last failure.
        reason: String,
    },
    /// A drive's data changed freshness: `live` again, or not live
    /// (`stale`: polls missing; `offline`: it stopped answering; `never`:
    /// not answered since its bus opened; `bus-down`: its bus's port is
    /// gone), with why and since when. Values received before are the
    /// drive's current ones only while it is `live`.
    Freshness {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// The new freshness, why and since when.
        #[serde(flatten)]
        freshness: FreshnessView,
        /// Age of its last value, ms (`null`: it never answered).
        age_ms: Option<u64>,
    },
    /// A motor-safety lease ended without renewal (or its WebSocket
    /// closed; or, for a Modbus TCP client's communication-loss lease, no
    /// request came within the time or its connection closed) and the
    /// stop action was tried.
    LeaseExpired {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// Who held the lease.
        owner: String,
        /// Why it ended.
        reason: String,
        /// `[safety] on_lease_expiry` (or the client network's
        /// `comm_loss_action`): `zero-speed`, `brake` or `none`.
        action: String,
        /// What was sent to the drive, if anything.
        sent: Option<String>,
        /// True when the action was carried out (or nothing was needed).
        ok: bool,
        /// The drive's answer, or why the action failed.
        result: String,
        /// True when the action failed and drivegate keeps trying it until
        /// the drive confirms it; a `lease-stop` message tells the end.
        retrying: bool,
    },
    /// How the stop of a lease that failed at first ended: carried out at
    /// last, or not tried again because something newer took over the
    /// drive (a confirmed setpoint, brake or deactivation).
    LeaseStop {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// Who held the lease.
        owner: String,
        /// `[safety] on_lease_expiry` (or the client network's
        /// `comm_loss_action`): `zero-speed` or `brake`.
        action: String,
        /// What was sent to the drive at last, if anything.
        sent: Option<String>,
        /// True when the drive confirmed the stop (or nothing was needed).
        stopped: bool,
        /// Tries made.
        attempts: u32,
        /// The drive's answer, or what took over.
        result: String,
    },
    /// A motor-safety lease ended without a stop: released, replaced by a
    /// newer lease, or ended by a write that stops the motor itself (a
    /// brake or a deactivation, from any face), so no stop follows.
    LeaseEnded {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// Who held the lease.
        owner: String,
        /// Why it ended.
        reason: String,
    },
    /// An alarm was raised (a fault, a stall, a drive offline, a bus down,
    /// a stop not confirmed, a communication-loss stop, a write refused by
    /// a safety rule), or an event came again before it was acknowledged
    /// (same `id`, `count` up). Sent to every client.
    AlarmRaised {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// An alarm's condition ended. Sent to every client.
    AlarmCleared {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// An operator acknowledged an alarm. Sent to every client.
    AlarmAcknowledged {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// The answer to a command sent on the stream, with its `id`.
    Reply {
        /// The command's `id`, echoed.
        id: Value,
        /// True on success (`result`), false on failure (`problem`).
        ok: bool,
        /// The same body the REST route returns.
        #[serde(skip_serializing_if = "Option::is_none")]
        result: Option<Value>,
        /// The same problem the REST route returns.
        #[serde(skip_serializing_if = "Option::is_none")]
        #[schema(value_type = Option<ProblemDetails>)]
        problem: Option<Problem>,
    },
}

impl DriveMessage {
    /// The reply to command `id`: its result or its problem.
    pub fn reply(id: Value, result: Result<Value, Problem>) -> Self {
        match result {
            Ok(result) => DriveMessage::Reply {
                id,
                ok: true,
                result: Some(result),
                problem: None,
            },
            Err(problem) => DriveMessage::Reply {
                id,
                ok: false,
                result: None,
                problem: Some(problem),
            },
        }
    }

    /// The message as JSON text.
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).unwrap_or_else(|e| {
            serde_json::json!({"type": "error", "detail": e.to_string()}).to_string()
        })
    }
}

/// Lease news as a message about its drive: the drive's name and the
/// message, if the drive is still configured.
pub(crate) fn of_lease(plant: &Plant, lease: &LeaseEvent) -> Option<(String, DriveMessage)> {
    let now = plant.now();
    let drive = now.drive_at(lease.drive())?;
    let (name, bus, unit) = (
        drive.name.clone(),
        now.handle_of(drive)?.name().to_string(),
        drive.unit,
    );
    let message = match lease.clone() {
        LeaseEvent::Ended { owner, reason, .. } => DriveMessage::LeaseEnded {
            drive: name.clone(),
            bus,
            unit,
            owner: owner.to_string(),
            reason,
        },
        LeaseEvent::Expired {
            owner,
            reason,
            action,
            sent,
            ok,
            result,
            retrying,
            ..
        } => DriveMessage::LeaseExpired {
            drive: name.clone(),
            bus,
            unit,
            owner: owner.to_string(),
            reason,
            action: action.name().to_string(),
            sent,
            ok,
            result,
            retrying,
        },
        LeaseEvent::StopSettled {
            owner,
            action,
            sent,
            stopped,
            attempts,
            result,
            ..
        } => DriveMessage::LeaseStop {
            drive: name.clone(),
            bus,
            unit,
            owner: owner.to_string(),
            action: action.name().to_string(),
            sent,
            stopped,
            attempts,
            result,
        },
    };
    Some((name, message))
}

/// Freshness news as a message about its drive: the drive's name and the
/// message, if the drive is still configured.
pub(crate) fn of_freshness(plant: &Plant, news: &FreshnessNews) -> Option<(String, DriveMessage)> {
    let now = plant.now();
    let drive = now.drive_at(news.drive)?;
    let handle = now.handle_of(drive)?;
    let message = DriveMessage::Freshness {
        drive: drive.name.clone(),
        bus: news.bus.to_string(),
        unit: news.unit,
        freshness: FreshnessView::of(&news.verdict, &news.bus, news.unit, handle.line().baud()),
        age_ms: news
            .verdict
            .age
            .map(|a| u64::try_from(a.as_millis()).unwrap_or(u64::MAX)),
    };
    Some((drive.name.clone(), message))
}

/// Alarm news as a message: the drive it concerns (`None`: bus-wide) and
/// the message.
pub(crate) fn of_alarm(news: &AlarmNews) -> (Option<String>, DriveMessage) {
    let alarm = AlarmView::from(news.alarm());
    let drive = alarm.drive.clone();
    let message = match news {
        AlarmNews::Raised(_) => DriveMessage::AlarmRaised { alarm },
        AlarmNews::Cleared(_) => DriveMessage::AlarmCleared { alarm },
        AlarmNews::Acknowledged(_) => DriveMessage::AlarmAcknowledged { alarm },
    };
    (drive, message)
}
