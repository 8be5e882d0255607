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
//!   and is published. Only live ones: a retained DCMD or NCMD, or one
//!   queued for an earlier session, is refused by the core (audited) and
//!   answered in `command/last_result` ([`super::arrival`]).
//! - **The session's lease.** While connected (and the primary host is
//!   online), the session is renewed a few times per `comm_loss_ms`; once
//!   the connection is lost, its leases end after `comm_loss_ms` with
//!   `comm_loss_action`. The host's `STATE` offline ends them at once (the
//!   session closes), and the node publishes its NDEATH and reconnects, as
//!   Sparkplug 3.0 asks of an edge node whose primary host went away.
//!
//! The loop is here; what it does on each wake-up is in the files named
//! for it: [`incoming`] (what the broker sends), [`births`], [`data`],
//! [`dcmd`] (hosts' commands and their results) and [`freshness`].

mod births;
mod command_result;
mod data;
mod dcmd;
mod freshness;
mod incoming;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use rumqttc::{Event, LastWill, QoS};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::{Instant, sleep_until};
use tokio_util::sync::CancellationToken;

use super::bd_seq::BdSeq;
use super::connection::{Backoff, Connection, next_event};
use super::exception::Reported;
use super::host::Host;
use super::metric::Setpoints;
use super::outbox::Outbox;
use super::relay::TooLarge;
use super::replay::{self, Held};
use super::topic::{Kind, NodeTopics};
use crate::bus::SourceId;
use crate::bus::cache::BusEvent;
use crate::bus::handle::PortState;
use crate::config::MqttConfig;
use crate::control::{CommLoss, Control, Face, SessionGuard};
use crate::metrics::Metrics;
use command_result::CommandResult;

/// The QoS of births and data (Sparkplug: 0); the NDEATH, as the will
/// and at a clean stop, goes with 1.
const DATA_QOS: QoS = QoS::AtMostOnce;

/// How often kept data is replayed, and how many messages at a time.
const REPLAY_EVERY: Duration = Duration::from_millis(20);
const REPLAY_BATCH: usize = 8;

/// How the session's closing reads in lease news and the audit log.
const SESSION_CLOSING: &str =
    "the MQTT session ended (the primary host went offline, or the face stopped)";

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
    /// Their role, from the core ([`crate::control::identity`]).
    role: crate::control::Role,
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
    /// Messages cut for their size, for all connections.
    too_large: Arc<TooLarge>,
    /// What is known of the current connection, to tell a live command
    /// from a retained or queued one.
    connected: super::arrival::Connected,
}

/// Starts the edge node's task; it ends after `shutdown` fired.
#[allow(clippy::too_many_arguments)]
pub(super) fn spawn(
    config: Arc<MqttConfig>,
    identity: crate::control::identity::Identity,
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
    let who = identity.who;
    let session = open_session(&control, &config);
    let node = Node {
        topics,
        who: who.clone(),
        role: identity.role,
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
        too_large: TooLarge::new(metrics.clone(), who.clone(), &config),
        connected: super::arrival::Connected::default(),
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
        let mut backoff = Backoff::new();
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
                _ = sleep_until(backoff.at()), if conn.is_none() => {
                    match self.connect() {
                        Ok(c) => conn = Some(c),
                        Err(why) => {
                            self.failed(&why);
                            backoff.failed();
                        }
                    }
                }
                event = next_event(&mut conn) => self.on_connection(&mut conn, event, &mut backoff),
                Some(event) = bus_rx.recv() => self.on_bus(conn.as_ref(), event),
                Some(result) = results_rx.recv() => self.on_result(conn.as_ref(), result),
                published = control_rx.recv() => self.on_control(conn.as_ref(), published),
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
        self.stop(conn).await;
    }

    /// An event of the connection, or its end. A connection that ended is
    /// gone with its bdSeq; the next one comes at once when the primary
    /// host went offline, else after the backoff.
    fn on_connection(
        &mut self,
        conn: &mut Option<Connection>,
        event: Option<Result<Event, String>>,
        backoff: &mut Backoff,
    ) {
        let (end, was_accepted) = match event {
            Some(Ok(event)) => {
                let Some(c) = conn.as_mut() else { return };
                match self.on_event(c, event) {
                    Ok(()) => {
                        if c.accepted {
                            backoff.accepted();
                        }
                        return;
                    }
                    Err(end) => (end, c.accepted),
                }
            }
            Some(Err(why)) => (End::Error(why), false),
            None => (
                End::Error("the connection's event loop ended".to_string()),
                false,
            ),
        };
        *conn = None;
        self.lost();
        match end {
            End::HostOffline => backoff.at_once(),
            End::Error(why) => {
                self.failed(&why);
                if was_accepted {
                    backoff.accepted();
                }
                backoff.failed();
            }
        }
        self.bd_seq.next();
    }

    /// At shutdown: the NDEATH and a clean disconnect (a connection the
    /// broker accepted), and what is kept back to the store.
    async fn stop(&mut self, conn: Option<Connection>) {
        if let Some(mut c) = conn
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
            &self.too_large,
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
