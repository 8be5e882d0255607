//! What the broker sends the node: its acceptance of the connection (then
//! the subscriptions and, without a primary host, the births), the
//! acknowledgement of the subscriptions, the primary host's `STATE`, an
//! NCMD asking for a rebirth, and DCMDs. A command that is not live
//! (retained, or queued for an earlier session) is refused by the core.

use prost::Message;
use rumqttc::{Event, Packet, QoS, SubscribeFilter};

use super::{Connection, End, Node, now_ms, open_session};
use crate::control::{Caller, Face};
use crate::mqtt::arrival::Connected;
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
                self.connected = Connected::accepted(now_ms(), ack.session_present);
                if ack.session_present {
                    tracing::warn!(
                        broker = %self.config.broker,
                        "MQTT: the broker kept a session for drivegate although it asked for a clean one: commands it queued are refused"
                    );
                }
                self.metrics.mqtt().connected(self.connections == 0);
                self.connections += 1;
                tracing::info!(broker = %self.config.broker, bd_seq = self.bd_seq.get(), "MQTT connected");
                let mut filters: Vec<String> = self.topics.command_filters().to_vec();
                if let Some(host) = &self.config.primary_host_id {
                    filters.push(state_topic(host));
                }
                // One SUBSCRIBE, so one SUBACK: what comes before it was
                // queued for an earlier session.
                c.client
                    .try_subscribe_many(
                        filters
                            .into_iter()
                            .map(|f| SubscribeFilter::new(f, QoS::AtLeastOnce)),
                    )
                    .map_err(|e| End::Error(format!("cannot subscribe: {e}")))?;
                if self.config.primary_host_id.is_none() {
                    self.births(c)?;
                }
            }
            Event::Incoming(Packet::SubAck(_)) => self.connected.subscribed(),
            Event::Incoming(Packet::Publish(p)) => {
                self.on_publish(c, &p.topic, &p.payload, p.retain)?;
            }
            _ => {}
        }
        Ok(())
    }

    /// A message on a topic the node subscribed to (`retained`: its
    /// retain flag on delivery).
    fn on_publish(
        &mut self,
        c: &mut Connection,
        topic: &str,
        payload: &[u8],
        retained: bool,
    ) -> Result<(), End> {
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
                let delivery = self.connected.delivery(retained, p.timestamp);
                if self
                    .control
                    .check_live(
                        &self.caller(),
                        "the node",
                        &format!("NCMD {REBIRTH}"),
                        delivery,
                    )
                    .is_err()
                {
                    self.metrics.mqtt().command("refused");
                    return Ok(());
                }
                if rebirth && (self.born || self.host_ok()) {
                    tracing::info!("MQTT: rebirth asked for");
                    self.births(c)?;
                }
            }
            Incoming::DeviceCommand { device } => {
                self.metrics.mqtt().received("dcmd");
                self.on_dcmd(c, device.to_string(), payload, retained);
            }
            Incoming::Other => self.metrics.mqtt().received("other"),
        }
        Ok(())
    }
}

impl Node {
    /// The caller of a command from the broker: face `mqtt`, who sent it
    /// as far as known, the role the core gave `[mqtt] commands`, in the
    /// session.
    pub(super) fn caller(&self) -> Caller {
        Caller::new(Face::Mqtt, self.who.clone(), self.role, self.source)
            .in_session(Face::Mqtt, self.session.id())
    }
}
