//! The stream's fan-out: one task per bus turns its events (polled statuses,
//! online/offline, port up/down) into JSON once, one task does the same for
//! the control core's lease news, and both publish on one broadcast channel
//! every WebSocket session reads.
//!
//! Serialising once per event rather than once per client keeps a hundred
//! dashboards cheap; a broadcast send never waits, so clients can never
//! slow the bus.

use std::collections::HashMap;
use std::sync::Arc;

use axum::extract::ws::Utf8Bytes;
use serde::Serialize;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;
use utoipa::ToSchema;

use super::alarms::AlarmView;
use super::document::{DeclaredState, SettingsDiff};
use super::drives::{FreshnessView, StatusView};
use super::problem::{Problem, ProblemDetails};
use crate::bus::BusEvent;
use crate::control::{Control, ControlEvent, Published, SessionId};
use crate::ops::messages::DriveMessage;
use crate::plant::Plant;
use crate::scope::result::ScopeState;
use crate::timestamp::rfc3339;

/// Events the hub holds for sessions that fall behind; a session's own
/// bounded buffer comes after this.
const CAPACITY: usize = 4096;

/// A message the server sends on the stream.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum ServerMessage {
    /// A drive's status was read (by its poll, or on request).
    Status {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// When it was read (RFC 3339, UTC).
        seen_at: String,
        /// The decoded status (same fields as the REST status).
        status: StatusView,
    },
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
    /// A bus's serial port opened.
    BusUp {
        /// Bus name.
        bus: String,
    },
    /// A bus's serial port failed; drivegate reopens it.
    BusDown {
        /// Bus name.
        bus: String,
        /// Why.
        reason: String,
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
    /// A write to a drive, from any client or face (REST, stream, Modbus
    /// TCP) or from drivegate itself (a lease's stop, the shutdown stop),
    /// once the drive answered or the write failed: the audit log's line.
    Write {
        /// Drive name; `null` for a broadcast (unit 0) or a unit that is
        /// not configured.
        drive: Option<String>,
        /// Its bus.
        bus: String,
        /// The unit written to (0: broadcast).
        unit: u8,
        /// Who sent it: a token name, a client address, or
        /// `lease-expiry (<owner>)`, `shutdown`.
        who: String,
        /// What was written, in words, with the registers and raw values.
        what: String,
        /// True when the drive confirmed it.
        ok: bool,
        /// The drive's answer, or why the write failed.
        answer: String,
        /// When (RFC 3339, UTC).
        at: String,
    },
    /// A drive with declared settings (`[bus.drive.settings]`) was
    /// compared with them: when it came online (start, a power cycle, a
    /// replaced drive), after a settings document was put on it, or while
    /// drivegate applies them (`on-drift`).
    SettingsDrift {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// The declaration's state, as in the drive's `declared_settings`
        /// (`drift`: true when it does not hold them).
        #[serde(flatten)]
        declared: DeclaredState,
        /// When (RFC 3339, UTC).
        at: String,
    },
    /// A settings document was put on a drive (from any face, or by
    /// drivegate for a declaration): what each setting was and is. Its
    /// writes come as `write` messages too.
    SettingsApplied {
        /// Who sent it (`declared-settings`: drivegate itself).
        who: String,
        /// The diff, as `PUT .../settings` answers it.
        #[serde(flatten)]
        diff: SettingsDiff,
        /// When (RFC 3339, UTC).
        at: String,
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
    /// A scope capture was armed, triggered, ended, or filled some more
    /// (every 100 ms while it runs): its state, as `GET
    /// /api/v1/buses/{bus}/scope` shows it. Sent to every client
    /// subscribed to at least one drive.
    Scope(ScopeState),
    /// This client fell behind: `missed` updates were skipped for it.
    Lagged {
        /// Messages skipped.
        missed: u64,
    },
    /// The drives this client now receives.
    Subscribed {
        /// Drive names.
        drives: Vec<String>,
        /// What the daemon did to these drives when it started, from the
        /// safety journal the last process left (a lease kept, a stop owed
        /// by a lease whose holder is gone or whose time ran out, a brake
        /// that holds); absent when it owed nothing.
        #[serde(skip_serializing_if = "Vec::is_empty")]
        restart: Vec<RestartDecision>,
    },
    /// The answer to a command sent on the stream, with its `id`.
    Reply {
        /// The command's `id`, echoed.
        id: serde_json::Value,
        /// True on success (`result`), false on failure (`problem`).
        ok: bool,
        /// The same body the REST route returns.
        #[serde(skip_serializing_if = "Option::is_none")]
        result: Option<serde_json::Value>,
        /// The same problem the REST route returns.
        #[serde(skip_serializing_if = "Option::is_none")]
        #[schema(value_type = Option<ProblemDetails>)]
        problem: Option<Problem>,
    },
    /// A message from the client could not be understood.
    Error {
        /// What was wrong.
        #[schema(value_type = ProblemDetails)]
        problem: Problem,
    },
}

impl ServerMessage {
    /// The message as a WebSocket text payload.
    pub fn to_text(&self) -> Utf8Bytes {
        json_text(self)
    }
}

/// `value` as JSON text; if it cannot be serialised (never expected: every
/// field serialises), an `error` message whose text is escaped like any
/// other string, so the client still gets valid JSON.
fn json_text<T: Serialize>(value: &T) -> Utf8Bytes {
    serde_json::to_string(value)
        .unwrap_or_else(|e| {
            serde_json::json!({"type": "error", "detail": e.to_string()}).to_string()
        })
        .into()
}

/// A decision of the start-up replay of the safety journal, in words.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct RestartDecision {
    /// Drive name.
    pub drive: String,
    /// `stop-holder-gone`, `stop-ran-out`, `stop-unfinished`, `brake-again`,
    /// `stop-unknown-state`, `lease-kept`, `brake-holds` or `not-configured`.
    pub decision: String,
    /// Who held the lease concerned, if anyone.
    pub who: Option<String>,
    /// What was done and why.
    pub text: String,
    /// When (RFC 3339, UTC).
    pub at: String,
}

/// One published message: the drive it concerns (`None`: every client),
/// already serialised.
#[derive(Debug, Clone)]
pub struct HubEvent {
    /// Index of the drive in the plant, `None` for bus-wide news.
    pub drive: Option<usize>,
    /// The stream session that got this message directly (the one that
    /// held the lease it is about): it skips this copy.
    pub delivered_to: Option<SessionId>,
    /// The JSON text.
    pub text: Utf8Bytes,
}

/// The fan-out.
pub struct Hub {
    tx: broadcast::Sender<HubEvent>,
}

impl Hub {
    /// Starts one forwarding task per bus of `plant` and one for the
    /// control core's news; they end with `shutdown`.
    pub fn start(plant: &Arc<Plant>, control: &Control, shutdown: &CancellationToken) -> Arc<Hub> {
        let (tx, _) = broadcast::channel(CAPACITY);
        let hub = Arc::new(Hub { tx });
        tokio::spawn(forward_control(
            hub.clone(),
            plant.clone(),
            control.subscribe(),
            shutdown.clone(),
        ));
        follow_buses(&hub, plant, shutdown);
        hub
    }

    /// Publishes `message` about drive `drive` (or everyone's business).
    pub fn publish(&self, drive: Option<usize>, message: &ServerMessage) {
        self.publish_text(drive, None, message.to_text());
    }

    /// Publishes `text` about drive `drive`, which the stream session
    /// `delivered_to` (if any) got directly already.
    pub fn publish_text(
        &self,
        drive: Option<usize>,
        delivered_to: Option<SessionId>,
        text: Utf8Bytes,
    ) {
        // No session listening is not an error.
        let _ = self.tx.send(HubEvent {
            drive,
            delivered_to,
            text,
        });
    }

    /// A receiver of every future message.
    pub fn subscribe(&self) -> broadcast::Receiver<HubEvent> {
        self.tx.subscribe()
    }
}

/// A control event as a stream message: lease news, every write the
/// core settled (from any face, and the daemon's own stops), and alarms.
pub fn render(plant: &Plant, event: &ControlEvent) -> Option<Utf8Bytes> {
    let lease = match event {
        ControlEvent::Lease(lease) => lease,
        ControlEvent::Drift(d) => {
            let now = plant.now();
            let drive = now.drive_at(d.drive)?;
            let declared = drive.declared.as_ref()?;
            let message = ServerMessage::SettingsDrift {
                drive: drive.name.clone(),
                bus: now.handle_of(drive)?.name().to_string(),
                unit: drive.unit,
                declared: DeclaredState::new(declared, Some(&d.view)),
                at: rfc3339(d.view.checked_at),
            };
            return Some(message.to_text());
        }
        ControlEvent::Settings(applied) => {
            let now = plant.now();
            let drive = now.drive_at(applied.report.drive)?;
            let message = ServerMessage::SettingsApplied {
                who: applied.who.to_string(),
                diff: SettingsDiff::of(
                    drive.name.clone(),
                    now.handle_of(drive)?.name().to_string(),
                    drive.unit,
                    &applied.report,
                ),
                at: rfc3339(applied.at),
            };
            return Some(message.to_text());
        }
        // Its stop follows as lease news; the alarm it raises as an alarm.
        ControlEvent::CommLoss { .. } => return None,
        ControlEvent::Freshness(news) => {
            let (_, message) = crate::ops::messages::of_freshness(plant, news)?;
            return Some(ServerMessage::from(message).to_text());
        }
        ControlEvent::Alarm(news) => {
            let (_, message) = crate::ops::messages::of_alarm(news);
            return Some(ServerMessage::from(message).to_text());
        }
        ControlEvent::Write(w) => {
            let message = ServerMessage::Write {
                drive: w
                    .drive
                    .and_then(|i| plant.now().drive_at(i).map(|d| d.name.clone())),
                bus: w.bus.to_string(),
                unit: w.unit,
                who: w.who.to_string(),
                what: w.what.clone(),
                ok: w.result.is_ok(),
                answer: w.result.to_string(),
                at: rfc3339(w.at),
            };
            return Some(message.to_text());
        }
    };
    let (_, message) = crate::ops::messages::of_lease(plant, lease)?;
    Some(ServerMessage::from(message).to_text())
}

impl From<DriveMessage> for ServerMessage {
    /// The stream's message of the same type and fields.
    fn from(m: DriveMessage) -> Self {
        match m {
            DriveMessage::Online { drive, bus, unit } => ServerMessage::Online { drive, bus, unit },
            DriveMessage::Offline {
                drive,
                bus,
                unit,
                reason,
            } => ServerMessage::Offline {
                drive,
                bus,
                unit,
                reason,
            },
            DriveMessage::Freshness {
                drive,
                bus,
                unit,
                freshness,
                age_ms,
            } => ServerMessage::Freshness {
                drive,
                bus,
                unit,
                freshness,
                age_ms,
            },
            DriveMessage::LeaseExpired {
                drive,
                bus,
                unit,
                owner,
                reason,
                action,
                sent,
                ok,
                result,
                retrying,
            } => ServerMessage::LeaseExpired {
                drive,
                bus,
                unit,
                owner,
                reason,
                action,
                sent,
                ok,
                result,
                retrying,
            },
            DriveMessage::LeaseStop {
                drive,
                bus,
                unit,
                owner,
                action,
                sent,
                stopped,
                attempts,
                result,
            } => ServerMessage::LeaseStop {
                drive,
                bus,
                unit,
                owner,
                action,
                sent,
                stopped,
                attempts,
                result,
            },
            DriveMessage::LeaseEnded {
                drive,
                bus,
                unit,
                owner,
                reason,
            } => ServerMessage::LeaseEnded {
                drive,
                bus,
                unit,
                owner,
                reason,
            },
            DriveMessage::AlarmRaised { alarm } => ServerMessage::AlarmRaised { alarm },
            DriveMessage::AlarmCleared { alarm } => ServerMessage::AlarmCleared { alarm },
            DriveMessage::AlarmAcknowledged { alarm } => ServerMessage::AlarmAcknowledged { alarm },
            DriveMessage::Reply {
                id,
                ok,
                result,
                problem,
            } => ServerMessage::Reply {
                id,
                ok,
                result,
                problem,
            },
        }
    }
}

/// Publishes the control core's lease news.
async fn forward_control(
    hub: Arc<Hub>,
    plant: Arc<Plant>,
    mut rx: broadcast::Receiver<Published>,
    shutdown: CancellationToken,
) {
    loop {
        let published = tokio::select! {
            () = shutdown.cancelled() => return,
            published = rx.recv() => published,
        };
        match published {
            Ok(p) => {
                if let Some(text) = render(&plant, &p.event) {
                    hub.publish_text(p.event.drive(), p.delivered_to, text);
                }
            }
            Err(broadcast::error::RecvError::Lagged(n)) => {
                tracing::warn!("the stream fell {n} control events behind");
                hub.publish(None, &ServerMessage::Lagged { missed: n });
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

/// Forwards the events of every bus, following the plant: a bus a reload
/// adds or reopens gets its forwarder (with the units of its drives), one
/// it removes or reopens loses its own.
fn follow_buses(hub: &Arc<Hub>, plant: &Arc<Plant>, shutdown: &CancellationToken) {
    let (hub, forwarded) = (hub.clone(), plant.clone());
    plant.for_each_bus(shutdown, move |bus_index, bus, stop| {
        let units: HashMap<u8, usize> = forwarded
            .now()
            .indexed_drives()
            .filter(|(_, d)| d.bus == bus_index)
            .map(|(i, d)| (d.unit, i))
            .collect();
        tokio::spawn(forward(
            hub.clone(),
            forwarded.clone(),
            units,
            bus.handle.subscribe(),
            stop,
        ));
    });
}

async fn forward(
    hub: Arc<Hub>,
    plant: Arc<Plant>,
    units: HashMap<u8, usize>,
    mut rx: broadcast::Receiver<BusEvent>,
    shutdown: CancellationToken,
) {
    let name = |i: usize| {
        plant
            .now()
            .drive_at(i)
            .map_or_else(String::new, |d| d.name.clone())
    };
    loop {
        let event = tokio::select! {
            () = shutdown.cancelled() => return,
            event = rx.recv() => event,
        };
        let (drive, message) = match event {
            Ok(BusEvent::Status {
                bus,
                unit,
                status,
                at,
            }) => {
                // A scan reads units that are not configured: not news.
                let Some(&i) = units.get(&unit) else { continue };
                (
                    Some(i),
                    ServerMessage::Status {
                        drive: name(i),
                        bus: bus.to_string(),
                        unit,
                        seen_at: rfc3339(at),
                        status: StatusView::from(&status),
                    },
                )
            }
            Ok(BusEvent::Online { bus, unit }) => {
                let Some(&i) = units.get(&unit) else { continue };
                (
                    Some(i),
                    ServerMessage::Online {
                        drive: name(i),
                        bus: bus.to_string(),
                        unit,
                    },
                )
            }
            Ok(BusEvent::Offline { bus, unit, reason }) => {
                let Some(&i) = units.get(&unit) else { continue };
                (
                    Some(i),
                    ServerMessage::Offline {
                        drive: name(i),
                        bus: bus.to_string(),
                        unit,
                        reason,
                    },
                )
            }
            Ok(BusEvent::BusUp { bus }) => (
                None,
                ServerMessage::BusUp {
                    bus: bus.to_string(),
                },
            ),
            Ok(BusEvent::BusDown { bus, reason }) => (
                None,
                ServerMessage::BusDown {
                    bus: bus.to_string(),
                    reason,
                },
            ),
            Err(broadcast::error::RecvError::Lagged(n)) => {
                // Only if this task was starved of CPU: tell every client.
                tracing::warn!("the stream fell {n} bus events behind");
                (None, ServerMessage::Lagged { missed: n })
            }
            Err(broadcast::error::RecvError::Closed) => return,
        };
        hub.publish(drive, &message);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_drive_message_reads_as_the_streams_message_of_its_type() {
        let (drive, bus) = ("conveyor".to_string(), "sim".to_string());
        let messages = [
            DriveMessage::Online {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
            },
            DriveMessage::Offline {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
                reason: "timeout".into(),
            },
            DriveMessage::LeaseExpired {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
                owner: "mqtt scada".into(),
                reason: "communication was lost".into(),
                action: "zero-speed".into(),
                sent: Some("speed 0 rpm".into()),
                ok: true,
                result: "confirmed".into(),
                retrying: false,
            },
            DriveMessage::LeaseStop {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
                owner: "mqtt scada".into(),
                action: "brake".into(),
                sent: None,
                stopped: true,
                attempts: 2,
                result: "confirmed".into(),
            },
            DriveMessage::LeaseEnded {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
                owner: "op".into(),
                reason: "released".into(),
            },
            DriveMessage::Freshness {
                drive: drive.clone(),
                bus: bus.clone(),
                unit: 1,
                freshness: FreshnessView {
                    freshness: crate::ops::status::FreshnessName::BusDown,
                    freshness_since: Some("2026-01-01T00:00:00.000Z".into()),
                    freshness_reason: Some("bus sim is down: gone".into()),
                },
                age_ms: Some(1200),
            },
            DriveMessage::reply(serde_json::json!(7), Ok(serde_json::json!({"a": 1}))),
            DriveMessage::reply(
                serde_json::json!("x"),
                Err(Problem::invalid("no such thing")),
            ),
        ];
        for m in messages {
            let stream = ServerMessage::from(m.clone());
            assert_eq!(
                serde_json::to_value(&m).unwrap(),
                serde_json::to_value(&stream).unwrap()
            );
        }
    }

    /// A value whose serialisation fails with quotes in the message.
    struct Unserialisable;

    impl Serialize for Unserialisable {
        fn serialize<S: serde::Serializer>(&self, _: S) -> Result<S::Ok, S::Error> {
            Err(serde::ser::Error::custom("field \"x\" is \\ broken"))
        }
    }

    #[test]
    fn a_message_that_cannot_be_serialised_is_still_valid_json() {
        let text = json_text(&Unserialisable);
        let v: serde_json::Value = serde_json::from_str(text.as_str()).expect("valid JSON");
        assert_eq!(v["type"], "error");
        assert_eq!(v["detail"], "field \"x\" is \\ broken");
    }
}
