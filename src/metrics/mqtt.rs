//! The MQTT face's counters and the state of its link to the broker, for
//! `/metrics`, `/readyz` and the console. The face updates them; every
//! series exists from start-up, at 0, whether `[mqtt]` is configured or not,
//! so an alert needs no `absent()`.

use std::sync::Mutex;
use std::time::SystemTime;

use prometheus::{IntCounter, IntCounterVec, IntGauge, Opts, Registry};

/// What a message is, for the counters' `type` label.
const SENT_TYPES: &[&str] = &[
    "nbirth", "ndeath", "ndata", "dbirth", "ddeath", "ddata", "state", "status", "event", "reply",
];
/// What a received message is.
const RECEIVED_TYPES: &[&str] = &["ncmd", "dcmd", "state", "command", "other"];
/// What became of a command from MQTT.
const COMMAND_RESULTS: &[&str] = &["confirmed", "refused", "failed", "malformed"];

/// The link as `/readyz` and the console show it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LinkState {
    /// The broker, as configured (`mqtt://host:port`); `None`: no `[mqtt]`.
    pub broker: Option<String>,
    /// Connected to the broker (its CONNACK received).
    pub connected: bool,
    /// The primary host's last `STATE` said online (`None`: no primary
    /// host configured, or none heard yet).
    pub host_online: Option<bool>,
    /// Births are out: data flows to the host.
    pub born: bool,
    /// The last connection error, in words, and when.
    pub last_error: Option<(SystemTime, String)>,
}

/// The MQTT face's metrics.
pub struct MqttMetrics {
    connected: IntGauge,
    host_online: IntGauge,
    sent: IntCounterVec,
    received: IntCounterVec,
    reconnects: IntCounter,
    errors: IntCounter,
    last_error: IntGauge,
    commands: IntCounterVec,
    store_bytes: IntGauge,
    store_messages: IntGauge,
    store_dropped: IntCounter,
    store_skipped: IntGauge,
    replay_dropped: IntCounter,
    too_large: IntCounter,
    link: Mutex<LinkState>,
}

impl MqttMetrics {
    /// Creates the series and registers them in `registry`.
    pub fn register(registry: &Registry) -> Self {
        let gauge = |name: &str, help: &str| {
            let g = IntGauge::new(name, help)
                .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
            let _ = registry.register(Box::new(g.clone()));
            g
        };
        let counter = |name: &str, help: &str| {
            let c = IntCounter::new(name, help)
                .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
            let _ = registry.register(Box::new(c.clone()));
            c
        };
        let counter_vec = |name: &str, help: &str, label: &str, values: &[&str]| {
            let c = IntCounterVec::new(Opts::new(name, help), &[label])
                .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
            let _ = registry.register(Box::new(c.clone()));
            for v in values {
                c.with_label_values(&[v]);
            }
            c
        };
        MqttMetrics {
            connected: gauge(
                "drivegate_mqtt_connected",
                "1 while the MQTT face is connected to its broker.",
            ),
            host_online: gauge(
                "drivegate_mqtt_primary_host_online",
                "1 while the Sparkplug primary host's STATE says online (or no primary host is configured and the broker is connected).",
            ),
            sent: counter_vec(
                "drivegate_mqtt_messages_sent_total",
                "MQTT messages published, by type: Sparkplug's, or the JSON format's state, status, event, reply.",
                "type",
                SENT_TYPES,
            ),
            received: counter_vec(
                "drivegate_mqtt_messages_received_total",
                "MQTT messages received, by type: Sparkplug's, or the JSON format's command (other: on no topic the face serves).",
                "type",
                RECEIVED_TYPES,
            ),
            reconnects: counter(
                "drivegate_mqtt_reconnects_total",
                "Connections to the broker after the first.",
            ),
            errors: counter(
                "drivegate_mqtt_connection_errors_total",
                "Connections to the broker that failed or broke (refused, TLS, credentials, I/O).",
            ),
            last_error: gauge(
                "drivegate_mqtt_last_error_timestamp_seconds",
                "Unix time of the last MQTT connection error (0: none); /readyz says what it was.",
            ),
            commands: counter_vec(
                "drivegate_mqtt_commands_total",
                "Commands received over MQTT (DCMD metrics), by result: confirmed by the drive, refused by the control core, failed on the bus, malformed.",
                "result",
                COMMAND_RESULTS,
            ),
            store_bytes: gauge(
                "drivegate_mqtt_store_bytes",
                "Bytes of device data kept on disk while the broker or the primary host is away, not yet replayed.",
            ),
            store_messages: gauge(
                "drivegate_mqtt_store_messages",
                "Messages of device data kept on disk, not yet replayed.",
            ),
            store_dropped: counter(
                "drivegate_mqtt_store_dropped_total",
                "Stored messages dropped unsent, the oldest first, to keep [mqtt] store_max_mb.",
            ),
            store_skipped: gauge(
                "drivegate_mqtt_store_skipped_bytes",
                "Bytes of the store skipped unread when it was opened: older segments beyond [mqtt] store_max_mb, and the head of a segment longer than one may be; 0 when it was read within its bound.",
            ),
            replay_dropped: counter(
                "drivegate_mqtt_replay_dropped_total",
                "Stored messages dropped at replay because their drive is no longer configured (it will never be born again).",
            ),
            too_large: counter(
                "drivegate_mqtt_messages_too_large_total",
                "MQTT messages from the broker larger than [mqtt] max_message_bytes, dropped unread (each audited once); the connection stays.",
            ),
            link: Mutex::new(LinkState::default()),
        }
    }

    /// A message above `max_message_bytes` was dropped.
    pub fn too_large(&self) {
        self.too_large.inc();
    }

    /// The face started towards `broker`.
    pub fn configured(&self, broker: String) {
        self.with_link(|l| l.broker = Some(broker));
    }

    /// The face stopped for good (a reload removed `[mqtt]`): `/readyz`
    /// and the console no longer show a link.
    pub fn unconfigured(&self) {
        self.connected.set(0);
        self.with_link(|l| *l = LinkState::default());
    }

    /// The broker accepted a connection (`first`: the first since start).
    pub fn connected(&self, first: bool) {
        if !first {
            self.reconnects.inc();
        }
        self.connected.set(1);
        self.with_link(|l| l.connected = true);
    }

    /// The connection failed or broke, `why` in words.
    pub fn connection_error(&self, why: String) {
        self.errors.inc();
        self.connected.set(0);
        let now = SystemTime::now();
        let secs = now
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_secs()).unwrap_or(i64::MAX));
        self.last_error.set(secs);
        self.with_link(|l| {
            l.connected = false;
            l.born = false;
            l.last_error = Some((now, why));
        });
    }

    /// The connection ended without an error (shutdown, host offline).
    pub fn disconnected(&self) {
        self.connected.set(0);
        self.with_link(|l| {
            l.connected = false;
            l.born = false;
        });
    }

    /// The primary host's `STATE`, or `None` without a primary host.
    pub fn host(&self, online: Option<bool>) {
        self.host_online.set(i64::from(online.unwrap_or(true)));
        self.with_link(|l| l.host_online = online);
    }

    /// Births are out (or, `false`, data no longer flows).
    pub fn born(&self, born: bool) {
        self.with_link(|l| l.born = born);
    }

    /// A message of type `kind` (one of [`SENT_TYPES`]) was published.
    pub fn sent(&self, kind: &str) {
        self.sent.with_label_values(&[kind]).inc();
    }

    /// A message of type `kind` (one of [`RECEIVED_TYPES`]) came in.
    pub fn received(&self, kind: &str) {
        self.received.with_label_values(&[kind]).inc();
    }

    /// A command's result (one of [`COMMAND_RESULTS`]).
    pub fn command(&self, result: &str) {
        self.commands.with_label_values(&[result]).inc();
    }

    /// The store's bytes skipped unread when it was opened.
    pub fn store_skipped(&self, bytes: u64) {
        self.store_skipped
            .set(i64::try_from(bytes).unwrap_or(i64::MAX));
    }

    /// The store's figures now: bytes and messages waiting, messages
    /// dropped since start-up.
    pub fn store(&self, bytes: u64, messages: u64, dropped: u64) {
        self.store_bytes
            .set(i64::try_from(bytes).unwrap_or(i64::MAX));
        self.store_messages
            .set(i64::try_from(messages).unwrap_or(i64::MAX));
        let counted = self.store_dropped.get();
        if dropped > counted {
            self.store_dropped.inc_by(dropped - counted);
        }
    }

    /// `n` kept messages were dropped at replay: their drive is no
    /// longer configured.
    pub fn replay_dropped(&self, n: u64) {
        self.replay_dropped.inc_by(n);
    }

    /// The link now.
    pub fn link(&self) -> LinkState {
        self.link.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    fn with_link(&self, f: impl FnOnce(&mut LinkState)) {
        f(&mut self.link.lock().unwrap_or_else(|p| p.into_inner()));
    }
}
