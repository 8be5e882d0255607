//! A request waiting for the bus, and the reply it becomes: a read's bus
//! job (also the read of a read/write multiple, whose write the core has
//! carried out: its reply goes back under 0x17), or the control core's
//! writes (one for a unit, one per bus for a broadcast).
//!
//! Holding a [`Pending`] keeps its jobs alive; dropping or cancelling it
//! makes the bus drop those still queued before they reach the wire (a
//! brake excepted: the core follows it to its end).

use tokio::sync::oneshot;
use tokio::sync::oneshot::error::TryRecvError;

use super::outcome::{Outcome, exception_pdu, failure_reply, gateway_exception};
use super::request;
use crate::bus::handle::JobOptions;
use crate::bus::job::JobResult;
use crate::bus::{BusError, BusHandle};
use crate::control;
use crate::metrics::Metrics;
use crate::modbus::ExceptionCode;
use crate::modbus::function::EXCEPTION_BIT;

/// A read's bus job.
#[derive(Debug)]
pub enum ReadState {
    /// On the queue or the wire.
    Waiting(oneshot::Receiver<JobResult>),
    /// Done.
    Done(JobResult),
}

impl ReadState {
    /// The job for `pdu` to `unit`, queued now.
    pub fn submit(bus: &BusHandle, unit: u8, pdu: Vec<u8>, options: JobOptions) -> Self {
        match bus.submit(unit, pdu, options) {
            Ok(rx) => ReadState::Waiting(rx),
            Err(e) => ReadState::Done(Err(e)),
        }
    }

    async fn wait(&mut self) {
        if let ReadState::Waiting(rx) = self {
            let result = rx.await.unwrap_or(Err(BusError::ShuttingDown));
            *self = ReadState::Done(result);
        }
    }

    fn try_ready(&mut self) -> bool {
        match self {
            ReadState::Done(_) => true,
            ReadState::Waiting(rx) => match rx.try_recv() {
                Ok(result) => {
                    *self = ReadState::Done(result);
                    true
                }
                Err(TryRecvError::Closed) => {
                    *self = ReadState::Done(Err(BusError::ShuttingDown));
                    true
                }
                Err(TryRecvError::Empty) => false,
            },
        }
    }

    /// The reply PDU for a request of `function` and how it ended: the
    /// drive's reply with `function` as its code, or the gateway's
    /// exception.
    fn reply(self, function: u8) -> (Vec<u8>, Outcome) {
        let result = match self {
            ReadState::Done(result) => result,
            ReadState::Waiting(_) => Err(BusError::ShuttingDown),
        };
        match result {
            Ok(exchange) => {
                let mut reply = exchange.reply;
                let exception = reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0);
                if let Some(code) = reply.first_mut() {
                    *code = function | (*code & EXCEPTION_BIT);
                }
                let outcome = if exception {
                    Outcome::Exception
                } else {
                    Outcome::Ok
                };
                (reply, outcome)
            }
            Err(e) => {
                let (code, outcome) = gateway_exception(&e);
                (exception_pdu(function, code), outcome)
            }
        }
    }
}

/// A request waiting for the bus.
#[derive(Debug)]
pub enum Pending {
    /// A read, passed through.
    Read {
        /// The client's request (a read/write multiple's, for its read).
        pdu: Vec<u8>,
        /// Its job.
        state: ReadState,
    },
    /// Writes through the control core.
    Writes {
        /// The request.
        pdu: Vec<u8>,
        /// True for a broadcast.
        broadcast: bool,
        /// One per bus.
        writes: Vec<control::Pending>,
    },
}

impl Pending {
    /// The core's `writes` of `pdu` (one per bus for a broadcast).
    pub fn writes(pdu: &[u8], broadcast: bool, writes: Vec<control::Pending>) -> Self {
        Pending::Writes {
            pdu: pdu.to_vec(),
            broadcast,
            writes,
        }
    }

    /// Waits until every job has a result. Cancel-safe: results already
    /// in stay in.
    pub async fn wait(&mut self) {
        match self {
            Pending::Read { state, .. } => state.wait().await,
            Pending::Writes { writes, .. } => {
                for w in writes {
                    w.wait().await;
                }
            }
        }
    }

    /// True when every job has a result (without waiting).
    pub fn try_ready(&mut self) -> bool {
        match self {
            Pending::Read { state, .. } => state.try_ready(),
            Pending::Writes { writes, .. } => writes.iter_mut().all(control::Pending::try_ready),
        }
    }

    /// The function code of the client's request.
    fn function(&self) -> u8 {
        match self {
            Pending::Read { pdu, .. } | Pending::Writes { pdu, .. } => {
                pdu.first().copied().unwrap_or(0)
            }
        }
    }

    /// The reply PDU once every job is done (for a broadcast, the write's
    /// confirmation or the first failure); counts it.
    pub fn finish(self, metrics: &Metrics) -> Vec<u8> {
        let function = self.function();
        let (reply, outcome) = match self {
            Pending::Read { state, .. } => state.reply(function),
            Pending::Writes {
                pdu,
                broadcast,
                writes,
            } => writes_reply(&pdu, broadcast, writes),
        };
        metrics.faces().tcp_request(function, outcome.label());
        reply
    }

    /// The client has gone: the bus drops the jobs still queued before they
    /// reach the wire. A write already on the wire finishes there; the
    /// control core audits it.
    pub fn cancel(self, metrics: &Metrics) {
        metrics
            .faces()
            .tcp_request(self.function(), Outcome::Cancelled.label());
        drop(self);
    }
}

/// The reply to the core's writes of `pdu`: the drive's (for a broadcast,
/// the write's confirmation), or the first failure.
fn writes_reply(pdu: &[u8], broadcast: bool, writes: Vec<control::Pending>) -> (Vec<u8>, Outcome) {
    let function = pdu.first().copied().unwrap_or(0);
    let mut answer = None;
    for w in writes {
        let result = w.finish();
        // The first failure is what the client hears about.
        if answer.is_none() || (broadcast && result.is_err() && answer_ok(&answer)) {
            answer = Some(match result {
                Ok(control::Outcome::Confirmed { reply, .. }) => {
                    (request::reply_to(pdu, reply), Outcome::Ok)
                }
                Ok(control::Outcome::Broadcast) => {
                    (request::write_confirmation(pdu), Outcome::Broadcast)
                }
                Err(failure) => failure_reply(function, &failure),
            });
        }
    }
    answer.unwrap_or_else(|| {
        (
            exception_pdu(function, ExceptionCode::GATEWAY_PATH_UNAVAILABLE),
            Outcome::PathUnavailable,
        )
    })
}

pub(super) fn answer_ok(answer: &Option<(Vec<u8>, Outcome)>) -> bool {
    matches!(answer, Some((_, Outcome::Ok | Outcome::Broadcast)))
}
