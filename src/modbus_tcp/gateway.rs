//! Turns one Modbus TCP request into a bus job and the job's result into the
//! reply PDU: routing by unit id, the read-only rule, the polled copy,
//! broadcasts, gateway exceptions, metrics and the write audit log.
//!
//! The connection (see [`super::connection`]) decides *when* replies go out;
//! this module decides *what* they are.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;
use tokio::sync::oneshot::error::TryRecvError;
use tracing::{debug, warn};

use super::config::ModbusTcpConfig;
use super::outcome::{Outcome, exception_pdu, gateway_exception};
use super::polled_copy;
use super::request;
use super::routing::{BusUnits, Route, UnitRoutes};
use crate::bus::handle::JobOptions;
use crate::bus::job::JobResult;
use crate::bus::{BusError, Origin, Priority, SourceId};
use crate::drive::Register;
use crate::metrics::Metrics;
use crate::modbus::ExceptionCode;
use crate::modbus::function::{EXCEPTION_BIT, WRITE_SINGLE_REGISTER, be_u16};
use crate::plant::Plant;

/// One connected client.
#[derive(Debug, Clone)]
pub struct Client {
    /// Its address: who it is in the audit log.
    pub peer: SocketAddr,
    /// Its source id: the bus queue takes turns between sources, so one
    /// connection flooding requests cannot starve the others.
    pub source: SourceId,
}

impl Client {
    /// A new client at `peer`, with a source id of its own.
    pub fn new(peer: SocketAddr) -> Self {
        Self {
            peer,
            source: SourceId::new_unique(),
        }
    }

    fn who(&self) -> String {
        self.peer.to_string()
    }
}

/// What to do about one request.
#[derive(Debug)]
pub enum Answer {
    /// Reply with this PDU (already decided, counted and audited).
    Now(Vec<u8>),
    /// Send nothing (a broadcast without reply).
    Silent,
    /// Wait for the bus.
    Pending(Pending),
}

/// The routing and policy of one listener.
pub struct Gateway {
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    routes: UnitRoutes,
    /// Maximum age of the polled copy per bus index (`None`: strict passthrough).
    polled_copy: Vec<Option<Duration>>,
    read_only: bool,
    broadcast_reply: bool,
}

impl Gateway {
    /// The gateway for `config` over `plant`; warns about unreachable units.
    pub fn new(config: &ModbusTcpConfig, plant: Arc<Plant>, metrics: Arc<Metrics>) -> Self {
        let buses: Vec<BusUnits> = plant
            .buses()
            .iter()
            .map(|b| BusUnits {
                name: b.handle.name().to_string(),
                units: b.config.drives.iter().map(|d| d.unit()).collect(),
            })
            .collect();
        let (routes, warnings) = UnitRoutes::build(&config.unit_map, &buses);
        for w in warnings {
            warn!("{w}");
        }
        let polled_copy = buses
            .iter()
            .map(|b| {
                config
                    .polled_copy
                    .iter()
                    .find(|p| p.bus == b.name)
                    .map(|p| p.max_age())
            })
            .collect();
        Self {
            plant,
            metrics,
            routes,
            polled_copy,
            read_only: config.read_only,
            broadcast_reply: config.broadcast_reply,
        }
    }

    /// The metrics this gateway counts into.
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// Decides what to do with `pdu` sent by `client` to `unit` in MBAP
    /// transaction `transaction`. Requests that go to the bus are queued
    /// before this returns, so pipelined requests wait in the bus queue,
    /// not in the socket.
    pub fn handle(&self, client: &Client, transaction: u16, unit: u8, pdu: Vec<u8>) -> Answer {
        if pdu.is_empty() {
            // The MBAP codec never yields one; answer rather than panic.
            return Answer::Now(exception_pdu(0, ExceptionCode::ILLEGAL_FUNCTION));
        }
        if unit == 0 {
            return self.broadcast(client, transaction, pdu);
        }
        let Some(route) = self.routes.route(unit) else {
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
        let bus = &self.plant.buses()[route.bus].handle;
        let target = (bus.name(), route.unit);
        if self.read_only && !request::reads_only(&pdu) {
            return self.refuse(
                client,
                target,
                &pdu,
                ExceptionCode::ILLEGAL_FUNCTION,
                Outcome::ReadOnly,
                "refused: this Modbus TCP listener is read-only".to_string(),
            );
        }
        if let Err(code) = request::check_shape(&pdu) {
            return self.refuse(
                client,
                target,
                &pdu,
                code,
                Outcome::Invalid,
                "refused: the request's length or quantity does not fit its function code"
                    .to_string(),
            );
        }
        if let Some(max_age) = self.polled_copy[route.bus]
            && let Some(snapshot) = bus.drive(route.unit)
            && let Some(reply) = polled_copy::answer(&pdu, &snapshot, max_age)
        {
            self.count(function, Outcome::Cached);
            return Answer::Now(reply);
        }
        let mut pending = Pending::new(client, transaction, &pdu, false);
        pending.submit(self, route, pdu);
        Answer::Pending(pending)
    }

    /// Unit 0: every bus the listener reaches, no reply waited for.
    fn broadcast(&self, client: &Client, transaction: u16, pdu: Vec<u8>) -> Answer {
        let refusal = if self.read_only {
            Some((
                ExceptionCode::ILLEGAL_FUNCTION,
                Outcome::ReadOnly,
                "refused: this Modbus TCP listener is read-only",
            ))
        } else if !request::broadcastable(&pdu) {
            Some((
                ExceptionCode::ILLEGAL_FUNCTION,
                Outcome::Refused,
                "refused: only writes (0x05, 0x06, 0x0F, 0x10, 0x16) can be broadcast",
            ))
        } else if let Err(code) = request::check_shape(&pdu) {
            Some((
                code,
                Outcome::Invalid,
                "refused: the request's length or quantity does not fit its function",
            ))
        } else if self.readdresses_a_shared_bus(&pdu) {
            // Manual 1.2: address setting is a broadcast and only one drive
            // may be on the bus; on a bus of several drives every one of them
            // would take the same address.
            Some((
                ExceptionCode::ILLEGAL_FUNCTION,
                Outcome::Refused,
                "refused: an address broadcast (SLAVE_ADDR) would give every drive of a bus with several drives the same address",
            ))
        } else if self.routes.broadcast_buses().is_empty() {
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
            return if self.broadcast_reply {
                answer
            } else {
                Answer::Silent
            };
        }
        let mut pending = Pending::new(client, transaction, &pdu, true);
        for &bus in self.routes.broadcast_buses() {
            pending.submit(self, Route { bus, unit: 0 }, pdu.clone());
        }
        if self.broadcast_reply {
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

    /// True for a broadcast write of SLAVE_ADDR reaching a bus with more
    /// than one configured drive.
    fn readdresses_a_shared_bus(&self, pdu: &[u8]) -> bool {
        let slave_addr = pdu.first() == Some(&WRITE_SINGLE_REGISTER)
            && be_u16(pdu, 1) == Some(Register::SlaveAddr.address());
        slave_addr
            && self
                .routes
                .broadcast_buses()
                .iter()
                .any(|&b| self.plant.buses()[b].config.drives.len() > 1)
    }

    /// Answers at once with `code` (audited when the request was a write).
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
            crate::audit::write(
                &client.who(),
                bus,
                unit,
                &request::describe(pdu),
                &Err::<String, _>(format!("{why}; answered {code}")),
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

/// A request waiting for its bus job(s): one for a unit, one per bus for a
/// broadcast. Holding it keeps the jobs alive; dropping or cancelling it
/// makes the bus drop those still queued before they reach the wire.
#[derive(Debug)]
pub struct Pending {
    who: String,
    source: SourceId,
    origin: Origin,
    request: Vec<u8>,
    broadcast: bool,
    jobs: Vec<Job>,
}

#[derive(Debug)]
struct Job {
    bus: Arc<str>,
    unit: u8,
    state: JobState,
}

#[derive(Debug)]
enum JobState {
    Waiting(oneshot::Receiver<JobResult>),
    Done(JobResult),
}

impl Pending {
    fn new(client: &Client, transaction: u16, pdu: &[u8], broadcast: bool) -> Self {
        Self {
            who: client.who(),
            source: client.source,
            origin: Origin::modbus_tcp(client.peer, transaction),
            request: pdu.to_vec(),
            broadcast,
            jobs: Vec::new(),
        }
    }

    /// Queues `pdu` on the route's bus as a command from this client.
    fn submit(&mut self, gateway: &Gateway, route: Route, pdu: Vec<u8>) {
        let handle = &gateway.plant.buses()[route.bus].handle;
        let options = JobOptions {
            priority: Priority::Command,
            source: self.source,
            queue_timeout: None,
            max_attempts: None,
            origin: self.origin.clone(),
        };
        let state = match handle.submit(route.unit, pdu, options) {
            Ok(rx) => JobState::Waiting(rx),
            Err(e) => JobState::Done(Err(e)),
        };
        self.jobs.push(Job {
            bus: handle.name_arc(),
            unit: route.unit,
            state,
        });
    }

    /// Waits until every job has a result. Cancel-safe: results already
    /// in stay in.
    pub async fn wait(&mut self) {
        for job in &mut self.jobs {
            if let JobState::Waiting(rx) = &mut job.state {
                let result = rx.await.unwrap_or(Err(BusError::ShuttingDown));
                job.state = JobState::Done(result);
            }
        }
    }

    /// True when every job has a result (without waiting).
    pub fn try_ready(&mut self) -> bool {
        for job in &mut self.jobs {
            if let JobState::Waiting(rx) = &mut job.state {
                match rx.try_recv() {
                    Ok(result) => job.state = JobState::Done(result),
                    Err(TryRecvError::Closed) => {
                        job.state = JobState::Done(Err(BusError::ShuttingDown))
                    }
                    Err(TryRecvError::Empty) => return false,
                }
            }
        }
        true
    }

    /// The reply PDU once every job is done (for a broadcast, the write's
    /// confirmation or the first failure); counts and audits it.
    pub fn finish(self, metrics: &Metrics) -> Vec<u8> {
        let function = self.request.first().copied().unwrap_or(0);
        let is_write = !request::reads_only(&self.request);
        let what = if is_write {
            request::describe(&self.request)
        } else {
            String::new()
        };
        let mut reply = None;
        let mut outcome = if self.broadcast {
            Outcome::Broadcast
        } else {
            Outcome::Ok
        };
        for job in self.jobs {
            let result = match job.state {
                JobState::Done(result) => result,
                JobState::Waiting(_) => Err(BusError::ShuttingDown),
            };
            let audit: Result<String, String> = match &result {
                Ok(_) if self.broadcast => Ok("broadcast sent".to_string()),
                Ok(exchange)
                    if exchange
                        .reply
                        .first()
                        .is_some_and(|f| f & EXCEPTION_BIT != 0) =>
                {
                    let code = ExceptionCode(exchange.reply.get(1).copied().unwrap_or(0));
                    Err(format!("the drive refused it: {code}"))
                }
                Ok(exchange) => Ok(format!("confirmed [{}]", request::hex(&exchange.reply))),
                Err(e) => Err(e.to_string()),
            };
            if is_write {
                crate::audit::write(&self.who, &job.bus, job.unit, &what, &audit);
            }
            match result {
                Ok(exchange) if !self.broadcast => {
                    if exchange
                        .reply
                        .first()
                        .is_some_and(|f| f & EXCEPTION_BIT != 0)
                    {
                        outcome = Outcome::Exception;
                    }
                    reply = Some(exchange.reply);
                }
                Ok(_) => {}
                Err(e) => {
                    // The first failure is what the client hears about.
                    if reply.is_none() {
                        let (code, failed) = gateway_exception(&e);
                        outcome = failed;
                        reply = Some(exception_pdu(function, code));
                    }
                }
            }
        }
        metrics.faces().tcp_request(function, outcome.label());
        reply.unwrap_or_else(|| request::write_confirmation(&self.request))
    }

    /// The client has gone: the bus drops the jobs still queued before they
    /// reach the wire. A job already on the wire finishes there; its result
    /// is audited if it is in by now.
    pub fn cancel(mut self, metrics: &Metrics) {
        let function = self.request.first().copied().unwrap_or(0);
        for job in &mut self.jobs {
            if let JobState::Waiting(rx) = &mut job.state {
                rx.close();
                if let Ok(result) = rx.try_recv() {
                    job.state = JobState::Done(result);
                }
            }
        }
        metrics
            .faces()
            .tcp_request(function, Outcome::Cancelled.label());
        if request::reads_only(&self.request) {
            return;
        }
        let what = request::describe(&self.request);
        for job in &self.jobs {
            let audit: Result<String, String> = match &job.state {
                JobState::Done(Ok(exchange)) => Ok(format!(
                    "carried out, but the client disconnected before the reply [{}]",
                    request::hex(&exchange.reply)
                )),
                JobState::Done(Err(e)) => Err(e.to_string()),
                JobState::Waiting(_) => Err(
                    "the client disconnected before the reply: dropped unsent if still queued, otherwise its result is unknown"
                        .to_string(),
                ),
            };
            crate::audit::write(&self.who, &job.bus, job.unit, &what, &audit);
        }
    }
}
