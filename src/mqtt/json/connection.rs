//! One MQTT 5 connection to the broker for the JSON format: rumqttc's
//! `v5` client with options built from `[mqtt]` (keepalive, credentials,
//! TLS) and `<prefix>/state` = `offline` (retained) as its will, its event
//! loop polled in a task of its own whose events come to the node. MQTT 5
//! gives a command its response topic and correlation data.

use crate::config::MqttConfig;
use crate::mqtt::connection::{EventLoop, Link};
use rumqttc::v5::mqttbytes::QoS;
use rumqttc::v5::mqttbytes::v5::LastWill;
use rumqttc::v5::{AsyncClient, Event, MqttOptions};

/// How many requests (publishes, subscriptions) may wait in the client.
const REQUEST_CAPACITY: usize = 4096;

/// One MQTT 5 connection to the broker.
pub(super) type Connection = Link<AsyncClient, Event>;

impl EventLoop for rumqttc::v5::EventLoop {
    type Event = Event;
    async fn next(&mut self) -> Result<Event, String> {
        self.poll().await.map_err(|e| describe(&e))
    }
}

impl Connection {
    /// Starts connecting as `client_id`, with `will_topic` = `offline`
    /// (retained) as the will. Fails only on what is wrong before any
    /// network traffic (the password file, the TLS files).
    pub(super) fn open(
        config: &MqttConfig,
        client_id: &str,
        will_topic: &str,
    ) -> Result<Connection, String> {
        let mut options =
            MqttOptions::new(client_id, config.broker.host.clone(), config.broker.port);
        options.set_keep_alive(config.keepalive());
        // A clean session that ends with the connection: the broker keeps
        // nothing for drivegate while it is away, so no command queued
        // then is delivered later (one that came anyway is refused,
        // `super::super::arrival`).
        options.set_clean_start(true);
        // MQTT 5's Maximum Packet Size, in CONNECT: the broker sends
        // nothing larger (mosquitto drops it and logs "Dropping too large
        // outgoing PUBLISH"), so a large message costs itself, not the
        // connection.
        options.set_max_packet_size(Some(config.max_message_bytes));
        options.set_session_expiry_interval(Some(0));
        options.set_last_will(LastWill::new(
            will_topic,
            "offline",
            QoS::AtLeastOnce,
            true,
            None,
        ));
        if let Some((user, password)) = crate::mqtt::connection::credentials(config)? {
            options.set_credentials(user, password);
        }
        if let Some(tls) = crate::mqtt::connection::tls_transport(config)? {
            options.set_transport(tls);
        }
        let (client, eventloop) = AsyncClient::new(options, REQUEST_CAPACITY);
        Ok(Link::new(client, eventloop))
    }
}

/// A connection error in words a plant engineer can act on.
fn describe(e: &rumqttc::v5::ConnectionError) -> String {
    use rumqttc::v5::ConnectionError as E;
    match e {
        E::Io(io) => crate::mqtt::relay::io_words(io),
        E::MqttState(rumqttc::v5::StateError::Deserialization(
            rumqttc::v5::mqttbytes::Error::PayloadSizeLimitExceeded { pkt_size, .. },
        )) => crate::mqtt::connection::too_large_words(*pkt_size),
        E::ConnectionRefused(code) => format!("the broker refused the connection: {code:?}"),
        E::Tls(tls) => format!("TLS with the broker: {tls}"),
        other => other.to_string(),
    }
}
