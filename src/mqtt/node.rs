//! The Sparkplug B edge node: one task that owns the broker connection and
//! everything the node has said on it (bdSeq, seq, which devices are born,
//! what each last published), so their order on the wire is the order
//! they were decided in.
//!
//! Its loop waits on the connection's events, the buses' status events, the
//! results of commands, and its timers:
//!
//! - **Connection.** A new connection for every bdSeq: the NDEATH that ends
//!   it is its MQTT will, so a reconnect (after an error, or after the
//!   primary host went offline) builds new options with the next bdSeq
//!   rather than letting the client reconnect with a stale will. rumqttc's
//!   event loop is polled in a task of its own and its events come here.
//! - **Births.** NBIRTH (bdSeq, `Node Control/Rebirth`, version, buses),
//!   then a DBIRTH for each drive that answers, once the broker accepted the
//!   connection and, with a primary host, once its `STATE` says online. An
//!   NCMD `Node Control/Rebirth` publishes them again, same bdSeq.
//! - **Data.** Each status of a drive publishes the fields that moved past
//!   their deadbands (one DDATA per poll), and a value that settled within
//!   its deadband once it held ([`super::exception`]). Births and deaths
//!   follow the core's freshness ([`freshness`]): a drive that stops
//!   answering, or whose bus goes down, gets a DDEATH, and a DBIRTH once
//!   its data is live again. While nothing can be published, the changes
//!   go to the [`Outbox`](super::Outbox).
//! - **Commands** go to the control core in a task per DCMD (its metrics in
//!   order), with a caller in the MQTT session; the result comes back here
//!   and is published.
//! - **The session's lease.** While connected (and the primary host is
//!   online), the session is renewed a few times per `comm_loss_ms`; once
//!   the connection is lost, its leases end after `comm_loss_ms` with
//!   `comm_loss_action`. The host's `STATE` offline ends them at once (the
//!   session closes), and the node publishes its NDEATH and reconnects, as
//!   Sparkplug 3.0 asks of an edge node whose primary host went away.

mod freshness;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use prost::Message;
use rumqttc::{Event, LastWill, Packet, QoS};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::{Instant, sleep_until};
use tokio_util::sync::CancellationToken;

use super::Outbox;
use super::bd_seq::BdSeq;
use super::commands::{self, Command};
use super::connection::{Connection, next_event};
use super::exception::Reported;
use super::host::{Host, HostChange, HostState};
use super::metric::{self, BD_SEQ, LAST_RESULT, REBIRTH, Setpoints, Value, Writable};
use super::replay::{self, Held};
use super::sparkplug_b::payload::Metric;
use super::sparkplug_b::{DataType, Payload};
use super::topic::{Incoming, Kind, NodeTopics, state_topic};
use crate::bus::SourceId;
use crate::bus::cache::BusEvent;
use crate::bus::handle::PortState;
use crate::config::MqttConfig;
use crate::control::{Caller, CommLoss, Control, Face, SessionGuard};
use crate::metrics::Metrics;

/// The QoS of births and data (Sparkplug: 0); the NDEATH, as the will
/// and at a clean stop, goes with 1.
const DATA_QOS: QoS = QoS::AtMostOnce;

/// How often kept data is replayed, and how many messages at a time.
const REPLAY_EVERY: Duration = Duration::from_millis(20);
const REPLAY_BATCH: usize = 8;

/// The first wait before reconnecting; it doubles up to [`BACKOFF_MAX`].
const BACKOFF_MIN: Duration = Duration::from_millis(250);
const BACKOFF_MAX: Duration = Duration::from_secs(15);

/// How the session's closing reads in lease news and the audit log.
const SESSION_CLOSING: &str =
    "the MQTT session ended (the primary host went offline, or the face stopped)";

/// What a command's task reports.
struct CommandResult {
    device: String,
    metric: Writable,
    /// The value the drive confirmed, or the failure in words.
    outcome: Result<Value, String>,
}

/// What the node knows of one drive (device).
#[derive(Default)]
struct Device {
    /// Its DBIRTH is out on this connection.
    born: bool,
    /// Its status fields as last published (or kept).
    reported: Reported,
    /// The last setpoints the drive confirmed from MQTT.
    setpoints: Setpoints,
    /// What became of the last command (empty: confirmed).
    last_result: String,
}

/// The edge node.
struct Node {
    config: Arc<MqttConfig>,
    control: Control,
    metrics: Arc<Metrics>,
    topics: NodeTopics,
    /// Who commands come from, for the audit log and lease owners.
    who: Arc<str>,
    source: SourceId,
    outbox: Box<dyn Outbox>,
    /// Kept data taken from the outbox, waiting for its drive's birth.
    held: Held,
    bd_seq: BdSeq,
    seq: u8,
    /// Births are out on the current connection.
    born: bool,
    devices: BTreeMap<String, Device>,
    host: Host,
    session: SessionGuard,
    connections: u64,
    results_tx: mpsc::UnboundedSender<CommandResult>,
    bus_tx: mpsc::Sender<BusEvent>,
    forwarders: Vec<JoinHandle<()>>,
    /// The plant's directory version the forwarders were started for.
    followed: Option<u64>,
    /// The commands on their way through the core, in the current session.
    commands: tokio::task::JoinSet<()>,
}

/// Starts the edge node's task; it ends after `shutdown` fired.
pub(super) fn spawn(
    config: Arc<MqttConfig>,
    node_id: String,
    control: Control,
    metrics: Arc<Metrics>,
    outbox: Box<dyn Outbox>,
    state_dir: Option<std::path::PathBuf>,
    shutdown: CancellationToken,
) -> JoinHandle<()> {
    let (results_tx, results_rx) = mpsc::unbounded_channel();
    let (bus_tx, bus_rx) = mpsc::channel(4096);
    let topics = NodeTopics::new(&config.group_id, &node_id);
    // What is known of who commands: the broker's login, the host claimed.
    let who: Arc<str> = super::identity::who(&config, config.primary_host_id.as_deref()).into();
    let session = open_session(&control, &config);
    let node = Node {
        topics,
        who,
        source: SourceId::new_unique(),
        outbox,
        held: Held::default(),
        bd_seq: BdSeq::load(state_dir.as_deref()),
        seq: 0,
        born: false,
        devices: BTreeMap::new(),
        host: Host::default(),
        session,
        connections: 0,
        results_tx,
        bus_tx,
        forwarders: Vec::new(),
        followed: None,
        commands: tokio::task::JoinSet::new(),
        config,
        control,
        metrics,
    };
    tokio::spawn(node.run(bus_rx, results_rx, shutdown))
}

impl Node {
    /// Runs the node until `shutdown` fires, then publishes its NDEATH and
    /// disconnects.
    async fn run(
        mut self,
        mut bus_rx: mpsc::Receiver<BusEvent>,
        mut results_rx: mpsc::UnboundedReceiver<CommandResult>,
        shutdown: CancellationToken,
    ) {
        self.metrics
            .mqtt()
            .configured(self.config.broker.to_string());
        self.metrics
            .mqtt()
            .host(self.config.primary_host_id.as_ref().map(|_| false));
        self.follow_buses();
        let mut conn: Option<Connection> = None;
        let mut reconnect_at = Instant::now();
        let mut backoff = BACKOFF_MIN;
        let renew_every = (self.config.comm_loss() / 4).max(Duration::from_millis(20));
        let mut renew = tokio::time::interval(renew_every);
        renew.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let full_every = Duration::from_secs(self.config.full_publish_s.max(1));
        let mut replay = tokio::time::interval(REPLAY_EVERY);
        replay.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut full = tokio::time::interval_at(Instant::now() + full_every, full_every);
        full.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut control_rx = self.control.subscribe();
        loop {
            tokio::select! {
                _ = shutdown.cancelled() => break,
                _ = sleep_until(reconnect_at), if conn.is_none() => {
                    match self.connect() {
                        Ok(c) => conn = Some(c),
                        Err(why) => {
                            self.failed(&why);
                            reconnect_at = Instant::now() + backoff;
                            backoff = (backoff * 2).min(BACKOFF_MAX);
                        }
                    }
                }
                event = next_event(&mut conn) => {
                    let Some(c) = conn.as_mut() else { continue };
                    match event {
                        Some(Ok(event)) => {
                            if let Err(end) = self.on_event(c, event) {
                                let was_accepted = c.accepted;
                                conn = None;
                                self.lost();
                                match end {
                                    End::HostOffline => {
                                        reconnect_at = Instant::now();
                                    }
                                    End::Error(why) => {
                                        self.failed(&why);
                                        if was_accepted {
                                            backoff = BACKOFF_MIN;
                                        }
                                        reconnect_at = Instant::now() + backoff;
                                        backoff = (backoff * 2).min(BACKOFF_MAX);
                                    }
                                }
                                self.bd_seq.next();
                            } else if c.accepted {
                                backoff = BACKOFF_MIN;
                            }
                        }
                        Some(Err(why)) => {
                            conn = None;
                            self.lost();
                            self.failed(&why);
                            reconnect_at = Instant::now() + backoff;
                            backoff = (backoff * 2).min(BACKOFF_MAX);
                            self.bd_seq.next();
                        }
                        None => {
                            conn = None;
                            self.lost();
                            self.failed("the connection's event loop ended");
                            reconnect_at = Instant::now() + backoff;
                            backoff = (backoff * 2).min(BACKOFF_MAX);
                            self.bd_seq.next();
                        }
                    }
                }
                Some(event) = bus_rx.recv() => {
                    self.on_bus(conn.as_ref(), event);
                }
                Some(result) = results_rx.recv() => {
                    self.on_result(conn.as_ref(), result);
                }
                published = control_rx.recv() => {
                    self.on_control(conn.as_ref(), published);
                }
                _ = renew.tick() => {
                    let connected = conn.as_ref().is_some_and(|c| c.accepted);
                    if connected && self.host_ok() {
                        self.session.active();
                    }
                    self.reconcile(conn.as_ref());
                }
                _ = replay.tick() => {
                    if let Some(c) = conn.as_ref() && self.born {
                        self.replay(c);
                    }
                }
                _ = full.tick(), if self.config.full_publish_s > 0 => {
                    if let Some(c) = conn.as_ref() && self.born {
                        self.full_publish(c);
                    }
                }
            }
        }
        if let Some(mut c) = conn.take()
            && c.accepted
        {
            // A clean DISCONNECT suppresses the will: the NDEATH is sent
            // explicitly, so hosts see the node go.
            let ndeath = self.ndeath();
            let _ = c.client.try_publish(
                self.topics.node_topic(Kind::NDeath),
                QoS::AtLeastOnce,
                false,
                ndeath,
            );
            self.metrics.mqtt().sent(Kind::NDeath.label());
            let _ = c.client.try_disconnect();
            let flushed = tokio::time::timeout(Duration::from_secs(2), async {
                while let Some(Ok(event)) = c.events.recv().await {
                    if matches!(event, Event::Outgoing(rumqttc::Outgoing::Disconnect)) {
                        break;
                    }
                }
            })
            .await;
            if flushed.is_err() {
                tracing::warn!("MQTT: the broker did not take the NDEATH within 2 s at shutdown");
            }
        }
        self.metrics.mqtt().disconnected();
        // Data still waiting for its drive's birth goes back to the store,
        // for the next process.
        for (device, metrics) in self.held.drain() {
            self.outbox.keep(&device, metrics);
        }
        for f in self.forwarders.drain(..) {
            f.abort();
        }
    }

    /// The primary host allows data and renewals (or there is none).
    fn host_ok(&self) -> bool {
        self.config.primary_host_id.is_none() || self.host.online() == Some(true)
    }

    /// Starts a connection with the current bdSeq's NDEATH as its will.
    fn connect(&mut self) -> Result<Connection, String> {
        self.bd_seq.connecting();
        let conn = Connection::open(
            &self.config,
            &format!("drivegate-{}-{}", self.config.group_id, self.topics.node()),
            LastWill::new(
                self.topics.node_topic(Kind::NDeath),
                self.ndeath(),
                QoS::AtLeastOnce,
                false,
            ),
        )?;
        self.born = false;
        self.metrics.mqtt().born(false);
        // The host's retained STATE comes again on this connection.
        self.host = Host::default();
        Ok(conn)
    }

    /// The connection is gone (error, or closed by the node).
    fn lost(&mut self) {
        self.born = false;
        for d in self.devices.values_mut() {
            d.born = false;
        }
        self.metrics.mqtt().disconnected();
    }

    fn failed(&self, why: &str) {
        tracing::warn!(broker = %self.config.broker, "MQTT: {why}");
        self.metrics.mqtt().connection_error(why.to_string());
    }

    fn on_event(&mut self, c: &mut Connection, event: Event) -> Result<(), End> {
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

    /// A DCMD for `device`: its metrics in order, through the core, in a
    /// task of their own.
    fn on_dcmd(&mut self, c: &Connection, device: String, payload: &[u8]) {
        let Ok(target) = self.control.target(&device) else {
            self.metrics.mqtt().command("malformed");
            tracing::warn!(
                device,
                "MQTT: a DCMD for a device that is not a configured drive: ignored"
            );
            return;
        };
        let Ok(p) = Payload::decode(payload) else {
            self.metrics.mqtt().command("malformed");
            self.last_result(
                Some(c),
                &device,
                "the DCMD is no Sparkplug B payload".to_string(),
            );
            return;
        };
        let mut run: Vec<Command> = Vec::new();
        for m in &p.metrics {
            match commands::parse(m) {
                Ok(Some(cmd)) => run.push(cmd),
                Ok(None) => {}
                Err(malformed) => {
                    self.metrics.mqtt().command("malformed");
                    self.last_result(Some(c), &device, malformed.0);
                }
            }
        }
        if run.is_empty() {
            return;
        }
        let role = self.config.commands().role();
        let caller = Caller::new(Face::Mqtt, self.who.clone(), role, self.source)
            .in_session(Face::Mqtt, self.session.id());
        self.session.active();
        let control = self.control.clone();
        let results = self.results_tx.clone();
        // Finished commands' handles go; the others stay to be aborted
        // with their session.
        while self.commands.try_join_next().is_some() {}
        self.commands.spawn(async move {
            for cmd in run {
                let outcome = commands::run(&control, &caller, target, &cmd)
                    .await
                    .map(|()| commands::confirmed_value(&cmd))
                    .map_err(|f| f.to_string());
                let failed = outcome.is_err();
                let _ = results.send(CommandResult {
                    device: device.clone(),
                    metric: cmd.metric,
                    outcome,
                });
                // The rest of a DCMD whose command failed is not sent: a
                // setpoint after a refused mode would go to the wrong mode.
                if failed {
                    break;
                }
            }
        });
    }

    fn on_result(&mut self, c: Option<&Connection>, result: CommandResult) {
        let now = now_ms();
        let device = self.devices.entry(result.device.clone()).or_default();
        let mut metrics = Vec::new();
        match result.outcome {
            Ok(value) => {
                self.metrics.mqtt().command("confirmed");
                match (&value, result.metric) {
                    (Value::Double(v), Writable::SpeedRpm) => device.setpoints.speed_rpm = Some(*v),
                    (Value::Double(v), Writable::PositionDeg) => {
                        device.setpoints.position_deg = Some(*v);
                    }
                    (Value::Double(v), Writable::TorqueA) => device.setpoints.torque_a = Some(*v),
                    _ => {}
                }
                device.last_result.clear();
                metrics.push(metric::metric(
                    result.metric.name(),
                    result.metric.datatype(),
                    value,
                    now,
                ));
                metrics.push(metric::metric(
                    LAST_RESULT,
                    DataType::String,
                    Value::Text(String::new()),
                    now,
                ));
            }
            Err(words) => {
                let refused = words.starts_with("refused");
                self.metrics
                    .mqtt()
                    .command(if refused { "refused" } else { "failed" });
                let words = format!("{}: {words}", result.metric.name());
                device.last_result = words.clone();
                metrics.push(metric::metric(
                    LAST_RESULT,
                    DataType::String,
                    Value::Text(words),
                    now,
                ));
            }
        }
        self.device_data(c, &result.device, metrics);
    }

    fn last_result(&mut self, c: Option<&Connection>, device: &str, words: String) {
        let now = now_ms();
        self.devices
            .entry(device.to_string())
            .or_default()
            .last_result = words.clone();
        self.device_data(
            c,
            device,
            vec![metric::metric(
                LAST_RESULT,
                DataType::String,
                Value::Text(words),
                now,
            )],
        );
    }

    /// Publishes `metrics` of `device` as a DDATA when its birth is out,
    /// else keeps them in the outbox.
    fn device_data(&mut self, c: Option<&Connection>, device: &str, metrics: Vec<Metric>) {
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

    fn on_bus(&mut self, c: Option<&Connection>, event: BusEvent) {
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

    /// The configured drive at `unit` of bus `bus`, read from the plant
    /// now (the set of drives may change while the daemon runs).
    fn drive_at(&self, bus: &str, unit: u8) -> Option<String> {
        let now = self.control.plant().now();
        let index = now
            .indexed_buses()
            .find(|(_, b)| b.handle.name() == bus)
            .map(|(i, _)| i)?;
        now.drive_on(index, unit).map(|d| d.name.clone())
    }

    fn bus_state(&self, bus: &str) -> String {
        self.control
            .plant()
            .bus(bus)
            .map_or("unknown", |b| match b.handle.port_state() {
                PortState::Opening => "opening",
                PortState::Up { .. } => "up",
                PortState::Down { .. } => "down",
            })
            .to_string()
    }

    /// NBIRTH and every answering drive's DBIRTH (seq from 0).
    fn births(&mut self, c: &Connection) -> Result<(), End> {
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

    fn device_birth(&mut self, c: &Connection, name: &str, status: Option<&crate::drive::Status>) {
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

    /// Every field of every born drive, whatever its deadband.
    fn full_publish(&mut self, c: &Connection) {
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
    fn replay(&mut self, c: &Connection) {
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

    /// Follows the plant's changes (a configuration reload): a bus added
    /// is followed, a drive no longer configured dies (DDEATH).
    fn reconcile(&mut self, c: Option<&Connection>) {
        let plant = self.control.plant().now();
        // A bus added, removed or reopened: follow the buses as they are.
        if self.followed != Some(plant.version()) {
            self.follow_buses();
        }
        let gone: Vec<String> = self
            .devices
            .keys()
            .filter(|name| !plant.drives().any(|d| &d.name == *name))
            .cloned()
            .collect();
        let dropped = self.held.drop_gone(|name| {
            if plant.drives().any(|d| d.name == name) {
                replay::Device::Unborn
            } else {
                replay::Device::Gone
            }
        });
        if dropped > 0 {
            self.metrics.mqtt().replay_dropped(dropped as u64);
        }
        for name in gone {
            let born = self.devices.remove(&name).is_some_and(|d| d.born);
            if let Some(c) = c
                && self.born
                && born
            {
                let payload = self.payload(Vec::new());
                let topic = self.topics.device_topic(Kind::DDeath, &name);
                let _ = self.publish(c, topic, payload, Kind::DDeath);
            }
        }
    }

    /// A payload with the next seq.
    fn payload(&mut self, metrics: Vec<Metric>) -> Payload {
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
    fn publish(
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

    /// The NDEATH of the current bdSeq (no seq: Sparkplug 3.0).
    fn ndeath(&self) -> Vec<u8> {
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

    /// Follows the status events of every bus the plant has now.
    fn follow_buses(&mut self) {
        for f in self.forwarders.drain(..) {
            f.abort();
        }
        let now = self.control.plant().now();
        self.followed = Some(now.version());
        for bus in now.buses() {
            let mut rx = bus.handle.subscribe();
            let tx = self.bus_tx.clone();
            self.forwarders.push(tokio::spawn(async move {
                loop {
                    match rx.recv().await {
                        Ok(event) => {
                            if tx.send(event).await.is_err() {
                                break;
                            }
                        }
                        // Lost statuses are made up by the next one (the
                        // changes are against what was last published).
                        Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                        Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                    }
                }
            }));
        }
    }
}

/// Why a connection ended.
enum End {
    /// The primary host went offline: reconnect at once, births wait.
    HostOffline,
    /// An error, in words: reconnect after the backoff.
    Error(String),
}

fn open_session(control: &Control, config: &MqttConfig) -> SessionGuard {
    control
        .open_session(
            SESSION_CLOSING,
            Some(CommLoss {
                after: config.comm_loss(),
                action: config.comm_loss_action,
                face: Face::Mqtt,
            }),
        )
        .0
}

fn now_ms() -> u64 {
    ms_of(SystemTime::now())
}

fn ms_of(t: SystemTime) -> u64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}
