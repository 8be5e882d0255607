//! What the broker sends the node: its acceptance of the connection (then
//! the subscriptions and, without a primary host, the births), the primary
//! host's `STATE`, an NCMD asking for a rebirth, and DCMDs.

use prost::Message;
use rumqttc::{Event, Packet, QoS};

use super::{Connection, End, Node, open_session};
use crate::mqtt::host::{HostChange, HostState};
use crate::mqtt::metric::{self, REBIRTH};
use crate::mqtt::sparkplug_b::Payload;
use crate::mqtt::topic::{Incoming, Kind, state_topic};

impl Node {
    /// An event of the connection; an error, or the primary host gone,
    /// ends it.
    pub(super) fn on_event(&mut self, c: &mut Connection, event: Event) -> Result<(), End> {
        match event {
            Event::Incoming(Packet::ConnAck(ack)) => {
                if ack.code != rumqttc::ConnectReturnCode::Success {
                    return Err(End::Error(format!(
                        "the broker refused the connection: {:?}",
                        ack.code
                    )));
                }
                c.accepted = true;
                self.metrics.mqtt().connected(self.connections == 0);
                self.connections += 1;
                tracing::info!(broker = %self.config.broker, bd_seq = self.bd_seq.get(), "MQTT connected");
                let mut filters: Vec<String> = self.topics.command_filters().to_vec();
                if let Some(host) = &self.config.primary_host_id {
                    filters.push(state_topic(host));
                }
                for f in filters {
                    c.client
                        .try_subscribe(f, QoS::AtLeastOnce)
                        .map_err(|e| End::Error(format!("cannot subscribe: {e}")))?;
                }
                if self.config.primary_host_id.is_none() {
                    self.births(c)?;
                }
            }
            Event::Incoming(Packet::Publish(p)) => self.on_publish(c, &p.topic, &p.payload)?,
            _ => {}
        }
        Ok(())
    }

    /// A message on a topic the node subscribed to.
    fn on_publish(&mut self, c: &mut Connection, topic: &str, payload: &[u8]) -> Result<(), End> {
        match self.topics.classify(topic) {
            Incoming::State { host } => {
                self.metrics.mqtt().received("state");
                if self.config.primary_host_id.as_deref() != Some(host) {
                    return Ok(());
                }
                let Some(state) = HostState::parse(payload) else {
                    tracing::warn!(
                        topic,
                        "MQTT: a STATE that is not {{\"online\": bool, \"timestamp\": ms}}: ignored"
                    );
                    return Ok(());
                };
                let change = self.host.update(state);
                self.metrics.mqtt().host(self.host.online());
                match change {
                    HostChange::Online => {
                        tracing::info!(host, "MQTT: the primary host is online");
                        if !self.born {
                            self.births(c)?;
                        }
                    }
                    HostChange::Offline => {
                        tracing::warn!(
                            host,
                            "MQTT: the primary host went offline: the leases of its commands end, the node disconnects"
                        );
                        // Its commands still queued are dropped first, so
                        // none lands after the stop; then its leases end
                        // now, with their stop.
                        self.commands.abort_all();
                        self.session = open_session(&self.control, &self.config);
                        let _ = c.client.try_publish(
                            self.topics.node_topic(Kind::NDeath),
                            QoS::AtLeastOnce,
                            false,
                            self.ndeath(),
                        );
                        self.metrics.mqtt().sent(Kind::NDeath.label());
                        let _ = c.client.try_disconnect();
                        return Err(End::HostOffline);
                    }
                    HostChange::None => {}
                }
            }
            Incoming::NodeCommand => {
                self.metrics.mqtt().received("ncmd");
                let Ok(p) = Payload::decode(payload) else {
                    tracing::warn!(
                        topic,
                        "MQTT: an NCMD that is no Sparkplug B payload: ignored"
                    );
                    return Ok(());
                };
                let rebirth = p.metrics.iter().any(|m| {
                    m.name.as_deref() == Some(REBIRTH) && metric::as_bool(m) == Some(true)
                });
                if rebirth && (self.born || self.host_ok()) {
                    tracing::info!("MQTT: rebirth asked for");
                    self.births(c)?;
                }
            }
            Incoming::DeviceCommand { device } => {
                self.metrics.mqtt().received("dcmd");
                self.on_dcmd(c, device.to_string(), payload);
            }
            Incoming::Other => self.metrics.mqtt().received("other"),
        }
        Ok(())
    }
}
