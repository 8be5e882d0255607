//! Data: each status of a born drive as a DDATA of the fields that moved
//! past their deadbands, a bus's state as an NDATA, the periodic full
//! publish, and the outbox's replay; each payload with the next seq,
//! and what the client cannot take kept in the outbox.

use prost::Message;

use super::{Connection, DATA_QOS, Node, REPLAY_BATCH, ms_of, now_ms};
use crate::bus::cache::BusEvent;
use crate::mqtt::metric::{self, Value};
use crate::mqtt::replay;
use crate::mqtt::sparkplug_b::payload::Metric;
use crate::mqtt::sparkplug_b::{DataType, Payload};
use crate::mqtt::topic::Kind;

impl Node {
    /// A bus's event: a status into DDATA (or, for a drive not born yet
    /// whose data is live, its DBIRTH), the port's state into NDATA.
    pub(super) fn on_bus(&mut self, c: Option<&Connection>, event: BusEvent) {
        match event {
            BusEvent::Status {
                bus,
                unit,
                status,
                at,
            } => {
                let Some(name) = self.drive_at(&bus, unit) else {
                    return;
                };
                let ts = ms_of(at);
                let device = self.devices.entry(name.clone()).or_default();
                if self.born && !device.born {
                    // Born only while its data is live: a status queued
                    // here before its bus went down is no birth.
                    if let Some(c) = c
                        && self.is_live(&bus, unit)
                    {
                        self.device_birth(c, &name, Some(&status));
                    }
                    return;
                }
                let changes = device
                    .reported
                    .changes(&status, &self.config.deadbands, false);
                let metrics: Vec<Metric> = changes
                    .into_iter()
                    .map(|(f, v)| metric::status_metric(f, v, ts))
                    .collect();
                self.device_data(c, &name, metrics);
            }
            BusEvent::BusUp { bus } | BusEvent::BusDown { bus, .. } => {
                if let Some(c) = c
                    && self.born
                {
                    let state = self.bus_state(&bus);
                    let now = now_ms();
                    let payload = self.payload(vec![metric::metric(
                        &format!("buses/{bus}/state"),
                        DataType::String,
                        Value::Text(state),
                        now,
                    )]);
                    let topic = self.topics.node_topic(Kind::NData);
                    let _ = self.publish(c, topic, payload, Kind::NData);
                }
            }
            // Deaths and births follow the core's freshness news.
            BusEvent::Online { .. } | BusEvent::Offline { .. } => {}
        }
    }

    /// Publishes `metrics` of `device` as a DDATA when its birth is out,
    /// else keeps them in the outbox.
    pub(super) fn device_data(
        &mut self,
        c: Option<&Connection>,
        device: &str,
        metrics: Vec<Metric>,
    ) {
        if metrics.is_empty() {
            return;
        }
        let born = self.devices.get(device).is_some_and(|d| d.born);
        match c {
            Some(c) if self.born && born => {
                let payload = self.payload(metrics);
                let topic = self.topics.device_topic(Kind::DData, device);
                if let Err(metrics) = self.publish(c, topic, payload, Kind::DData) {
                    self.outbox.keep(device, metrics);
                }
            }
            _ => self.outbox.keep(device, metrics),
        }
    }

    /// Every field of every born drive, whatever its deadband.
    pub(super) fn full_publish(&mut self, c: &Connection) {
        let plant = self.control.plant().now();
        for drive in plant.drives() {
            let Some(status) = plant
                .handle_of(drive)
                .and_then(|h| h.drive(drive.unit))
                .and_then(|s| s.status)
            else {
                continue;
            };
            let Some(device) = self.devices.get_mut(&drive.name) else {
                continue;
            };
            if !device.born {
                continue;
            }
            let now = now_ms();
            let metrics = device
                .reported
                .changes(&status, &self.config.deadbands, true)
                .into_iter()
                .map(|(f, v)| metric::status_metric(f, v, now))
                .collect();
            let payload = self.payload(metrics);
            let topic = self.topics.device_topic(Kind::DData, &drive.name);
            let _ = self.publish(c, topic, payload, Kind::DData);
        }
    }

    /// Replays what the outbox kept, marked historical, [`REPLAY_BATCH`]
    /// messages per [`REPLAY_EVERY`], so live data keeps its pace. A
    /// drive's data goes only after its DBIRTH (it waits in `held` until
    /// then); a drive no longer configured has its data dropped, counted.
    pub(super) fn replay(&mut self, c: &Connection) {
        let mut sent = 0;
        while sent < REPLAY_BATCH {
            let plant = self.control.plant().now();
            let devices = &self.devices;
            let state = |name: &str| {
                if !plant.drives().any(|d| d.name == name) {
                    replay::Device::Gone
                } else if devices.get(name).is_some_and(|d| d.born) {
                    replay::Device::Born
                } else {
                    replay::Device::Unborn
                }
            };
            let (device, mut metrics) = match self.held.next_born(state) {
                Some(next) => next,
                None => {
                    if self.held.full() {
                        return;
                    }
                    let Some((device, metrics)) = self.outbox.next() else {
                        return;
                    };
                    let now = state(&device);
                    match self.held.offer(device, metrics, now) {
                        replay::Verdict::Send(device, metrics) => (device, metrics),
                        replay::Verdict::Held => {
                            if self.held.full() {
                                tracing::warn!(
                                    held = self.held.len(),
                                    "MQTT store: the replay waits for drives not born yet; the rest of the store stays on disk meanwhile"
                                );
                            }
                            continue;
                        }
                        replay::Verdict::Dropped => {
                            self.metrics.mqtt().replay_dropped(1);
                            continue;
                        }
                    }
                }
            };
            sent += 1;
            for m in &mut metrics {
                m.is_historical = Some(true);
            }
            let payload = self.payload(metrics);
            let topic = self.topics.device_topic(Kind::DData, &device);
            if let Err(metrics) = self.publish(c, topic, payload, Kind::DData) {
                // Back in later; the client's queue is full now.
                self.outbox.keep(&device, metrics);
                return;
            }
        }
    }

    /// A payload with the next seq.
    pub(super) fn payload(&mut self, metrics: Vec<Metric>) -> Payload {
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        Payload {
            timestamp: Some(now_ms()),
            metrics,
            seq: Some(u64::from(seq)),
            ..Default::default()
        }
    }

    /// Hands `payload` (just made, with the last seq) to the client; when
    /// its queue is full it is not sent, its seq is given back, and its
    /// metrics come back for the outbox.
    pub(super) fn publish(
        &mut self,
        c: &Connection,
        topic: String,
        payload: Payload,
        kind: Kind,
    ) -> Result<(), Vec<Metric>> {
        match c
            .client
            .try_publish(topic, DATA_QOS, false, payload.encode_to_vec())
        {
            Ok(()) => {
                self.metrics.mqtt().sent(kind.label());
                Ok(())
            }
            Err(e) => {
                tracing::warn!("MQTT: a {} was not sent: {e}", kind.level());
                self.seq = self.seq.wrapping_sub(1);
                Err(payload.metrics)
            }
        }
    }
}
