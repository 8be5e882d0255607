//! The stream's fan-out: one of each bus's followers turns its events
//! (polled statuses, online/offline, port up/down) into JSON once, one
//! task does the same for the control core's lease news, and both publish
//! on one broadcast channel every WebSocket session reads.
//!
//! Serialising once per event rather than once per client keeps a hundred
//! dashboards cheap; a broadcast send never waits, so clients can never
//! slow the bus.

use std::sync::Arc;

use axum::extract::ws::Utf8Bytes;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

use super::settings_diff::{DeclaredState, SettingsDiff};
use super::stream_messages::{ServerMessage, StreamMessage};
use crate::bus::{BusEvent, BusFollower};
use crate::control::{Control, ControlEvent, Published, SessionId};
use crate::faces_shared::messages::{self, DriveMessage};
use crate::faces_shared::status::StatusView;
use crate::plant::Plant;
use crate::timestamp::rfc3339;

/// Events the hub holds for sessions that fall behind; a session's own
/// bounded buffer comes after this.
const CAPACITY: usize = 4096;

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
    /// Follows every bus of `plant` and starts one task for the
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
    pub fn publish(&self, drive: Option<usize>, message: impl Into<ServerMessage>) {
        self.publish_text(drive, None, message.into().to_text());
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
/// core settled (from any face, and the daemon's own stops), settings
/// applied and compared, freshness and alarms.
pub fn render(plant: &Plant, event: &ControlEvent) -> Option<Utf8Bytes> {
    message_of(plant, event).map(|message| message.to_text())
}

fn message_of(plant: &Plant, event: &ControlEvent) -> Option<ServerMessage> {
    let now = plant.now();
    Some(match event {
        ControlEvent::Lease(lease) => messages::of_lease(plant, lease)?.1.into(),
        ControlEvent::Freshness(news) => messages::of_freshness(plant, news)?.1.into(),
        ControlEvent::Alarm(news) => messages::of_alarm(news).1.into(),
        // Its stop follows as lease news; the alarm it raises as an alarm.
        ControlEvent::CommLoss { .. } => return None,
        ControlEvent::Drift(d) => {
            let drive = now.drive_at(d.drive)?;
            StreamMessage::SettingsDrift {
                drive: drive.name.clone(),
                bus: now.handle_of(drive)?.name().to_string(),
                unit: drive.unit,
                declared: DeclaredState::new(drive.declared.as_ref()?, Some(&d.view)),
                at: rfc3339(d.view.checked_at),
            }
            .into()
        }
        ControlEvent::Settings(applied) => {
            let drive = now.drive_at(applied.report.drive)?;
            StreamMessage::SettingsApplied {
                who: applied.who.to_string(),
                diff: SettingsDiff::of(
                    drive.name.clone(),
                    now.handle_of(drive)?.name().to_string(),
                    drive.unit,
                    &applied.report,
                ),
                at: rfc3339(applied.at),
            }
            .into()
        }
        ControlEvent::Write(w) => StreamMessage::Write {
            drive: w
                .drive
                .and_then(|i| now.drive_at(i).map(|d| d.name.clone())),
            bus: w.bus.to_string(),
            unit: w.unit,
            who: w.who.to_string(),
            what: w.what.clone(),
            ok: w.result.is_ok(),
            answer: w.result.to_string(),
            at: rfc3339(w.at),
        }
        .into(),
    })
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
                hub.publish(None, StreamMessage::Lagged { missed: n });
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

/// Forwards the events of every bus, following the plant: a bus a reload
/// adds or reopens gets its follower, one it removes or reopens loses its
/// own. Each event's drive is looked up when it comes: a bus changed in
/// place keeps its follower, with its drives as they are now (added,
/// removed, renamed).
fn follow_buses(hub: &Arc<Hub>, plant: &Arc<Plant>, shutdown: &CancellationToken) {
    let (hub, forwarded) = (hub.clone(), plant.clone());
    plant.for_each_bus(shutdown, move |bus_index, bus, stop| {
        let follower = Forward {
            hub: hub.clone(),
            plant: forwarded.clone(),
            bus_index,
        };
        bus.handle.follow(Arc::new(follower), stop);
    });
}

/// The stream as a bus's follower: each event written out once, in the
/// task every follower of the bus shares.
struct Forward {
    hub: Arc<Hub>,
    plant: Arc<Plant>,
    bus_index: usize,
}

impl Forward {
    /// The slot and the name of the drive at `unit` now (a scan reads
    /// units that are not configured: not news).
    fn drive_at(&self, unit: u8) -> Option<(usize, String)> {
        let now = self.plant.now();
        now.indexed_drives()
            .find(|(_, d)| d.bus == self.bus_index && d.unit == unit)
            .map(|(i, d)| (i, d.name.clone()))
    }

    fn message(&self, event: &BusEvent) -> Option<(Option<usize>, ServerMessage)> {
        Some(match event {
            BusEvent::Status {
                bus,
                unit,
                status,
                at,
            } => {
                // A status nobody's stream is open for is not written out.
                if self.hub.tx.receiver_count() == 0 {
                    return None;
                }
                let (i, drive) = self.drive_at(*unit)?;
                let message = StreamMessage::Status {
                    drive,
                    bus: bus.to_string(),
                    unit: *unit,
                    seen_at: rfc3339(*at),
                    status: StatusView::from(status),
                };
                (Some(i), message.into())
            }
            BusEvent::Online { bus, unit } => {
                let (i, drive) = self.drive_at(*unit)?;
                let message = DriveMessage::Online {
                    drive,
                    bus: bus.to_string(),
                    unit: *unit,
                };
                (Some(i), message.into())
            }
            BusEvent::Offline { bus, unit, reason } => {
                let (i, drive) = self.drive_at(*unit)?;
                let message = DriveMessage::Offline {
                    drive,
                    bus: bus.to_string(),
                    unit: *unit,
                    reason: reason.clone(),
                };
                (Some(i), message.into())
            }
            BusEvent::BusUp { bus } => {
                let bus = bus.to_string();
                (None, StreamMessage::BusUp { bus }.into())
            }
            BusEvent::BusDown { bus, reason } => {
                let (bus, reason) = (bus.to_string(), reason.clone());
                (None, StreamMessage::BusDown { bus, reason }.into())
            }
        })
    }
}

impl BusFollower for Forward {
    fn event(&self, event: &BusEvent) {
        if let Some((drive, message)) = self.message(event) {
            self.hub.publish(drive, message);
        }
    }

    fn lagged(&self, missed: u64) {
        // Only if the followers' task was starved of CPU: tell every client.
        tracing::warn!("the stream fell {missed} bus events behind");
        self.hub.publish(None, StreamMessage::Lagged { missed });
    }
}
