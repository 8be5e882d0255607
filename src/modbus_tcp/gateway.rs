//! Turns one Modbus TCP request into work and the work's result into the
//! reply PDU: routing by unit id, the Modbus shape rules, the polled copy,
//! broadcasts, gateway exceptions and metrics.
//!
//! Reads go to the bus as they came. Writes go through the control core
//! ([`crate::control`]), decoded into what they mean for the drive: the
//! core checks the client's role (from its network), the still-check and
//! the other rules, keeps the leases and the brake, sends, and audits;
//! this module renders its decision as the drive's own reply or an
//! exception (see [`super::outcome`]).
//!
//! The connection (see [`super::connection`]) decides *when* replies go out;
//! this module decides *what* they are.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tracing::{debug, warn};

use super::access::Rights;
use super::outcome::{Outcome, exception_pdu, failure_reply};
pub use super::pending::{Pending, ReadState};
use super::polled_copy;
use super::request;
use super::routing::{BusUnits, UnitRoutes};
use crate::bus::handle::JobOptions;
use crate::bus::{BusHandle, Origin, Priority, SourceId};
use crate::config::ModbusTcpConfig;
use crate::control::{self, Caller, Control, ControlRequest, Face, SessionId, Target, Write};
use crate::drive::writes;
use crate::metrics::Metrics;
use crate::modbus::ExceptionCode;
use crate::plant::Plant;

/// One connected client.
#[derive(Debug, Clone)]
pub struct Client {
    /// Its address: who it is in the audit log.
    pub peer: SocketAddr,
    /// Who it is to the control core: its address, the role of its
    /// network, and its source id (the bus queue takes turns between
    /// sources, so one connection flooding requests cannot starve the
    /// others).
    pub caller: Caller,
    /// Writes that need standstill go even while the motor turns.
    pub allow_saves_while_moving: bool,
    /// Its name, if it has one: the CN of its certificate.
    pub name: Option<Arc<String>>,
}

impl Client {
    /// A new client at `peer` with `rights` in `session` (its connection),
    /// with a source id of its own.
    pub fn new(peer: SocketAddr, rights: Rights, session: SessionId) -> Self {
        Self::named(peer, None, rights, session)
    }

    /// A new client called `name` (the CN of its certificate), which the
    /// audit log and the bus monitor show with its address.
    pub fn named(
        peer: SocketAddr,
        name: Option<Arc<String>>,
        rights: Rights,
        session: SessionId,
    ) -> Self {
        let who = match &name {
            Some(name) => format!("{name} ({peer})"),
            None => peer.to_string(),
        };
        Self {
            peer,
            caller: Caller::new(Face::ModbusTcp, who, rights.role, SourceId::new_unique())
                .in_session(Face::ModbusTcp, session)
                .with_origin(Origin::modbus_tcp_named(peer, name.clone(), 0)),
            allow_saves_while_moving: rights.allow_saves_while_moving,
            name,
        }
    }

    /// The origin of its request `transaction`, for the bus monitor.
    fn origin(&self, transaction: u16) -> Origin {
        Origin::modbus_tcp_named(self.peer, self.name.clone(), transaction)
    }
}

/// What to do about one request.
#[derive(Debug)]
pub enum Answer {
    /// Reply with this PDU (already decided and counted).
    Now(Vec<u8>),
    /// Send nothing (a broadcast without reply).
    Silent,
    /// Wait for the bus.
    Pending(Pending),
}

/// The routing and policy of one listener.
pub struct Gateway {
    plant: Arc<Plant>,
    control: Control,
    metrics: Arc<Metrics>,
    /// `[modbus_tcp]` as last applied (a reload replaces it).
    config: std::sync::RwLock<ModbusTcpConfig>,
    /// The tables of the plant as it was when they were built.
    tables: std::sync::RwLock<Arc<Tables>>,
    /// The running configuration: a reload's `[modbus_tcp]` applies from
    /// the next request on.
    follower: crate::control::reload::ConfigFollower,
}

/// What the unit map and the polled copy make of the plant: built again
/// when the plant or `[modbus_tcp]` changes, so a drive a reload adds is
/// reachable at once and one it removes is not.
struct Tables {
    /// The plant's version these are for.
    version: u64,
    routes: UnitRoutes,
    /// Maximum age of the polled copy per bus slot (`None`: strict passthrough).
    polled_copy: Vec<Option<Duration>>,
    broadcast_reply: bool,
    /// Function codes the core cannot decode that admins may send
    /// unchecked (`raw_functions`).
    raw_functions: Vec<u8>,
}

impl Tables {
    fn build(config: &ModbusTcpConfig, plant: &Plant) -> (Tables, Vec<String>) {
        let now = plant.now();
        // One entry per bus slot, a removed bus as one with no name.
        let buses: Vec<BusUnits> = (0..now.bus_slots())
            .map(|i| match now.bus_at(i) {
                Some(b) => BusUnits {
                    name: b.handle.name().to_string(),
                    units: b.config.drives.iter().map(|d| d.unit()).collect(),
                },
                None => BusUnits {
                    name: String::new(),
                    units: Vec::new(),
                },
            })
            .collect();
        let (routes, warnings) = UnitRoutes::build(&config.unit_map, &buses);
        let polled_copy = buses
            .iter()
            .map(|b| {
                config
                    .polled_copy
                    .iter()
                    .find(|p| p.bus.get_ref() == &b.name)
                    .map(|p| p.max_age())
            })
            .collect();
        let tables = Tables {
            version: now.version(),
            routes,
            polled_copy,
            broadcast_reply: config.broadcast_reply,
            raw_functions: config
                .raw_functions
                .iter()
                .map(|f| f.get_ref().code())
                .collect(),
        };
        (tables, warnings)
    }
}

impl Gateway {
    /// The gateway for `config` over `plant`, writing through `control`;
    /// warns about unreachable units.
    pub fn new(
        config: &ModbusTcpConfig,
        plant: Arc<Plant>,
        control: Control,
        metrics: Arc<Metrics>,
    ) -> Self {
        let (tables, warnings) = Tables::build(config, &plant);
        for w in warnings {
            warn!("{w}");
        }
        Self {
            plant,
            follower: crate::control::reload::ConfigFollower::new(&control),
            control,
            metrics,
            config: std::sync::RwLock::new(config.clone()),
            tables: std::sync::RwLock::new(Arc::new(tables)),
        }
    }

    /// Applies a reloaded `[modbus_tcp]`: its unit map, polled copies and
    /// broadcast replies from the next request on.
    pub fn set_config(&self, config: &ModbusTcpConfig) {
        *self.config.write().unwrap_or_else(|p| p.into_inner()) = config.clone();
        self.rebuild();
    }

    fn rebuild(&self) -> Arc<Tables> {
        let config = self.config.read().unwrap_or_else(|p| p.into_inner());
        let (tables, warnings) = Tables::build(&config, &self.plant);
        for w in warnings {
            warn!("{w}");
        }
        let tables = Arc::new(tables);
        *self.tables.write().unwrap_or_else(|p| p.into_inner()) = tables.clone();
        tables
    }

    /// The tables for the plant as it is now.
    fn tables(&self) -> Arc<Tables> {
        if let Some(config) = self.follower.changed() {
            self.set_config(&config.modbus_tcp);
        }
        let tables = self
            .tables
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        if tables.version == self.plant.now().version() {
            tables
        } else {
            self.rebuild()
        }
    }

    /// The metrics this gateway counts into.
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// The control core its writes go through.
    pub fn control(&self) -> &Control {
        &self.control
    }

    /// Decides what to do with `pdu` sent by `client` to `unit` in MBAP
    /// transaction `transaction`, received at `received`. Requests that go
    /// to the bus are queued before this returns (writes that need the
    /// drive's state read first, after that read), so pipelined requests
    /// keep their order and wait in the bus queue, not in the socket. A
    /// write waits for the bus at most `queue_timeout_ms` from
    /// `received`, its wait behind a full pipeline included.
    pub async fn handle(
        &self,
        client: &Client,
        (transaction, unit): (u16, u8),
        pdu: Vec<u8>,
        received: Instant,
    ) -> Answer {
        if pdu.is_empty() {
            // The MBAP codec never yields one; answer rather than panic.
            return Answer::Now(exception_pdu(0, ExceptionCode::ILLEGAL_FUNCTION));
        }
        if unit == 0 {
            return self.broadcast(client, transaction, pdu, received).await;
        }
        let tables = self.tables();
        let Some(route) = tables.routes.route(unit) else {
            return self.refuse(
                client,
                ("-", unit),
                &pdu,
                ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
                Outcome::PathUnavailable,
                format!("unit {unit} is not on any configured bus"),
            );
        };
        let function = pdu[0];
        let Some(bus) = self.plant.now().bus_at(route.bus).map(|b| b.handle.clone()) else {
            return self.refuse(
                client,
                ("-", unit),
                &pdu,
                ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
                Outcome::PathUnavailable,
                format!("unit {unit} is on a bus that is no longer configured"),
            );
        };
        let bus = &bus;
        if let Err(code) = request::check_shape(&pdu) {
            return self.refuse(
                client,
                (bus.name(), route.unit),
                &pdu,
                code,
                Outcome::Invalid,
                "refused: the request's length or quantity does not fit its function code"
                    .to_string(),
            );
        }
        // The bus monitor shows this request's frames as the client's,
        // with its transaction id.
        let caller = client.caller.with_origin(client.origin(transaction));
        if !request::reads_only(&pdu) {
            let target = self.control.unit_target(route.bus, route.unit);
            let unchecked = tables.raw_functions.contains(&function);
            return self
                .write(client, &caller, (target, bus), pdu, (unchecked, received))
                .await;
        }
        // The copy only while the drive's data is live (judged after the
        // snapshot is taken): a bus that went down or a drive whose polls
        // are missing is read from the bus, which answers 0x0A or 0x0B.
        if let Some(max_age) = tables.polled_copy.get(route.bus).copied().flatten()
            && let Some(snapshot) = bus.drive(route.unit)
            && let Some(freshness) = bus.freshness(route.unit)
            && let Some(reply) = polled_copy::answer(&pdu, &snapshot, &freshness, max_age)
        {
            self.count(function, Outcome::Cached);
            return Answer::Now(reply);
        }
        let state = ReadState::submit(bus, route.unit, pdu.clone(), job_options(&caller));
        Answer::Pending(Pending::Read { pdu, state })
    }

    /// A write to one unit, handed to the control core: decoded with the
    /// drive's register table when the unit is a configured drive, else as
    /// a device's. A read/write multiple to a drive is its write through
    /// the core, then its read: the read is queued once the drive confirmed
    /// the write, before this returns, so a request the client pipelined
    /// after it cannot come between the two.
    async fn write(
        &self,
        client: &Client,
        caller: &Caller,
        (target, bus): (Target, &BusHandle),
        pdu: Vec<u8>,
        (unchecked, received): (bool, Instant),
    ) -> Answer {
        let function = pdu[0];
        let (write, then_read) = if target.drive.is_some() {
            (Write::pdu(pdu.clone()), writes::read_after(&pdu))
        } else {
            (Write::device_pdu(pdu.clone()), None)
        };
        let request = ControlRequest::new(write)
            .forced(client.allow_saves_while_moving)
            .unchecked(unchecked)
            .received(received);
        let failure = match self.control.submit(caller, target, request).await {
            Ok(pending) => {
                let Some(read) = then_read else {
                    return Answer::Pending(Pending::writes(&pdu, false, vec![pending]));
                };
                match written(pending).await {
                    // The reply is the read's, under the client's function.
                    Ok(()) => {
                        let state = ReadState::submit(bus, target.unit, read, job_options(caller));
                        return Answer::Pending(Pending::Read { pdu, state });
                    }
                    Err(failure) => failure,
                }
            }
            Err(failure) => failure,
        };
        let (reply, outcome) = failure_reply(function, &failure);
        self.count(function, outcome);
        Answer::Now(reply)
    }

    /// Unit 0: every bus the listener reaches, no reply waited for.
    async fn broadcast(
        &self,
        client: &Client,
        transaction: u16,
        pdu: Vec<u8>,
        received: Instant,
    ) -> Answer {
        let function = pdu[0];
        let tables = self.tables();
        let refusal = if !request::broadcastable(&pdu) {
            Some((
                ExceptionCode::ILLEGAL_FUNCTION,
                Outcome::Refused,
                "refused: a read (and read/write multiple, which reads) cannot be broadcast: nobody would answer it",
            ))
        } else if let Err(code) = request::check_shape(&pdu) {
            Some((
                code,
                Outcome::Invalid,
                "refused: the request's length or quantity does not fit its function",
            ))
        } else if tables.routes.broadcast_buses().is_empty() {
            Some((
                ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
                Outcome::PathUnavailable,
                "no bus is reachable through this listener",
            ))
        } else {
            None
        };
        if let Some((code, outcome, why)) = refusal {
            let answer = self.refuse(client, ("all", 0), &pdu, code, outcome, why.to_string());
            return self.reply_to_broadcast(answer);
        }
        let caller = client.caller.with_origin(client.origin(transaction));
        let mut writes = Vec::new();
        for &bus in tables.routes.broadcast_buses() {
            let target = self.control.unit_target(bus, 0);
            let request = ControlRequest::new(Write::pdu(pdu.clone()))
                .forced(client.allow_saves_while_moving)
                .unchecked(tables.raw_functions.contains(&function))
                .received(received);
            match self.control.submit(&caller, target, request).await {
                Ok(pending) => writes.push(pending),
                Err(failure) => {
                    // The first bus that refuses answers for all; what went
                    // out on the others already is settled as they end.
                    let (reply, outcome) = failure_reply(function, &failure);
                    self.count(function, outcome);
                    return self.reply_to_broadcast(Answer::Now(reply));
                }
            }
        }
        let mut pending = Pending::writes(&pdu, true, writes);
        if tables.broadcast_reply {
            return Answer::Pending(pending);
        }
        // Nobody waits for a broadcast: it goes out even if the client
        // closes right after sending it, and its result is still audited.
        let metrics = self.metrics.clone();
        tokio::spawn(async move {
            pending.wait().await;
            let _ = pending.finish(&metrics);
        });
        Answer::Silent
    }

    /// A broadcast is answered only when the listener is set to.
    fn reply_to_broadcast(&self, answer: Answer) -> Answer {
        if self.tables().broadcast_reply {
            answer
        } else {
            Answer::Silent
        }
    }

    /// Answers at once with `code` a request the gateway cannot route or
    /// whose shape is wrong (audited when it was a write).
    fn refuse(
        &self,
        client: &Client,
        (bus, unit): (&str, u8),
        pdu: &[u8],
        code: ExceptionCode,
        outcome: Outcome,
        why: String,
    ) -> Answer {
        let function = pdu.first().copied().unwrap_or(0);
        self.count(function, outcome);
        if !request::reads_only(pdu) {
            control::audit::refused_by_face(
                client.caller.face.name(),
                &client.caller.who,
                bus,
                unit,
                &Write::pdu(pdu.to_vec()),
                &format!("{why}; answered {code}"),
            );
        } else {
            debug!(client = %client.peer, unit, "{why}; answered {code}");
        }
        Answer::Now(exception_pdu(function, code))
    }

    fn count(&self, function: u8, outcome: Outcome) {
        self.metrics.faces().tcp_request(function, outcome.label());
    }
}

/// Waits for a write and settles it: `Ok` once the drive confirmed it.
async fn written(mut pending: control::Pending) -> Result<(), control::Failure> {
    pending.wait().await;
    pending.finish().map(|_| ())
}

/// The bus job options of a client's request: its turn in the queue, its
/// origin on the bus monitor.
fn job_options(caller: &Caller) -> JobOptions {
    JobOptions {
        priority: Priority::Command,
        source: caller.source,
        queue_timeout: None,
        max_attempts: None,
        origin: caller.origin.clone(),
    }
}

#[cfg(test)]
mod tests {
    //! The gateway's own decisions, on a plant with no bus: what it answers
    //! before anything reaches the bus or the core (an empty PDU, a unit no
    //! bus has, a broadcast it cannot send), how a bus result becomes the
    //! reply, and what it counts. The path through the bus and the core is
    //! tested end to end in `tests/modbus_tcp/` and `tests/control/`.

    use std::time::Duration;

    use tokio_util::sync::CancellationToken;

    use super::*;
    use crate::bus::BusError;
    use crate::bus::job::{Exchange, JobResult};
    use crate::config::Config;
    use crate::control::Role;
    use crate::modbus_tcp::access::Rights;
    use crate::modbus_tcp::pending::answer_ok;

    fn gateway(broadcast_reply: bool) -> Gateway {
        let mut config = Config::embedded_default().expect("the built-in config");
        config.buses.clear();
        config.modbus_tcp.unit_map.clear();
        config.modbus_tcp.broadcast_reply = broadcast_reply;
        let plant = Arc::new(Plant::start(&config).expect("a plant with no bus"));
        let control = Control::start(plant.clone(), &config.safety, CancellationToken::new());
        let metrics = Metrics::new(plant.clone());
        Gateway::new(&config.modbus_tcp, plant, control, metrics)
    }

    fn client(role: Role) -> Client {
        let rights = Rights {
            role,
            allow_saves_while_moving: false,
            comm_loss: None,
        };
        Client::new(
            SocketAddr::from(([127, 0, 0, 1], 50_000)),
            rights,
            SessionId::new_unique(),
        )
    }

    /// The count of `function` with `outcome` in the metrics.
    fn counted(gateway: &Gateway, function: &str, outcome: &str) -> bool {
        let series = format!(
            "drivegate_modbus_tcp_requests_total{{function=\"{function}\",outcome=\"{outcome}\"}} 1"
        );
        gateway.metrics().render().lines().any(|l| l == series)
    }

    fn now(answer: Answer) -> Vec<u8> {
        match answer {
            Answer::Now(pdu) => pdu,
            other => panic!("expected an answer now, got {other:?}"),
        }
    }

    #[tokio::test]
    async fn an_empty_pdu_is_an_illegal_function_not_a_panic() {
        let g = gateway(false);
        assert_eq!(
            now(g
                .handle(&client(Role::Admin), (1, 1), Vec::new(), Instant::now())
                .await),
            [0x80, 0x01]
        );
    }

    #[tokio::test]
    async fn a_unit_on_no_bus_is_path_unavailable_and_counted() {
        let g = gateway(false);
        // A read of the status block, and a write, to unit 7.
        let read = vec![0x03, 0x00, 0xC0, 0x00, 0x07];
        assert_eq!(
            now(g
                .handle(&client(Role::Viewer), (1, 7), read, Instant::now())
                .await),
            [0x83, 0x0A]
        );
        assert!(counted(&g, "0x03", "path_unavailable"));
        let write = vec![0x06, 0x00, 0x02, 0x00, 0x05];
        assert_eq!(
            now(g
                .handle(&client(Role::Admin), (2, 7), write, Instant::now())
                .await),
            [0x86, 0x0A]
        );
        assert!(counted(&g, "0x06", "path_unavailable"));
    }

    #[tokio::test]
    async fn a_broadcast_is_answered_only_when_the_listener_says_so() {
        // A read cannot be broadcast: nobody would answer it.
        let read = vec![0x03, 0x00, 0xC0, 0x00, 0x07];
        let silent = gateway(false);
        assert!(matches!(
            silent
                .handle(&client(Role::Admin), (1, 0), read.clone(), Instant::now())
                .await,
            Answer::Silent
        ));
        assert!(counted(&silent, "0x03", "refused"));
        let answering = gateway(true);
        assert_eq!(
            now(answering
                .handle(&client(Role::Admin), (1, 0), read, Instant::now())
                .await),
            [0x83, 0x01]
        );
        // A write of the wrong length, and a write with no bus to go to.
        let short = vec![0x10, 0x00, 0x24, 0x00, 0x02, 0x04, 0x00];
        assert_eq!(
            now(answering
                .handle(&client(Role::Admin), (2, 0), short, Instant::now())
                .await),
            [0x90, 0x03]
        );
        let brake = vec![0x06, 0x00, 0x02, 0x00, 0x05];
        assert_eq!(
            now(answering
                .handle(&client(Role::Admin), (3, 0), brake, Instant::now())
                .await),
            [0x86, 0x0A]
        );
    }

    #[tokio::test]
    async fn a_reads_bus_result_becomes_its_reply() {
        let g = gateway(false);
        let read = vec![0x03, 0x00, 0xC0, 0x00, 0x01];
        let exchange = |reply: Vec<u8>| Exchange {
            reply,
            attempts: 1,
            queued: Duration::ZERO,
            on_wire: Duration::ZERO,
        };
        let finished = |result: JobResult| {
            Pending::Read {
                pdu: read.clone(),
                state: ReadState::Done(result),
            }
            .finish(g.metrics())
        };
        // The drive's reply, and its exception, go back as they came.
        assert_eq!(
            finished(Ok(exchange(vec![0x03, 0x02, 0x00, 0x10]))),
            [0x03, 0x02, 0x00, 0x10]
        );
        assert_eq!(finished(Ok(exchange(vec![0x83, 0x02]))), [0x83, 0x02]);
        assert!(counted(&g, "0x03", "exception"));
        // No answer from the drive: the gateway's target failed (0x0B).
        let timeout = BusError::Timeout {
            unit: 2,
            attempts: 2,
            timeout_ms: 50,
        };
        assert_eq!(finished(Err(timeout)), [0x83, 0x0B]);
        assert!(counted(&g, "0x03", "gateway_timeout"));
        // Writes with no bus to go to: path unavailable.
        let none = Pending::writes(&[0x06, 0x00, 0x02, 0x00, 0x05], true, Vec::new());
        assert_eq!(none.finish(g.metrics()), [0x86, 0x0A]);
    }

    #[test]
    fn the_first_failure_of_a_broadcast_is_what_the_client_hears() {
        let ok = Some((vec![0x06], Outcome::Ok));
        assert!(answer_ok(&ok));
        assert!(answer_ok(&Some((vec![0x06], Outcome::Broadcast))));
        assert!(!answer_ok(&Some((
            vec![0x86, 0x0B],
            Outcome::GatewayTimeout
        ))));
        assert!(!answer_ok(&None));
    }
}
