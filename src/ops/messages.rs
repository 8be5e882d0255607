//! The JSON messages about one drive that a face sends beside its
//! replies: the drive answering again or not, the news of the
//! motor-safety lease on it and its alarms, how fresh its data is, in the shape the WebSocket stream gives them
//! (`{"type": "online", ...}`, `{"type": "lease-expired", ...}`), and the
//! reply to a command message. The MQTT face publishes them on a drive's
//! `event` and `reply` topics; the stream's own `ServerMessage` carries
//! the same fields (a test in `api::hub` holds them equal).

use serde::Serialize;
use serde_json::Value;

use super::alarms::AlarmView;
use super::problem::Problem;
use super::status::FreshnessView;
use crate::control::LeaseEvent;
use crate::control::alarms::AlarmNews;
use crate::control::freshness::FreshnessNews;
use crate::plant::Plant;

/// A message about one drive.
#[derive(Debug, Clone, PartialEq, Serialize)]
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
    /// The drive's data changed freshness: `live` again, or not live
    /// (`stale`, `offline`, `never`, `bus-down`) with why and since when.
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
    /// A motor-safety lease ended without renewal (or its session ended)
    /// and the stop action was tried.
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
        /// `zero-speed`, `brake` or `none`.
        action: String,
        /// What was sent to the drive, if anything.
        sent: Option<String>,
        /// True when the action was carried out (or nothing was needed).
        ok: bool,
        /// The drive's answer, or why the action failed.
        result: String,
        /// True when the action failed and is tried again until the drive
        /// confirms it; a `lease-stop` message tells the end.
        retrying: bool,
    },
    /// How the stop of a lease that failed at first ended.
    LeaseStop {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// Who held the lease.
        owner: String,
        /// `zero-speed` or `brake`.
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
    /// A motor-safety lease ended without a stop (released, replaced, or
    /// ended by a brake or a deactivation).
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
    /// An alarm was raised (or an event came again: same `id`, `count`
    /// up).
    AlarmRaised {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// An alarm's condition ended.
    AlarmCleared {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// An operator acknowledged an alarm.
    AlarmAcknowledged {
        /// The alarm, as `GET /api/v1/alarms` shows it.
        alarm: AlarmView,
    },
    /// The answer to a command message.
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
pub fn of_lease(plant: &Plant, lease: &LeaseEvent) -> Option<(String, DriveMessage)> {
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
pub fn of_freshness(plant: &Plant, news: &FreshnessNews) -> Option<(String, DriveMessage)> {
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
pub fn of_alarm(news: &AlarmNews) -> (Option<String>, DriveMessage) {
    let alarm = AlarmView::from(news.alarm());
    let drive = alarm.drive.clone();
    let message = match news {
        AlarmNews::Raised(_) => DriveMessage::AlarmRaised { alarm },
        AlarmNews::Cleared(_) => DriveMessage::AlarmCleared { alarm },
        AlarmNews::Acknowledged(_) => DriveMessage::AlarmAcknowledged { alarm },
    };
    (drive, message)
}
