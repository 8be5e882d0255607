//! A request waiting for the bus, and the reply it becomes: a read's bus
//! job, the control core's writes (one for a unit, one per bus for a
//! broadcast), or a read/write multiple (0x17) carried out on a drive as
//! its write through the core, then its read.
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
    fn submit(bus: &BusHandle, unit: u8, pdu: Vec<u8>, options: JobOptions) -> Self {
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

/// The write of a read/write multiple, and its read to come.
#[derive(Debug)]
pub struct Writing {
    /// The write.
    write: control::Pending,
    /// Where the read goes after it.
    bus: BusHandle,
    /// The unit.
    unit: u8,
    /// The read (0x03).
    read: Vec<u8>,
    /// The read's job options (the client's source and origin).
    options: JobOptions,
}

/// A read/write multiple (0x17) on a drive, which has no such function:
/// its write goes through the control core as a 0x10, then, once the
/// drive confirmed it, its read goes to the bus as a 0x03, as the
/// specification orders them (the write first).
#[derive(Debug)]
pub enum WriteThenRead {
    /// The write, through the core.
    Writing(Box<Writing>),
    /// The read, once the write was confirmed.
    Reading(ReadState),
    /// The write failed: this is the reply.
    Failed(Vec<u8>, Outcome),
    /// Between states.
    Gone,
}

impl WriteThenRead {
    /// The write is in: settles it, and queues the read if it was
    /// confirmed.
    fn written(&mut self) {
        let WriteThenRead::Writing(writing) = std::mem::replace(self, WriteThenRead::Gone) else {
            return;
        };
        let Writing {
            write,
            bus,
            unit,
            read,
            options,
        } = *writing;
        *self = match write.finish() {
            Ok(_) => WriteThenRead::Reading(ReadState::submit(&bus, unit, read, options)),
            Err(failure) => {
                let (reply, outcome) = failure_reply(
                    crate::modbus::function::READ_WRITE_MULTIPLE_REGISTERS,
                    &failure,
                );
                WriteThenRead::Failed(reply, outcome)
            }
        };
    }

    async fn wait(&mut self) {
        if let WriteThenRead::Writing(writing) = self {
            writing.write.wait().await;
            self.written();
        }
        if let WriteThenRead::Reading(read) = self {
            read.wait().await;
        }
    }

    fn try_ready(&mut self) -> bool {
        if let WriteThenRead::Writing(writing) = self {
            if !writing.write.try_ready() {
                return false;
            }
            self.written();
        }
        match self {
            WriteThenRead::Reading(read) => read.try_ready(),
            _ => true,
        }
    }

    fn reply(self) -> (Vec<u8>, Outcome) {
        match self {
            WriteThenRead::Reading(read) => {
                read.reply(crate::modbus::function::READ_WRITE_MULTIPLE_REGISTERS)
            }
            WriteThenRead::Failed(reply, outcome) => (reply, outcome),
            // Given up on before the write's result: the core settles it
            // as a write whose client went away.
            WriteThenRead::Writing(_) | WriteThenRead::Gone => (
                exception_pdu(
                    crate::modbus::function::READ_WRITE_MULTIPLE_REGISTERS,
                    ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
                ),
                Outcome::PathUnavailable,
            ),
        }
    }
}

/// A request waiting for the bus.
#[derive(Debug)]
pub enum Pending {
    /// A read, passed through.
    Read {
        /// The request.
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
    /// A read/write multiple on a drive.
    WriteThenRead(WriteThenRead),
}

impl Pending {
    /// A read of `pdu`, queued on `bus` for `unit`.
    pub fn read(bus: &BusHandle, unit: u8, pdu: Vec<u8>, options: JobOptions) -> Self {
        let state = ReadState::submit(bus, unit, pdu.clone(), options);
        Pending::Read { pdu, state }
    }

    /// The core's `writes` of `pdu` (one per bus for a broadcast).
    pub fn writes(pdu: &[u8], broadcast: bool, writes: Vec<control::Pending>) -> Self {
        Pending::Writes {
            pdu: pdu.to_vec(),
            broadcast,
            writes,
        }
    }

    /// A read/write multiple: `write` through the core, then `read` (a
    /// 0x03) to `unit` on `bus` once the drive confirmed the write.
    pub fn write_then_read(
        write: control::Pending,
        bus: BusHandle,
        unit: u8,
        read: Vec<u8>,
        options: JobOptions,
    ) -> Self {
        Pending::WriteThenRead(WriteThenRead::Writing(Box::new(Writing {
            write,
            bus,
            unit,
            read,
            options,
        })))
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
            Pending::WriteThenRead(rw) => rw.wait().await,
        }
    }

    /// True when every job has a result (without waiting).
    pub fn try_ready(&mut self) -> bool {
        match self {
            Pending::Read { state, .. } => state.try_ready(),
            Pending::Writes { writes, .. } => writes.iter_mut().all(control::Pending::try_ready),
            Pending::WriteThenRead(rw) => rw.try_ready(),
        }
    }

    /// The function code of the client's request.
    fn function(&self) -> u8 {
        match self {
            Pending::Read { pdu, .. } | Pending::Writes { pdu, .. } => {
                pdu.first().copied().unwrap_or(0)
            }
            Pending::WriteThenRead(_) => crate::modbus::function::READ_WRITE_MULTIPLE_REGISTERS,
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
            Pending::WriteThenRead(rw) => rw.reply(),
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
