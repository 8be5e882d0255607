//! The JSON format's task: one MQTT 5 connection and everything said on
//! it, in the order it was decided.
//!
//! - **State.** `<prefix>/state` is `online` (retained) once the broker
//!   accepted the connection, and `offline` (retained) as the will and at
//!   a clean stop.
//! - **Status.** Each polled status of a drive is published, retained, on
//!   `<prefix>/<drive>/status` as the API's status JSON (with its
//!   `freshness`); at each connection every drive's latest status is
//!   published again, and again whenever its freshness changes (the bus
//!   down, the drive offline), so the retained copy never passes for live.
//! - **Events.** A drive answering again or not, its data's freshness, the
//!   news of the lease on it and its alarms, on `<prefix>/<drive>/event`,
//!   as the stream sends them (a bus-wide alarm on `<prefix>/event`).
//! - **Commands** on `<prefix>/<drive>/command` are the stream's command
//!   messages; each runs through the control core (face `mqtt`, the role of
//!   `[mqtt] commands`) in a task of its own and its reply (the result, or
//!   the problem in the API's words) goes to the MQTT 5 response topic with
//!   the correlation data, or to `<prefix>/<drive>/reply`. Only live ones:
//!   a retained command, or one queued for an earlier session, is refused
//!   by the core (audited) and answered with a `not-live` problem.
//! - **The session's lease**, as for Sparkplug's commands: renewed a few
//!   times per `comm_loss_ms` while connected, so losing the broker for
//!   longer ends the leases of MQTT's setpoints with `comm_loss_action`.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use bytes::Bytes;
use rumqttc::v5::mqttbytes::QoS;
use rumqttc::v5::mqttbytes::v5::{ConnectReturnCode, Packet, PublishProperties};
use rumqttc::v5::{AsyncClient, Event};
use serde_json::Value;
use tokio::sync::{broadcast, mpsc};
use tokio::task::JoinHandle;
use tokio::time::sleep_until;
use tokio_util::sync::CancellationToken;

use super::connection::Connection;
use super::topics::JsonTopics;
use crate::bus::SourceId;
use crate::bus::cache::BusEvent;
use crate::config::MqttConfig;
use crate::control::live::Delivery;
use crate::control::{
    Caller, CommLoss, Control, ControlEvent, Face, Failure, Published, SessionGuard,
};
use crate::faces_shared::command_messages::{self, CommandMessage, DRIVE_OPS};
use crate::faces_shared::messages::{self, DriveMessage};
use crate::faces_shared::problem::{BusContext, Problem};
use crate::faces_shared::status::{self, StatusSource};
use crate::faces_shared::target::Target;
use crate::faces_shared::writes;
use crate::metrics::Metrics;
use crate::mqtt::arrival::Connected;
use crate::mqtt::connection::{Backoff, next_event};

/// How the session's closing reads in lease news and the audit log.
const SESSION_CLOSING: &str = "the MQTT session ended (the face stopped)";

/// A reply on its way: where, with what correlation data, what.
struct Reply {
    topic: String,
    correlation: Option<Bytes>,
    message: DriveMessage,
}

/// The JSON format's state.
struct JsonNode {
    config: Arc<MqttConfig>,
    control: Control,
    metrics: Arc<Metrics>,
    topics: JsonTopics,
    client_id: String,
    /// Who commands come from, for the audit log and lease owners.
    who: Arc<str>,
    /// Their role, from the core ([`crate::control::identity`]).
    role: crate::control::Role,
    source: SourceId,
    session: SessionGuard,
    connections: u64,
    replies_tx: mpsc::UnboundedSender<Reply>,
    bus_tx: mpsc::Sender<BusEvent>,
    forwarders: Vec<JoinHandle<()>>,
    followed: Option<u64>,
    /// Drives whose status was published (retained), to clear a drive
    /// removed from the configuration.
    published: BTreeSet<String>,
    commands: tokio::task::JoinSet<()>,
    /// What is known of the current connection, to tell a live command
    /// from a retained or queued one.
    connected: Connected,
}

/// Starts the JSON format's task; it ends after `shutdown` fired.
pub(in crate::mqtt) fn spawn(
    config: Arc<MqttConfig>,
    identity: crate::control::identity::Identity,
    node_id: String,
    control: Control,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> JoinHandle<()> {
    let prefix = config
        .topic_prefix
        .clone()
        .unwrap_or_else(|| JsonTopics::default_prefix(&node_id));
    let (replies_tx, replies_rx) = mpsc::unbounded_channel();
    let (bus_tx, bus_rx) = mpsc::channel(4096);
    let session = open_session(&control, &config);
    let node = JsonNode {
        topics: JsonTopics::new(&prefix),
        client_id: format!("drivegate-json-{node_id}"),
        who: identity.who,
        role: identity.role,
        source: SourceId::new_unique(),
        session,
        connections: 0,
        replies_tx,
        bus_tx,
        forwarders: Vec::new(),
        followed: None,
        published: BTreeSet::new(),
        commands: tokio::task::JoinSet::new(),
        connected: Connected::default(),
        config,
        control,
        metrics,
    };
    tokio::spawn(node.run(bus_rx, replies_rx, shutdown))
}

impl JsonNode {
    async fn run(
        mut self,
        mut bus_rx: mpsc::Receiver<BusEvent>,
        mut replies_rx: mpsc::UnboundedReceiver<Reply>,
        shutdown: CancellationToken,
    ) {
        self.metrics
            .mqtt()
            .configured(self.config.broker.to_string());
        self.metrics.mqtt().host(None);
        self.follow_buses();
        let mut control_rx = self.control.subscribe();
        let mut conn: Option<Connection> = None;
        let mut backoff = Backoff::new();
        let renew_every = (self.config.comm_loss() / 4).max(Duration::from_millis(20));
        let mut renew = tokio::time::interval(renew_every);
        renew.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = shutdown.cancelled() => break,
                _ = sleep_until(backoff.at()), if conn.is_none() => {
                    match Connection::open(&self.config, &self.client_id, &self.topics.state()) {
                        Ok(c) => conn = Some(c),
                        Err(why) => {
                            self.failed(&why);
                            backoff.failed();
                        }
                    }
                }
                event = next_event(&mut conn) => self.on_connection(&mut conn, event, &mut backoff),
                Some(event) = bus_rx.recv() => self.on_bus(conn.as_ref(), event),
                published = control_rx.recv() => match published {
                    Ok(p) => self.on_control(conn.as_ref(), &p),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!("MQTT: {n} control events were not published (the face fell behind)");
                    }
                    Err(broadcast::error::RecvError::Closed) => {}
                },
                Some(reply) = replies_rx.recv() => self.send_reply(conn.as_ref(), reply),
                _ = renew.tick() => {
                    if conn.as_ref().is_some_and(|c| c.accepted) {
                        self.session.active();
                    }
                    self.reconcile(conn.as_ref());
                }
            }
        }
        self.stop(conn).await;
    }

    /// An event of the connection, or its end: a connection that ended is
    /// dropped, and the next one comes after the backoff.
    fn on_connection(
        &mut self,
        conn: &mut Option<Connection>,
        event: Option<Result<Event, String>>,
        backoff: &mut Backoff,
    ) {
        let Some(c) = conn.as_mut() else { return };
        let ended = match event {
            Some(Ok(event)) => self.on_event(c, event).err(),
            Some(Err(why)) => Some(why),
            None => Some("the connection's event loop ended".to_string()),
        };
        match ended {
            Some(why) => {
                let was_accepted = c.accepted;
                *conn = None;
                self.metrics.mqtt().disconnected();
                self.failed(&why);
                if was_accepted {
                    backoff.accepted();
                }
                backoff.failed();
            }
            None if c.accepted => backoff.accepted(),
            None => {}
        }
    }

    /// At shutdown: `offline` and a clean disconnect (a connection the
    /// broker accepted).
    async fn stop(&mut self, conn: Option<Connection>) {
        if let Some(mut c) = conn
            && c.accepted
        {
            // A clean DISCONNECT suppresses the will: say offline first.
            let _ = c
                .client
                .try_publish(self.topics.state(), QoS::AtLeastOnce, true, "offline");
            self.metrics.mqtt().sent("state");
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
                tracing::warn!(
                    "MQTT: the broker did not take the offline state within 2 s at shutdown"
                );
            }
        }
        self.metrics.mqtt().disconnected();
        for f in self.forwarders.drain(..) {
            f.abort();
        }
    }

    fn failed(&self, why: &str) {
        tracing::warn!(broker = %self.config.broker, "MQTT: {why}");
        self.metrics.mqtt().connection_error(why.to_string());
    }

    /// An event of the connection; an error (in words) ends it.
    fn on_event(&mut self, c: &mut Connection, event: Event) -> Result<(), String> {
        match event {
            Event::Incoming(Packet::ConnAck(ack)) => {
                if ack.code != ConnectReturnCode::Success {
                    return Err(format!("the broker refused the connection: {:?}", ack.code));
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
                tracing::info!(broker = %self.config.broker, prefix = self.topics.prefix(), "MQTT connected (JSON)");
                c.client
                    .try_subscribe(self.topics.command_filter(), QoS::AtLeastOnce)
                    .map_err(|e| format!("cannot subscribe: {e}"))?;
                c.client
                    .try_publish(self.topics.state(), QoS::AtLeastOnce, true, "online")
                    .map_err(|e| format!("cannot queue the online state: {e}"))?;
                self.metrics.mqtt().sent("state");
                self.metrics.mqtt().born(true);
                self.all_statuses(&c.client);
            }
            Event::Incoming(Packet::SubAck(_)) => self.connected.subscribed(),
            Event::Incoming(Packet::Publish(p)) => {
                let topic = String::from_utf8_lossy(&p.topic).into_owned();
                let Some(drive) = self.topics.command_drive(&topic).map(str::to_string) else {
                    self.metrics.mqtt().received("other");
                    return Ok(());
                };
                self.metrics.mqtt().received("command");
                let delivery = self.connected.delivery(p.retain, None);
                self.on_command(drive, &p.payload, p.properties.as_ref(), delivery);
            }
            _ => {}
        }
        Ok(())
    }

    /// A command message for `drive`, delivered as `delivery`: refused at
    /// once when it is none the face takes or the core finds it not live,
    /// else run through the core (which refuses what the role of `[mqtt]
    /// commands` may not do) in a task of its own; either way a reply
    /// follows.
    fn on_command(
        &mut self,
        drive: String,
        payload: &[u8],
        props: Option<&PublishProperties>,
        delivery: Delivery,
    ) {
        let topic = props
            .and_then(|p| p.response_topic.clone())
            .unwrap_or_else(|| self.topics.reply(&drive));
        let correlation = props.and_then(|p| p.correlation_data.clone());
        let reply = |message| Reply {
            topic: topic.clone(),
            correlation: correlation.clone(),
            message,
        };
        let parsed = parse(payload, &drive);
        let role = self.role;
        let caller = Caller::new(Face::Mqtt, self.who.clone(), role, self.source)
            .in_session(Face::Mqtt, self.session.id());
        let what = match &parsed {
            Ok((_, op, Some(body))) => format!("command \"{op}\" {body}"),
            Ok((_, op, None)) => format!("command \"{op}\""),
            Err(_) => "a command message that could not be read".to_string(),
        };
        if let Err(refusal) = self.control.check_live(&caller, &drive, &what, delivery) {
            self.metrics.mqtt().command("refused");
            let id = match &parsed {
                Ok((id, ..)) | Err((id, _)) => id.clone(),
            };
            let problem = writes::problem(
                &caller,
                &Failure::Refused(refusal),
                BusContext {
                    drive: Some(&drive),
                    offline: false,
                    setpoint: false,
                },
            );
            self.send_now(reply(DriveMessage::reply(id, Err(problem))));
            return;
        }
        let (id, op, body) = match parsed {
            Ok(parsed) => parsed,
            Err((id, problem)) => {
                self.metrics.mqtt().command("malformed");
                self.send_now(reply(DriveMessage::reply(id, Err(problem))));
                return;
            }
        };
        if !command_messages::is_drive_op(&op) {
            self.metrics.mqtt().command("malformed");
            let problem = Problem::invalid(format!(
                "\"{op}\" is not an operation MQTT takes: use {DRIVE_OPS} (the REST API and the WebSocket stream offer the rest)"
            ));
            self.send_now(reply(DriveMessage::reply(id, Err(problem))));
            return;
        }
        // The core decides, as for Sparkplug's commands: `[mqtt] commands`
        // is the caller's role, and "none" a viewer's.
        self.session.active();
        let control = self.control.clone();
        let metrics = self.metrics.clone();
        let replies = self.replies_tx.clone();
        // Finished commands' handles go; the others run on.
        while self.commands.try_join_next().is_some() {}
        self.commands.spawn(async move {
            let result =
                command_messages::run_drive_op(&control, &caller, &drive, &op, body, None).await;
            metrics.mqtt().command(match &result {
                Ok(_) => "confirmed",
                Err(p) if p.status < 500 => "refused",
                Err(_) => "failed",
            });
            let _ = replies.send(Reply {
                topic,
                correlation,
                message: DriveMessage::reply(id, result),
            });
        });
    }

    /// Sends `reply` through the node's loop (from the node itself).
    fn send_now(&self, reply: Reply) {
        let _ = self.replies_tx.send(reply);
    }

    fn send_reply(&self, c: Option<&Connection>, reply: Reply) {
        let Some(c) = c.filter(|c| c.accepted) else {
            tracing::warn!(
                topic = reply.topic,
                "MQTT: a command's reply is lost: the broker connection is down"
            );
            return;
        };
        let properties = PublishProperties {
            correlation_data: reply.correlation,
            content_type: Some("application/json".to_string()),
            ..Default::default()
        };
        match c.client.try_publish_with_properties(
            reply.topic,
            QoS::AtLeastOnce,
            false,
            reply.message.to_json(),
            properties,
        ) {
            Ok(()) => self.metrics.mqtt().sent("reply"),
            Err(e) => tracing::warn!("MQTT: a command's reply was not sent: {e}"),
        }
    }

    fn on_bus(&mut self, c: Option<&Connection>, event: BusEvent) {
        let Some(c) = c.filter(|c| c.accepted) else {
            return;
        };
        match event {
            BusEvent::Status {
                bus,
                unit,
                status,
                at,
            } => {
                let Some(target) = self.drive_at(&bus, unit) else {
                    return;
                };
                let age = SystemTime::now()
                    .duration_since(at)
                    .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX));
                let reply = status::reply(&target, &status, StatusSource::Cache, at, age);
                self.publish_status(&c.client, &target.drive.name, &reply);
            }
            BusEvent::Online { bus, unit } => {
                let Some(target) = self.drive_at(&bus, unit) else {
                    return;
                };
                let message = DriveMessage::Online {
                    drive: target.drive.name.clone(),
                    bus: bus.to_string(),
                    unit,
                };
                self.publish_event(&c.client, Some(&target.drive.name), &message);
            }
            BusEvent::Offline { bus, unit, reason } => {
                let Some(target) = self.drive_at(&bus, unit) else {
                    return;
                };
                let message = DriveMessage::Offline {
                    drive: target.drive.name.clone(),
                    bus: bus.to_string(),
                    unit,
                    reason,
                };
                self.publish_event(&c.client, Some(&target.drive.name), &message);
            }
            BusEvent::BusUp { .. } | BusEvent::BusDown { .. } => {}
        }
    }

    fn on_control(&mut self, c: Option<&Connection>, published: &Published) {
        let Some(c) = c.filter(|c| c.accepted) else {
            return;
        };
        match published.event.as_ref() {
            ControlEvent::Lease(lease) => {
                if let Some((drive, message)) = messages::of_lease(self.control.plant(), lease) {
                    self.publish_event(&c.client, Some(&drive), &message);
                }
            }
            ControlEvent::Alarm(news) => {
                let (drive, message) = messages::of_alarm(news);
                self.publish_event(&c.client, drive.as_deref(), &message);
            }
            ControlEvent::Freshness(news) => {
                let plant = self.control.plant().clone();
                let Some((drive, message)) = messages::of_freshness(&plant, news) else {
                    return;
                };
                self.publish_event(&c.client, Some(&drive), &message);
                // The retained status says it too: a client that comes
                // later must not take the last value for a live one.
                if let Some(target) = Target::at(&plant, news.drive)
                    && let Ok(reply) = status::cached(&target)
                {
                    self.publish_status(&c.client, &drive, &reply);
                }
            }
            _ => {}
        }
    }

    fn publish_status(
        &mut self,
        client: &AsyncClient,
        drive: &str,
        reply: &crate::faces_shared::status::StatusReply,
    ) {
        let Ok(json) = serde_json::to_string(reply) else {
            return;
        };
        match client.try_publish(self.topics.status(drive), QoS::AtMostOnce, true, json) {
            Ok(()) => {
                self.metrics.mqtt().sent("status");
                self.published.insert(drive.to_string());
            }
            Err(e) => tracing::warn!("MQTT: a status of {drive} was not sent: {e}"),
        }
    }

    /// `message` on `drive`'s event topic, or the gateway's (`None`: a
    /// bus-wide alarm).
    fn publish_event(&self, client: &AsyncClient, drive: Option<&str>, message: &DriveMessage) {
        let topic = drive.map_or_else(|| self.topics.gateway_event(), |d| self.topics.event(d));
        let drive = drive.unwrap_or("the gateway");
        match client.try_publish(topic, QoS::AtLeastOnce, false, message.to_json()) {
            Ok(()) => self.metrics.mqtt().sent("event"),
            Err(e) => tracing::warn!("MQTT: an event of {drive} was not sent: {e}"),
        }
    }

    /// Every drive's latest status, at a new connection.
    fn all_statuses(&mut self, client: &AsyncClient) {
        let plant = self.control.plant().clone();
        for index in 0..plant.now().drive_slots() {
            let Some(target) = Target::at(&plant, index) else {
                continue;
            };
            if let Ok(reply) = status::cached(&target) {
                self.publish_status(client, &target.drive.name, &reply);
            }
        }
    }

    /// The configured drive at `unit` of bus `bus`, now.
    fn drive_at(&self, bus: &str, unit: u8) -> Option<Target> {
        let plant = self.control.plant();
        let now = plant.now();
        let index = now
            .indexed_buses()
            .find(|(_, b)| b.handle.name() == bus)
            .map(|(i, _)| i)?;
        let slot = now
            .indexed_drives()
            .find(|(_, d)| d.bus == index && d.unit == unit)
            .map(|(i, _)| i)?;
        Target::at(plant, slot)
    }

    /// Follows the plant's changes: the buses as they are now, and the
    /// retained status of a drive no longer configured cleared.
    fn reconcile(&mut self, c: Option<&Connection>) {
        let plant = self.control.plant().now();
        if self.followed == Some(plant.version()) {
            return;
        }
        self.follow_buses();
        let Some(c) = c.filter(|c| c.accepted) else {
            return;
        };
        let gone: Vec<String> = self
            .published
            .iter()
            .filter(|name| !plant.drives().any(|d| &d.name == *name))
            .cloned()
            .collect();
        for name in gone {
            // An empty retained message removes the retained one.
            if c.client
                .try_publish(self.topics.status(&name), QoS::AtLeastOnce, true, "")
                .is_ok()
            {
                self.published.remove(&name);
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
                        // The next status replaces a lost one.
                        Err(broadcast::error::RecvError::Lagged(_)) => {}
                        Err(broadcast::error::RecvError::Closed) => break,
                    }
                }
            }));
        }
    }
}

/// A command message for `drive` read from `payload`: its id, op and
/// body, or the id (if one could be read) and what is wrong.
fn parse(payload: &[u8], drive: &str) -> Result<(Value, String, Option<Value>), (Value, Problem)> {
    let hint = "send {\"type\":\"command\",\"id\":1,\"op\":\"activate\"} or {\"type\":\"command\",\"id\":2,\"op\":\"setpoint\",\"body\":{\"speed_rpm\":100}}";
    let value: Value = serde_json::from_slice(payload).map_err(|e| {
        (
            Value::Null,
            Problem::invalid(format!("not a JSON command message: {e}; {hint}")),
        )
    })?;
    // The id, when there is one, is echoed even when the rest is wrong.
    let id = value.get("id").cloned().unwrap_or(Value::Null);
    let message: CommandMessage = serde_json::from_value(value).map_err(|e| {
        (
            id.clone(),
            Problem::invalid(format!("not a valid command message: {e}; {hint}")),
        )
    })?;
    let CommandMessage::Command {
        id,
        op,
        drive: named,
        body,
    } = message;
    if let Some(named) = named
        && named != drive
    {
        return Err((
            id,
            Problem::invalid(format!(
                "the message names drive \"{named}\" on the command topic of \"{drive}\": leave \"drive\" out, or send it to the drive's own topic"
            )),
        ));
    }
    Ok((id, op, body))
}

fn now_ms() -> u64 {
    crate::control::journal::format::unix_ms(SystemTime::now())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_command_message_is_read_with_its_id() {
        let (id, op, body) = parse(
            br#"{"type":"command","id":"a7","op":"setpoint","body":{"speed_rpm":100}}"#,
            "conveyor",
        )
        .unwrap();
        assert_eq!((id, op.as_str()), (Value::from("a7"), "setpoint"));
        assert_eq!(body, Some(serde_json::json!({"speed_rpm": 100})));
        // The drive may be named, if it is the topic's.
        assert!(
            parse(
                br#"{"type":"command","op":"brake","drive":"conveyor"}"#,
                "conveyor"
            )
            .is_ok()
        );
    }

    #[test]
    fn malformed_messages_say_what_is_wrong_and_keep_the_id() {
        let (id, p) = parse(b"{not json", "conveyor").unwrap_err();
        assert_eq!(id, Value::Null);
        assert!(
            p.detail.starts_with("not a JSON command message"),
            "{}",
            p.detail
        );
        let (id, p) = parse(br#"{"type":"command","id":9}"#, "conveyor").unwrap_err();
        assert_eq!(id, Value::from(9));
        assert!(p.detail.contains("missing field `op`"), "{}", p.detail);
        let (_, p) = parse(br#"{"type":"dance","id":1}"#, "conveyor").unwrap_err();
        assert!(p.detail.contains("dance"), "{}", p.detail);
        let (_, p) = parse(
            br#"{"type":"command","id":1,"op":"brake","drive":"lift"}"#,
            "conveyor",
        )
        .unwrap_err();
        assert!(p.detail.contains("\"lift\""), "{}", p.detail);
        let (_, p) = parse(b"\xff\xfe", "conveyor").unwrap_err();
        assert_eq!(p.status, 400);
    }
}
