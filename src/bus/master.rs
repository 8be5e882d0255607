//! The Modbus RTU master of one serial line.
//!
//! Rules it enforces, because RTU frames carry no length and no transaction id:
//! - one frame in flight; each request goes out in one write, only after the
//!   line has been silent for t3.5 (bytes seen meanwhile are stray: counted,
//!   discarded, and the silence starts again);
//! - the response timeout is the wait for the reply's first byte; once bytes
//!   flow, the deadline follows the wire (the bytes still to come at the
//!   character time, plus t3.5 and an allowance for delivery), so a long
//!   reply at a low baud rate is not cut off by a timeout meant for silence;
//! - the reply is framed by the length its function code implies, or by
//!   t3.5 of silence for codes whose length it cannot know, and checked:
//!   CRC, unit, function, and that it answers *this* request (an echo must
//!   repeat the write, an acknowledgement its address and count, a read the
//!   byte count asked for);
//! - after a timeout or a bad frame it waits a guard time, discarding what
//!   arrives, and flushes the input, so a late reply to one request is never
//!   taken as the answer to the next. A probe of a drive not known to answer
//!   (off, or never heard) gets one attempt, and after a timeout in which
//!   not one byte arrived its guard only lasts as long as a reply starting
//!   at the timeout would take, unless a fixed guard is configured: a dead
//!   drive then costs its timeout and little more;
//! - a broadcast (unit 0) is sent, followed by the turnaround delay, and no
//!   reply is read; bytes arriving during the turnaround do not shorten it.

use std::io;
use std::time::{Duration, Instant};

pub use super::fault::Fault;
use super::port::{Direction, Rs485Settings};
use super::stats::Outcome;
use super::tap::WireTap;
use super::transport::Transport;
use crate::clock::{PreciseTimer, SPIN};
use crate::modbus::function::EXCEPTION_BIT;
use crate::modbus::reply::{self, Mismatch};
use crate::modbus::rtu_frame::{self, FrameLength};
use crate::modbus::timing::LineTiming;

/// Time allowed, beyond the wire's own pace, for the rest of a reply to
/// reach the master once it has begun: USB adapters hand bytes over in
/// packets up to 16 ms apart (FTDI's default latency timer), and the system
/// may run the reader late. A reply that pauses longer is cut short.
pub const DELIVERY_ALLOWANCE: Duration = Duration::from_millis(20);

/// How long before the line is free the scheduler picks the next job: the
/// choice and the frame are ready when the silence ends, and the master
/// spins through the rest of it instead of risking a late wake-up. An
/// emergency that arrives in this last stretch goes on the next turn.
pub const PICK_AHEAD: Duration = Duration::from_micros(100);

/// Timing and retry settings of a master.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MasterSettings {
    /// The line's baud rate and character timing.
    pub line: LineTiming,
    /// How long to wait for a reply's first byte after the request has left
    /// the wire (the rest follows at the wire's pace).
    pub response_timeout: Duration,
    /// Attempts after the first, for timeouts and bad frames.
    pub retries: u8,
    /// Silence kept after a timeout or bad frame, discarding anything late.
    pub guard: Guard,
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
            guard: Guard::Auto,
            broadcast_delay: Duration::from_millis(20),
            rs485: Rs485Settings::default(),
        }
    }
}

/// How long the line is kept after a failed attempt, discarding whatever
/// arrives, so that a late reply is not taken for the next request's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Guard {
    /// The response timeout; but after a [probe](RtuMaster::probe)'s
    /// timeout in which not one byte arrived, as long as the awaited reply,
    /// had it started at the timeout, takes on the wire, plus t3.5, and on
    /// while bytes keep coming. A drive that is off then costs its timeout
    /// and a few milliseconds per probe, while a drive that answered its
    /// last request and is late once keeps the whole guard for its late
    /// reply.
    Auto,
    /// This long after every failed attempt: for drives that may answer
    /// later than the response timeout.
    Fixed(Duration),
}

/// The outcome counted in the bus's statistics for a failed attempt.
fn fault_outcome(fault: &Fault) -> Outcome {
    match fault {
        Fault::Timeout => Outcome::Timeout,
        Fault::Crc => Outcome::CrcError,
        Fault::Mismatch(_) => Outcome::BadReply,
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
    /// The silence the master left before the request: from the end of the
    /// previous frame (the last byte received, or sent with no reply) to
    /// the first byte of this one. At least t3.5; the rest is overhead.
    pub idle_before: Duration,
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
    port: Transport,
    settings: MasterSettings,
    timer: PreciseTimer,
    /// The line has been silent since this instant (may be in the future
    /// after a broadcast: the drives' turnaround).
    quiet_since: Instant,
    buf: Box<[u8; 512]>,
    stray: usize,
    /// Shows every frame to the bus's observers (the monitor, the scope).
    tap: WireTap,
}

impl RtuMaster {
    /// A master on an open port (a serial adapter or a serial device
    /// server's connection); must be created in the runtime that drives it.
    pub fn new(port: impl Into<Transport>, settings: MasterSettings) -> io::Result<Self> {
        Ok(Self {
            port: port.into(),
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

    /// The tap that shows every frame to the bus's observers.
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
        self.run(unit, pdu, max_attempts, false).await
    }

    /// Sends `pdu` once to `unit`, a drive not known to answer (off, or not
    /// heard yet): no retry, and after a timeout in which nothing arrived
    /// only the guard a late reply needs (with [`Guard::Auto`]). Errors as
    /// for [`transact`](Self::transact).
    pub async fn probe(&mut self, unit: u8, pdu: &[u8]) -> Result<Report, PortFailure> {
        self.run(unit, pdu, Some(1), true).await
    }

    async fn run(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
        probe: bool,
    ) -> Result<Report, PortFailure> {
        let mut sent = false;
        self.attempts(unit, pdu, max_attempts, probe, &mut sent)
            .await
            .map_err(|e| {
                if sent {
                    PortFailure::AfterSend(e)
                } else {
                    PortFailure::BeforeSend(e)
                }
            })
    }

    /// The attempts of a transaction (or a probe); sets `sent` once a byte
    /// of the request has been written.
    async fn attempts(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
        probe: bool,
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
        let mut idle_before = Duration::ZERO;
        for attempt in 1..=attempts_allowed {
            self.wait_for_silence(Duration::ZERO, PICK_AHEAD + PICK_AHEAD)
                .await?;
            let quiet_since = self.quiet_since;
            let sent_at = self.send(&frame, sent).await?;
            if started.is_none() {
                idle_before = sent_at.saturating_duration_since(quiet_since);
            }
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
                    idle_before,
                });
            }

            let received = self
                .receive(unit, pdu, wire_end + self.settings.response_timeout)
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
                        idle_before,
                    });
                }
                Err(fault) => {
                    let guard_start = Instant::now();
                    match (self.settings.guard, &fault) {
                        (Guard::Auto, Fault::Timeout) if probe => {
                            let reply_len = rtu_frame::expected_response_length(pdu)
                                .unwrap_or(rtu_frame::MAX_FRAME);
                            self.guard_late_reply(reply_len).await?;
                        }
                        (Guard::Auto, _) => self.guard(self.settings.response_timeout).await?,
                        (Guard::Fixed(time), _) => self.guard(time).await?,
                    }
                    busy += guard_start.elapsed();
                    last_fault = Some(fault);
                }
            }
        }
        let fault = last_fault.unwrap_or(Fault::Timeout);
        Ok(Report {
            outcome: fault_outcome(&fault),
            reply: None,
            attempts: attempts_allowed,
            fault: Some(fault),
            on_wire: started.map_or(Duration::ZERO, |s| s.elapsed()),
            busy,
            stray_bytes: self.stray,
            idle_before,
        })
    }

    /// When the line may carry the next request: t3.5 after the end of the
    /// last frame (later after a broadcast's turnaround).
    pub fn line_free_at(&self) -> Instant {
        self.quiet_since + self.settings.line.t3_5()
    }

    /// Waits until the line may carry the next request (t3.5 of silence),
    /// less [`PICK_AHEAD`]. The scheduler calls this *before* it picks the
    /// next job, so a command that arrives during the silence goes next
    /// instead of waiting for one more poll; [`transact`](Self::transact)
    /// then waits out the rest. Returns the stray bytes discarded meanwhile.
    pub async fn settle(&mut self) -> io::Result<usize> {
        self.stray = 0;
        self.wait_for_silence(PICK_AHEAD, SPIN).await?;
        Ok(std::mem::take(&mut self.stray))
    }

    /// Waits until the line has been silent for t3.5 (less `early`),
    /// discarding (and counting) whatever arrives meanwhile; every byte
    /// restarts the silence. The last `spin` of the wait is spun.
    async fn wait_for_silence(&mut self, early: Duration, spin: Duration) -> io::Result<()> {
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
            let deadline = self.quiet_since + t35.saturating_sub(early);
            let now = Instant::now();
            if now >= deadline {
                // Bytes that arrived but were not read yet (while we were
                // busy elsewhere, or spinning) are stray too, and the
                // silence starts again after them.
                if self.drain_input()? == 0 || now >= give_up {
                    break;
                }
                self.quiet_since = self.quiet_since.max(Instant::now());
                continue;
            }
            tokio::select! {
                biased;
                read = self.port.read(&mut self.buf[..]) => {
                    let n = self.got(read)?;
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
                // Spinning through the last stretch (the job is picked by
                // then): no wake-up can come late.
                slept = self.timer.sleep_until_spinning(deadline, spin) => slept?,
            }
        }
        Ok(())
    }

    /// Reads and discards what has arrived, without waiting; the count.
    fn drain_input(&mut self) -> io::Result<usize> {
        let mut drained = 0;
        loop {
            match self.port.try_read(&mut self.buf[..]) {
                Ok(0) => return Err(self.port.closed()),
                Ok(n) => {
                    drained += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        self.stray += drained;
        Ok(drained)
    }

    /// Puts one frame on the wire in one write; returns when it started.
    /// Sets `sent` as soon as the port has taken a byte of it.
    async fn send(&mut self, frame: &[u8], sent: &mut bool) -> io::Result<Instant> {
        let rs485 = self.settings.rs485;
        if rs485.direction == Direction::Rts {
            self.port.set_rts(rs485.rts_active_high)?;
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
            self.port.drain()?;
            if !rs485.after().is_zero() {
                self.timer
                    .sleep_until(Instant::now() + rs485.after())
                    .await?;
            }
            self.port.set_rts(!rs485.rts_active_high)?;
        }
        Ok(sent_at)
    }

    /// Reads one reply frame to `request` into `buf`; `Ok(Err(fault))` for a
    /// protocol fault, `Err` for a port failure.
    ///
    /// `first_byte_by` is the response timeout: the wait for the reply's
    /// first byte. Once bytes flow, the deadline follows the wire: the bytes
    /// still to come at the character time, plus t3.5 and the
    /// [`DELIVERY_ALLOWANCE`], counted from the last bytes received, but
    /// never earlier than the timeout. A 125-register reply takes 265 ms at
    /// 9600 baud; a drive that starts it in time gets it through whatever
    /// the timeout.
    async fn receive(
        &mut self,
        unit: u8,
        request: &[u8],
        first_byte_by: Instant,
    ) -> io::Result<Result<usize, Fault>> {
        let line = self.settings.line;
        let t35 = line.t3_5();
        let expected = rtu_frame::expected_response_length(request).unwrap_or(rtu_frame::MAX_FRAME);
        let mut len = 0;
        let mut last_byte = Instant::now();
        let mut deadline = first_byte_by;
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
                            len += self.got(read)?;
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
            if len > 0 {
                if self.buf[0] != unit {
                    return Ok(Err(Fault::Mismatch("reply from another unit")));
                }
                let remaining = need.unwrap_or(expected).saturating_sub(len);
                deadline =
                    deadline.max(last_byte + line.wire_time(remaining) + t35 + DELIVERY_ALLOWANCE);
            }
            let end = need.map_or(self.buf.len(), |n| n.min(self.buf.len()));
            match tokio::time::timeout_at(deadline.into(), self.port.read(&mut self.buf[len..end]))
                .await
            {
                Ok(read) => {
                    len += self.got(read)?;
                    last_byte = Instant::now();
                }
                Err(_) if len == 0 => return Ok(Err(Fault::Timeout)),
                Err(_) => return Ok(Err(Fault::Mismatch("reply cut short"))),
            }
        }
    }

    /// After a fault: keep the line for `time`, discarding anything that
    /// arrives (a late reply), then flush the input.
    async fn guard(&mut self, time: Duration) -> io::Result<()> {
        let until = Instant::now() + time;
        loop {
            tokio::select! {
                read = self.port.read(&mut self.buf[..]) => {
                    let n = self.got(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                slept = self.timer.sleep_until_relaxed(until) => {
                    slept?;
                    break;
                }
            }
        }
        self.flush_input()
    }

    /// After a timeout in which nothing arrived: keep the line as long as a
    /// reply of `reply_len` bytes starting now would take, plus t3.5, and
    /// on until t3.5 of silence if bytes come meanwhile (the late reply is
    /// then discarded whole); then flush the input.
    async fn guard_late_reply(&mut self, reply_len: usize) -> io::Result<()> {
        let line = self.settings.line;
        let mut until = Instant::now() + line.wire_time(reply_len) + line.t3_5();
        loop {
            tokio::select! {
                read = self.port.read(&mut self.buf[..]) => {
                    let n = self.got(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                    until = until.max(Instant::now() + line.t3_5());
                }
                slept = self.timer.sleep_until_relaxed(until) => {
                    slept?;
                    break;
                }
            }
        }
        self.flush_input()
    }

    /// Discards whatever the port holds unread; the line is silent from now.
    fn flush_input(&mut self) -> io::Result<()> {
        self.port.clear_input()?;
        self.quiet_since = Instant::now();
        Ok(())
    }

    /// A read's byte count; a read of 0 bytes means the line went away (the
    /// adapter was unplugged, the device server closed the connection).
    fn got(&self, read: io::Result<usize>) -> io::Result<usize> {
        match read {
            Ok(0) => Err(self.port.closed()),
            other => other,
        }
    }
}
