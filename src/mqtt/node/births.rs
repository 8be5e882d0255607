//! Births and the node's death: the NBIRTH (bdSeq, `Node Control/Rebirth`,
//! version, buses) and a DBIRTH for each drive whose data is live, with
//! seq from 0; the NDEATH of the current bdSeq, the connection's will.

use prost::Message;
use rumqttc::QoS;

use super::{Connection, End, Node, now_ms};
use crate::mqtt::exception::Reported;
use crate::mqtt::metric::{self, BD_SEQ, REBIRTH, Value};
use crate::mqtt::sparkplug_b::{DataType, Payload};
use crate::mqtt::topic::Kind;

impl Node {
    /// NBIRTH and every answering drive's DBIRTH (seq from 0).
    pub(super) fn births(&mut self, c: &Connection) -> Result<(), End> {
        self.seq = 0;
        self.follow_buses();
        let now = now_ms();
        let mut node = vec![
            metric::metric(
                BD_SEQ,
                DataType::Int64,
                Value::Int(i64::from(self.bd_seq.get())),
                now,
            ),
            metric::metric(REBIRTH, DataType::Boolean, Value::Bool(false), now),
            metric::metric(
                "Properties/version",
                DataType::String,
                Value::Text(env!("CARGO_PKG_VERSION").to_string()),
                now,
            ),
        ];
        let plant = self.control.plant().now();
        for bus in plant.buses() {
            let name = bus.handle.name();
            node.push(metric::metric(
                &format!("buses/{name}/state"),
                DataType::String,
                Value::Text(self.bus_state(name)),
                now,
            ));
        }
        let payload = self.payload(node);
        c.client
            .try_publish(
                self.topics.node_topic(Kind::NBirth),
                QoS::AtMostOnce,
                false,
                payload.encode_to_vec(),
            )
            .map_err(|e| End::Error(format!("cannot queue the NBIRTH: {e}")))?;
        self.metrics.mqtt().sent(Kind::NBirth.label());
        for d in self.devices.values_mut() {
            d.born = false;
        }
        for drive in plant.drives() {
            let Some(handle) = plant.handle_of(drive) else {
                continue;
            };
            let live = handle
                .freshness(drive.unit)
                .is_some_and(|v| v.freshness.is_live());
            if live && let Some(status) = handle.drive(drive.unit).and_then(|s| s.status) {
                self.device_birth(c, &drive.name, Some(&status));
            }
        }
        self.born = true;
        self.metrics.mqtt().born(true);
        tracing::info!(
            bd_seq = self.bd_seq.get(),
            devices = self.devices.values().filter(|d| d.born).count(),
            "MQTT: births published"
        );
        Ok(())
    }

    /// `name`'s DBIRTH with `status` (nulls without one): what is
    /// reported of it starts over from these values.
    pub(super) fn device_birth(
        &mut self,
        c: &Connection,
        name: &str,
        status: Option<&crate::drive::Status>,
    ) {
        let now = now_ms();
        let device = self.devices.entry(name.to_string()).or_default();
        device.reported = Reported::born(status);
        device.born = true;
        let metrics = metric::birth_metrics(status, &device.setpoints, &device.last_result, now);
        let payload = self.payload(metrics);
        let topic = self.topics.device_topic(Kind::DBirth, name);
        if self.publish(c, topic, payload, Kind::DBirth).is_err()
            && let Some(d) = self.devices.get_mut(name)
        {
            // Born at its next status.
            d.born = false;
        }
    }

    /// The NDEATH of the current bdSeq (no seq: Sparkplug 3.0).
    pub(super) fn ndeath(&self) -> Vec<u8> {
        Payload {
            timestamp: Some(now_ms()),
            metrics: vec![metric::metric(
                BD_SEQ,
                DataType::Int64,
                Value::Int(i64::from(self.bd_seq.get())),
                now_ms(),
            )],
            ..Default::default()
        }
        .encode_to_vec()
    }
}
