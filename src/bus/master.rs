//! The Modbus RTU master of one serial line.
//!
//! Rules it enforces, because RTU frames carry no length and no transaction id:
//! - one frame in flight; each request goes out in one write, only after the
//!   line has been silent for t3.5 (bytes seen meanwhile are stray: counted,
//!   discarded, and the silence starts again);
//! - the reply is framed by the length its function code implies, or by
//!   t3.5 of silence for codes whose length it cannot know, and checked:
//!   CRC, unit, function, and that it answers *this* request (an echo must
//!   repeat the write, an acknowledgement its address and count, a read the
//!   byte count asked for);
//! - after a timeout or a bad frame it waits a guard time, discarding what
//!   arrives, and flushes the input, so a late reply to one request is never
//!   taken as the answer to the next;
//! - a broadcast (unit 0) is sent, followed by the turnaround delay, and no
//!   reply is read; bytes arriving during the turnaround do not shorten it.

use std::io;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{SerialPort, SerialStream};

use super::port::{Direction, Rs485Settings};
use super::rs485;
use super::stats::Outcome;
use crate::clock::PreciseTimer;
use crate::modbus::function::EXCEPTION_BIT;
use crate::modbus::reply::{self, Mismatch};
use crate::modbus::rtu_frame::{self, FrameLength};
use crate::modbus::timing::LineTiming;
use crate::monitor::tap::WireTap;

/// Timing and retry settings of a master.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MasterSettings {
    /// The line's baud rate and character timing.
    pub line: LineTiming,
    /// How long to wait for a reply after the request has left the wire.
    pub response_timeout: Duration,
    /// Attempts after the first, for timeouts and bad frames.
    pub retries: u8,
    /// Silence kept after a timeout or bad frame, discarding anything late.
    pub guard_time: Duration,
    /// Time the drives get to act on a broadcast before the next request.
    pub broadcast_delay: Duration,
    /// RS-485 direction control.
    pub rs485: Rs485Settings,
}

impl MasterSettings {
    /// Settings for `baud` with the given timeout and retries, and guard and
    /// broadcast delays that suit most drives.
    pub fn new(baud: u32, response_timeout: Duration, retries: u8) -> Self {
        Self {
            line: LineTiming::new_8n1(baud),
            response_timeout,
            retries,
            guard_time: response_timeout,
            broadcast_delay: Duration::from_millis(20),
            rs485: Rs485Settings::default(),
        }
    }
}

/// What was wrong with one attempt.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Nothing (or too little) arrived before the timeout.
    Timeout,
    /// A frame arrived with a bad CRC.
    Crc,
    /// A frame that does not answer the request.
    Mismatch(&'static str),
}

impl Fault {
    fn outcome(&self) -> Outcome {
        match self {
            Fault::Timeout => Outcome::Timeout,
            Fault::Crc => Outcome::CrcError,
            Fault::Mismatch(_) => Outcome::BadReply,
        }
    }

    /// Text for error messages.
    pub fn describe(&self) -> String {
        match self {
            Fault::Timeout => "no reply".to_string(),
            Fault::Crc => "CRC error".to_string(),
            Fault::Mismatch(what) => what.to_string(),
        }
    }
}

/// The result of one transaction, all attempts included.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Report {
    /// How it ended.
    pub outcome: Outcome,
    /// The reply PDU when the outcome is `Ok` or `Exception` (empty for a broadcast).
    pub reply: Option<Vec<u8>>,
    /// Attempts made.
    pub attempts: u8,
    /// The last attempt's fault, if it failed.
    pub fault: Option<Fault>,
    /// First byte sent to last byte received (or timeout).
    pub on_wire: Duration,
    /// Time the line was occupied, silences included, for utilisation.
    pub busy: Duration,
    /// Bytes received that belonged to no reply.
    pub stray_bytes: usize,
}

/// The serial port itself failed during a transaction (adapter unplugged,
/// I/O error): the port must be closed and reopened. Whether the request
/// had started to leave decides what the caller may assume about the drive.
#[derive(Debug, thiserror::Error)]
pub enum PortFailure {
    /// Not one byte of the request was written: the drive cannot have
    /// received it.
    #[error("{0}")]
    BeforeSend(io::Error),
    /// The request (or part of it) was written before the port failed:
    /// the drive may have received and carried it out.
    #[error("{0}")]
    AfterSend(io::Error),
}

impl PortFailure {
    /// True when the request may have reached the drive.
    pub fn request_sent(&self) -> bool {
        matches!(self, PortFailure::AfterSend(_))
    }

    /// The port's error, for whoever closes the port.
    pub fn into_io(self) -> io::Error {
        match self {
            PortFailure::BeforeSend(e) | PortFailure::AfterSend(e) => e,
        }
    }
}

/// The RTU master; owns the port.
pub struct RtuMaster {
    port: SerialStream,
    settings: MasterSettings,
    timer: PreciseTimer,
    /// The line has been silent since this instant (may be in the future
    /// after a broadcast: the drives' turnaround).
    quiet_since: Instant,
    buf: Box<[u8; 512]>,
    stray: usize,
    /// Hands every frame to the bus monitor and the scope.
    tap: WireTap,
}

impl RtuMaster {
    /// A master on an open port; must be created in the runtime that drives it.
    pub fn new(port: SerialStream, settings: MasterSettings) -> io::Result<Self> {
        Ok(Self {
            port,
            settings,
            timer: PreciseTimer::new()?,
            quiet_since: Instant::now(),
            buf: Box::new([0; 512]),
            stray: 0,
            tap: WireTap::detached(settings.line),
        })
    }

    /// The master's settings.
    pub fn settings(&self) -> &MasterSettings {
        &self.settings
    }

    /// The tap that shows every frame to the bus monitor and the scope.
    pub fn tap(&mut self) -> &mut WireTap {
        &mut self.tap
    }

    /// Sends `pdu` to `unit` and returns the checked reply. `max_attempts`
    /// overrides the configured retries (1 = a single try).
    ///
    /// An `Err` is a failure of the port itself (unplugged adapter): the
    /// caller should close and reopen it. It says whether the request had
    /// begun to go out: a write cut off by the port may still have reached
    /// the drive.
    pub async fn transact(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
    ) -> Result<Report, PortFailure> {
        let mut sent = false;
        self.attempts(unit, pdu, max_attempts, &mut sent)
            .await
            .map_err(|e| {
                if sent {
                    PortFailure::AfterSend(e)
                } else {
                    PortFailure::BeforeSend(e)
                }
            })
    }

    /// [`transact`](Self::transact)'s attempts; sets `sent` once a byte of
    /// the request has been written.
    async fn attempts(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
        sent: &mut bool,
    ) -> io::Result<Report> {
        let frame = rtu_frame::encode(unit, pdu);
        if frame.len() > rtu_frame::MAX_FRAME || pdu.is_empty() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "request does not fit in an RTU frame",
            ));
        }
        let attempts_allowed = max_attempts
            .unwrap_or(self.settings.retries.saturating_add(1))
            .max(1);
        let t35 = self.settings.line.t3_5();
        self.stray = 0;
        let mut started = None;
        let mut busy = Duration::ZERO;
        let mut last_fault = None;
        for attempt in 1..=attempts_allowed {
            self.wait_for_silence().await?;
            let sent_at = self.send(&frame, sent).await?;
            self.tap.request(unit, &frame, sent_at, attempt);
            started.get_or_insert(sent_at);
            let wire_end = sent_at + self.settings.line.wire_time(frame.len());

            if unit == 0 {
                // Nobody answers a broadcast; give the drives their turnaround.
                self.quiet_since = wire_end + self.settings.broadcast_delay;
                busy += (self.quiet_since - sent_at) + t35;
                return Ok(Report {
                    outcome: Outcome::Ok,
                    reply: Some(Vec::new()),
                    attempts: attempt,
                    fault: None,
                    on_wire: wire_end - sent_at,
                    busy,
                    stray_bytes: self.stray,
                });
            }

            let received = self
                .receive(unit, wire_end + self.settings.response_timeout)
                .await?;
            let end = Instant::now();
            busy += (end - sent_at) + t35;
            let framed = received.as_ref().ok().copied();
            let checked = received.and_then(|len| {
                reply::check(unit, pdu, &self.buf[..len]).map_err(|m| match m {
                    Mismatch::Crc => Fault::Crc,
                    other => Fault::Mismatch(other.describe()),
                })
            });
            let frame = framed.map(|n| &self.buf[..n]);
            self.tap.reply(frame, end, checked.as_ref().err());
            match checked {
                Ok(reply) => {
                    let outcome = if reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0) {
                        Outcome::Exception
                    } else {
                        Outcome::Ok
                    };
                    return Ok(Report {
                        outcome,
                        reply: Some(reply),
                        attempts: attempt,
                        fault: None,
                        on_wire: end - *started.get_or_insert(sent_at),
                        busy,
                        stray_bytes: self.stray,
                    });
                }
                Err(fault) => {
                    let guard_start = Instant::now();
                    self.guard().await?;
                    busy += guard_start.elapsed();
                    last_fault = Some(fault);
                }
            }
        }
        let fault = last_fault.unwrap_or(Fault::Timeout);
        Ok(Report {
            outcome: fault.outcome(),
            reply: None,
            attempts: attempts_allowed,
            fault: Some(fault),
            on_wire: started.map_or(Duration::ZERO, |s| s.elapsed()),
            busy,
            stray_bytes: self.stray,
        })
    }

    /// Waits until the line may carry the next request (t3.5 of silence).
    /// The scheduler calls this *before* it picks the next job, so a command
    /// that arrives during the silence goes next instead of waiting for one
    /// more poll. Returns the stray bytes discarded meanwhile.
    pub async fn settle(&mut self) -> io::Result<usize> {
        self.stray = 0;
        self.wait_for_silence().await?;
        Ok(std::mem::take(&mut self.stray))
    }

    /// Waits until the line has been silent for t3.5, discarding (and
    /// counting) whatever arrives meanwhile; every byte restarts the silence.
    async fn wait_for_silence(&mut self) -> io::Result<()> {
        let t35 = self.settings.line.t3_5();
        // A line that never goes quiet (a babbling device) must not stall the
        // bus forever: after this long we send anyway, and the reply check
        // sorts out the rest. Counted from the end of a broadcast's
        // turnaround, which even a babbling line does not cut short.
        let give_up = self.quiet_since.max(Instant::now())
            + self
                .settings
                .response_timeout
                .max(Duration::from_millis(50));
        loop {
            let deadline = self.quiet_since + t35;
            if Instant::now() >= deadline {
                break;
            }
            tokio::select! {
                biased;
                read = self.port.read(&mut self.buf[..]) => {
                    let n = eof_is_error(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                    // The silence restarts now, unless it was set to end
                    // later (a broadcast's turnaround): a stray byte must
                    // not cut the drives' time to act short.
                    let now = Instant::now();
                    self.quiet_since = self.quiet_since.max(now);
                    if now >= give_up {
                        break;
                    }
                }
                slept = self.timer.sleep_until(deadline) => slept?,
            }
        }
        // Bytes that arrived but were not read yet (e.g. while we were busy
        // elsewhere) are stray too.
        loop {
            match self.port.try_read(&mut self.buf[..]) {
                Ok(0) => return Err(unplugged()),
                Ok(n) => {
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// Puts one frame on the wire in one write; returns when it started.
    /// Sets `sent` as soon as the port has taken a byte of it.
    async fn send(&mut self, frame: &[u8], sent: &mut bool) -> io::Result<Instant> {
        let rs485 = self.settings.rs485;
        if rs485.direction == Direction::Rts {
            self.port
                .write_request_to_send(rs485.rts_active_high)
                .map_err(io::Error::other)?;
            if !rs485.before().is_zero() {
                self.timer
                    .sleep_until(Instant::now() + rs485.before())
                    .await?;
            }
        }
        let sent_at = Instant::now();
        // write_all, counting: an error after a partial write must not pass
        // for a request that never left.
        let mut written = 0;
        while written < frame.len() {
            match self.port.write(&frame[written..]).await? {
                0 => return Err(io::ErrorKind::WriteZero.into()),
                n => {
                    written += n;
                    *sent = true;
                }
            }
        }
        self.port.flush().await?;
        if rs485.direction == Direction::Rts {
            // The bus thread is ours: blocking until the UART is empty is the
            // exact moment to release the line.
            rs485::drain(&self.port)?;
            if !rs485.after().is_zero() {
                self.timer
                    .sleep_until(Instant::now() + rs485.after())
                    .await?;
            }
            self.port
                .write_request_to_send(!rs485.rts_active_high)
                .map_err(io::Error::other)?;
        }
        Ok(sent_at)
    }

    /// Reads one reply frame into `buf`; `Ok(Err(fault))` for a protocol
    /// fault, `Err` for a port failure.
    async fn receive(&mut self, unit: u8, deadline: Instant) -> io::Result<Result<usize, Fault>> {
        let t35 = self.settings.line.t3_5();
        let mut len = 0;
        let mut last_byte = Instant::now();
        loop {
            // A full buffer holds no Modbus frame (the longest is 256 bytes):
            // it is noise. Reading on would read into an empty slice, whose
            // Ok(0) means an unplugged adapter.
            if len >= self.buf.len() {
                return Ok(Err(Fault::Mismatch("reply longer than any Modbus frame")));
            }
            let need = match rtu_frame::response_length(&self.buf[..len]) {
                FrameLength::Known(n) if len >= n => {
                    self.quiet_since = last_byte;
                    return Ok(Ok(n));
                }
                FrameLength::Known(n) => Some(n),
                FrameLength::NeedMore => None,
                FrameLength::BySilence => {
                    // The length is unknown: the frame ends at t3.5 of silence.
                    tokio::select! {
                        biased;
                        read = self.port.read(&mut self.buf[len..]) => {
                            len += eof_is_error(read)?;
                            last_byte = Instant::now();
                            continue;
                        }
                        slept = self.timer.sleep_until(last_byte + t35) => {
                            slept?;
                            self.quiet_since = last_byte;
                            return Ok(Ok(len));
                        }
                    }
                }
            };
            if len > 0 && self.buf[0] != unit {
                return Ok(Err(Fault::Mismatch("reply from another unit")));
            }
            let end = need.map_or(self.buf.len(), |n| n.min(self.buf.len()));
            match tokio::time::timeout_at(deadline.into(), self.port.read(&mut self.buf[len..end]))
                .await
            {
                Ok(read) => {
                    len += eof_is_error(read)?;
                    last_byte = Instant::now();
                }
                Err(_) if len == 0 => return Ok(Err(Fault::Timeout)),
                Err(_) => return Ok(Err(Fault::Mismatch("reply cut short"))),
            }
        }
    }

    /// After a fault: keep the line for `guard_time`, discarding anything
    /// that arrives (a late reply), then flush the input.
    async fn guard(&mut self) -> io::Result<()> {
        let until = Instant::now() + self.settings.guard_time;
        loop {
            tokio::select! {
                read = self.port.read(&mut self.buf[..]) => {
                    let n = eof_is_error(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                () = tokio::time::sleep_until(until.into()) => break,
            }
        }
        self.port
            .clear(tokio_serial::ClearBuffer::Input)
            .map_err(io::Error::other)?;
        self.quiet_since = Instant::now();
        Ok(())
    }
}

/// A serial read of 0 bytes means the device went away.
fn eof_is_error(read: io::Result<usize>) -> io::Result<usize> {
    match read {
        Ok(0) => Err(unplugged()),
        other => other,
    }
}

fn unplugged() -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        "the serial port was closed (adapter unplugged?)",
    )
}
