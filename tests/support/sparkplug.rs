//! A Sparkplug B host application for the MQTT tests: an MQTT client of
//! its own (rumqttc) that takes every Sparkplug message of the broker and
//! decodes it with the same `.proto`'s types as the daemon, announces
//! itself as a primary host (`STATE`, retained, its will saying offline)
//! and sends NCMD and DCMD.

use std::time::Duration;

use drivegate::mqtt::metric::{self, Value};
use drivegate::mqtt::sparkplug_b::payload::Metric;
use drivegate::mqtt::sparkplug_b::{DataType, Payload};
use prost::Message;
use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Packet, QoS};
use tokio::sync::mpsc;

/// One message the host received.
#[derive(Debug, Clone)]
pub struct Msg {
    pub topic: String,
    /// The message type (`NBIRTH`, `DDATA`, `STATE` ...).
    pub kind: String,
    /// The device id, for device messages.
    pub device: Option<String>,
    /// The decoded payload (not for `STATE`).
    pub payload: Option<Payload>,
    pub raw: Vec<u8>,
}

impl Msg {
    /// The metric named `name`, if the payload has one.
    pub fn metric(&self, name: &str) -> Option<&Metric> {
        self.payload
            .as_ref()?
            .metrics
            .iter()
            .find(|m| m.name.as_deref() == Some(name))
    }

    /// The value of metric `name`.
    pub fn value(&self, name: &str) -> Option<Value> {
        self.metric(name).map(metric::value_of)
    }

    pub fn seq(&self) -> Option<u64> {
        self.payload.as_ref()?.seq
    }

    /// The names of its metrics.
    pub fn names(&self) -> Vec<String> {
        self.payload
            .iter()
            .flat_map(|p| p.metrics.iter().filter_map(|m| m.name.clone()))
            .collect()
    }

    pub fn is(&self, kind: &str, device: Option<&str>) -> bool {
        self.kind == kind && self.device.as_deref() == device
    }
}

/// The host.
pub struct Host {
    pub client: AsyncClient,
    rx: mpsc::UnboundedReceiver<Msg>,
    /// Every message taken so far, in order.
    pub seen: Vec<Msg>,
    /// The primary host id it announces, if any.
    pub id: Option<String>,
}

fn decode(topic: &str, raw: &[u8]) -> Msg {
    let levels: Vec<&str> = topic.split('/').collect();
    let (kind, device) = match levels.as_slice() {
        ["spBv1.0", "STATE", _] => ("STATE".to_string(), None),
        ["spBv1.0", _, kind, _] => (kind.to_string(), None),
        ["spBv1.0", _, kind, _, device] => (kind.to_string(), Some(device.to_string())),
        _ => ("?".to_string(), None),
    };
    // What others send the node may be anything (the tests send garbage
    // on purpose); what the node sends must decode.
    let payload = if kind == "STATE" || (kind.ends_with("CMD") && Payload::decode(raw).is_err()) {
        None
    } else {
        Some(
            Payload::decode(raw)
                .unwrap_or_else(|e| panic!("{topic}: not a Sparkplug B payload: {e}")),
        )
    };
    Msg {
        topic: topic.to_string(),
        kind,
        device,
        payload,
        raw: raw.to_vec(),
    }
}

fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

/// A `STATE` payload.
pub fn state(online: bool) -> Vec<u8> {
    format!("{{\"online\":{online},\"timestamp\":{}}}", now_ms()).into_bytes()
}

impl Host {
    /// Connects to the broker at `port`, subscribes to every Sparkplug
    /// topic and returns once the subscription is in place. With
    /// `primary`, it is that primary host: its will is its `STATE`
    /// offline; it says online only when told ([`Host::online`]).
    pub async fn connect(port: u16, client_id: &str, primary: Option<&str>) -> Host {
        Self::connect_as(port, client_id, primary, None).await
    }

    /// [`Host::connect`], logged in to the broker as `login` (user,
    /// password).
    pub async fn connect_as(
        port: u16,
        client_id: &str,
        primary: Option<&str>,
        login: Option<(&str, &str)>,
    ) -> Host {
        let mut options = MqttOptions::new(client_id, "127.0.0.1", port);
        if let Some((user, password)) = login {
            options.set_credentials(user, password);
        }
        options.set_keep_alive(Duration::from_secs(5));
        options.set_max_packet_size(1 << 20, 1 << 20);
        if let Some(id) = primary {
            options.set_last_will(LastWill::new(
                format!("spBv1.0/STATE/{id}"),
                state(false),
                QoS::AtLeastOnce,
                true,
            ));
        }
        let (client, mut eventloop) = AsyncClient::new(options, 256);
        let (tx, rx) = mpsc::unbounded_channel();
        let (subscribed_tx, mut subscribed) = mpsc::unbounded_channel();
        client
            .subscribe("spBv1.0/#", QoS::AtLeastOnce)
            .await
            .unwrap();
        let again = client.clone();
        tokio::spawn(async move {
            loop {
                match eventloop.poll().await {
                    // A broker that restarted forgot the subscription.
                    Ok(Event::Incoming(Packet::ConnAck(ack))) if !ack.session_present => {
                        let _ = again.try_subscribe("spBv1.0/#", QoS::AtLeastOnce);
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        if tx.send(decode(&p.topic, &p.payload)).is_err() {
                            break;
                        }
                    }
                    Ok(Event::Incoming(Packet::SubAck(_))) => {
                        let _ = subscribed_tx.send(());
                    }
                    Ok(_) => {}
                    Err(_) => {
                        if tx.is_closed() {
                            break;
                        }
                        tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                }
            }
        });
        tokio::time::timeout(Duration::from_secs(10), subscribed.recv())
            .await
            .expect("the host's subscription is acknowledged within 10 s");
        Host {
            client,
            rx,
            seen: Vec::new(),
            id: primary.map(str::to_string),
        }
    }

    /// Publishes this primary host's `STATE` (retained).
    pub async fn announce(&self, online: bool) {
        let id = self.id.as_deref().expect("a primary host");
        self.client
            .publish(
                format!("spBv1.0/STATE/{id}"),
                QoS::AtLeastOnce,
                true,
                state(online),
            )
            .await
            .unwrap();
    }

    /// The next message for which `pred` holds (the ones before it are
    /// kept in `seen`), or fails the test after `limit`.
    pub async fn next(&mut self, limit: Duration, what: &str, pred: impl Fn(&Msg) -> bool) -> Msg {
        let deadline = tokio::time::Instant::now() + limit;
        loop {
            let msg = tokio::time::timeout_at(deadline, self.rx.recv())
                .await
                .unwrap_or_else(|_| {
                    panic!(
                        "no {what} within {limit:?}; seen: {:?}",
                        self.seen.iter().map(|m| &m.topic).collect::<Vec<_>>()
                    )
                })
                .expect("the host's connection task ended");
            self.seen.push(msg.clone());
            if pred(&msg) {
                return msg;
            }
        }
    }

    /// Sends `metrics` to device `device` of node `group`/`node` (DCMD).
    pub async fn dcmd(&self, group: &str, node: &str, device: &str, metrics: Vec<Metric>) {
        let payload = Payload {
            timestamp: Some(now_ms()),
            metrics,
            ..Default::default()
        };
        self.client
            .publish(
                format!("spBv1.0/{group}/DCMD/{node}/{device}"),
                QoS::AtLeastOnce,
                false,
                payload.encode_to_vec(),
            )
            .await
            .unwrap();
    }

    /// Asks node `group`/`node` for a rebirth (NCMD).
    pub async fn rebirth(&self, group: &str, node: &str) {
        let payload = Payload {
            timestamp: Some(now_ms()),
            metrics: vec![bool_metric("Node Control/Rebirth", true)],
            ..Default::default()
        };
        self.client
            .publish(
                format!("spBv1.0/{group}/NCMD/{node}"),
                QoS::AtLeastOnce,
                false,
                payload.encode_to_vec(),
            )
            .await
            .unwrap();
    }
}

pub fn bool_metric(name: &str, v: bool) -> Metric {
    metric::metric(name, DataType::Boolean, Value::Bool(v), now_ms())
}

pub fn double_metric(name: &str, v: f64) -> Metric {
    metric::metric(name, DataType::Double, Value::Double(v), now_ms())
}

pub fn string_metric(name: &str, v: &str) -> Metric {
    metric::metric(name, DataType::String, Value::Text(v.to_string()), now_ms())
}

/// A number from a metric's value.
pub fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Int(i) => Some(*i as f64),
        Value::UInt(u) => Some(f64::from(*u)),
        Value::Double(d) => Some(*d),
        _ => None,
    }
}
