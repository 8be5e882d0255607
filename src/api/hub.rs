//! The stream's fan-out: one task per bus turns its events (polled statuses,
//! online/offline, port up/down) into JSON once, and publishes them with
//! lease events on one broadcast channel every WebSocket session reads.
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

use super::drives::StatusView;
use super::problem::{Problem, ProblemDetails};
use super::timestamp::rfc3339;
use crate::bus::BusEvent;
use crate::plant::Plant;
use crate::scope::result::ScopeState;

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
    /// A motor-safety lease ended without renewal (or its WebSocket closed)
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
        /// `[safety] on_lease_expiry`: `zero-speed`, `brake` or `none`.
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
        /// `[safety] on_lease_expiry`: `zero-speed` or `brake`.
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
        serde_json::to_string(self)
            .unwrap_or_else(|e| format!("{{\"type\":\"error\",\"detail\":\"{e}\"}}"))
            .into()
    }
}

/// One published message: the drive it concerns (`None`: every client),
/// already serialised.
#[derive(Debug, Clone)]
pub struct HubEvent {
    /// Index of the drive in the plant, `None` for bus-wide news.
    pub drive: Option<usize>,
    /// The stream session that got this message directly (the one that
    /// held the lease it is about): it skips this copy.
    pub delivered_to: Option<u64>,
    /// The JSON text.
    pub text: Utf8Bytes,
}

/// The fan-out.
pub struct Hub {
    tx: broadcast::Sender<HubEvent>,
}

impl Hub {
    /// Starts one forwarding task per bus of `plant`; they end with `shutdown`.
    pub fn start(plant: &Arc<Plant>, shutdown: &CancellationToken) -> Arc<Hub> {
        let (tx, _) = broadcast::channel(CAPACITY);
        let hub = Arc::new(Hub { tx });
        for (bus_index, bus) in plant.buses().iter().enumerate() {
            let units: HashMap<u8, usize> = plant
                .drives()
                .iter()
                .enumerate()
                .filter(|(_, d)| d.bus == bus_index)
                .map(|(i, d)| (d.unit, i))
                .collect();
            let rx = bus.handle.subscribe();
            tokio::spawn(forward(
                hub.clone(),
                plant.clone(),
                units,
                rx,
                shutdown.clone(),
            ));
        }
        hub
    }

    /// Publishes `message` about drive `drive` (or everyone's business).
    pub fn publish(&self, drive: Option<usize>, message: &ServerMessage) {
        self.publish_text(drive, None, message.to_text());
    }

    /// Publishes `text` about drive `drive`, which the stream session
    /// `delivered_to` (if any) got directly already.
    pub fn publish_text(&self, drive: Option<usize>, delivered_to: Option<u64>, text: Utf8Bytes) {
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

async fn forward(
    hub: Arc<Hub>,
    plant: Arc<Plant>,
    units: HashMap<u8, usize>,
    mut rx: broadcast::Receiver<BusEvent>,
    shutdown: CancellationToken,
) {
    let name = |i: usize| {
        plant
            .drives()
            .get(i)
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
