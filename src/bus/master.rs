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
//! - the wait for a reply's first byte is learned per drive
//!   ([`reply_timeout`](super::reply_timeout)): the ceiling
//!   (`response_timeout`) until the drive has answered, then a little more
//!   than its usual turnaround, never less than the floor. The learned
//!   timeout decides when to give up and retry; the guard after it (the
//!   time the longest reply the request can draw takes on the wire, t3.5,
//!   and the learned timeout again) is still the request's own: nothing
//!   else was sent, so a reply that starts in it answers this request, is
//!   taken, and raises the drive's estimate. A frame from another unit (a
//!   late reply to an earlier request) is discarded and the wait goes on.
//!   A corrupted reply that ended needs only t3.5. The last attempt of a
//!   transaction waits the whole ceiling;
//! - a reply later than all that (a drive that slowed down) can still come
//!   until the ceiling: until then the drive is sent nothing its reply
//!   could pass for the answer to, except the same request again (whose
//!   answer it is) -- see [`held_until`](RtuMaster::held_until). A frame
//!   from the wrong unit is never taken;
//! - with a fixed guard configured, the old timing holds: the full response
//!   timeout for every reply, then the guard after every fault. A probe of a
//!   drive not known to answer (off, or never heard) gets one attempt; a
//!   scan of units that may not exist ([`scan`](RtuMaster::scan)) one
//!   attempt with the full response timeout;
//! - a broadcast (unit 0) is sent, followed by the turnaround delay, and no
//!   reply is read; bytes arriving during the turnaround do not shorten it.

use std::io;
use std::time::{Duration, Instant};

pub use super::fault::Fault;
use super::port::{Direction, Rs485Settings};
use super::reply_timeout::{Bounds, ReplyTimeout};
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

/// The default least learned reply timeout (`reply_timeout_floor_ms`): a
/// drive answering in 0.5 ms at 115200 baud is waited for at least this
/// long, and a reply that starts later still is taken in the guard after it.
pub const DEFAULT_REPLY_TIMEOUT_FLOOR: Duration = Duration::from_millis(3);

/// What a transaction is for, which decides how long it waits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Purpose {
    /// A request to a drive: its learned timeout, the ceiling on the last
    /// attempt.
    Transact,
    /// A probe of a configured drive not known to answer (off, or never
    /// heard): one attempt, the learned (or floor) timeout.
    Probe,
    /// A scan of a unit that may not exist: one attempt, the full response
    /// timeout, nothing learned.
    Scan,
}

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
    /// Silence kept after a timeout or bad frame, discarding anything late;
    /// [`Guard::Auto`] also learns each drive's reply timeout.
    pub guard: Guard,
    /// The least a learned reply timeout may be: room for a busy host's and
    /// an adapter's latency that the drive's own turnarounds do not show.
    pub reply_timeout_floor: Duration,
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
            reply_timeout_floor: DEFAULT_REPLY_TIMEOUT_FLOOR,
            broadcast_delay: Duration::from_millis(20),
            rs485: Rs485Settings::default(),
        }
    }
}

/// How long the line is kept after a failed attempt, discarding whatever
/// arrives, so that a late reply is not taken for the next request's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Guard {
    /// Sized by the wire: each drive's reply timeout is learned, and after
    /// it the line is kept as long as the longest reply the request can
    /// draw takes, plus t3.5 (a reply that started by the timeout ends in
    /// it); after a corrupted reply that ended, t3.5. A reply later still is
    /// kept from the wrong request by [`RtuMaster::held_until`].
    Auto,
    /// The full response timeout for every reply, and this long after every
    /// failed attempt: for drives that may answer later than the response
    /// timeout.
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
    /// The drive's turnaround for the reply taken: from the end of the
    /// request on the wire to the reply's first byte.
    pub turnaround: Option<Duration>,
    /// Replies taken after the learned timeout (a drive that slowed down).
    pub late_replies: u8,
    /// The drive's reply timeout after this transaction (what the next
    /// request to it waits for a first byte).
    pub reply_timeout: Duration,
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

/// True when a valid reply to `earlier` could pass the checks of a reply
/// to `later` (same function, same length): only then can a late reply be
/// taken for the wrong request's. Conservative: echoes of different writes
/// would fail the check, but are held too.
fn could_pass_for(earlier: &[u8], later: &[u8]) -> bool {
    earlier.first() == later.first()
        && rtu_frame::expected_response_length(earlier)
            == rtu_frame::expected_response_length(later)
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
    /// Limits of the learned reply timeouts.
    bounds: Bounds,
    /// Each unit's learned reply timeout, by unit address.
    timeouts: Box<[ReplyTimeout; 256]>,
    /// Each unit's request whose reply may still come, and until when.
    late: Box<[Option<LateWindow>; 256]>,
}

/// A request that got no reply in time, whose reply may still come until
/// the ceiling has passed.
#[derive(Debug, Clone)]
struct LateWindow {
    pdu: Vec<u8>,
    until: Instant,
}

impl RtuMaster {
    /// A master on an open port (a serial adapter or a serial device
    /// server's connection); must be created in the runtime that drives it.
    pub fn new(port: impl Into<Transport>, settings: MasterSettings) -> io::Result<Self> {
        let port = port.into();
        let mut bounds = Bounds::for_line(
            settings.line.t3_5(),
            settings.response_timeout,
            settings.reply_timeout_floor,
        );
        if matches!(port, Transport::Tcp { .. }) {
            // A serial device server hands bytes over a network: the wire's
            // timing reaches us late by as much as its packets and the
            // network's jitter, which its own turnarounds only partly show.
            bounds.margin = DELIVERY_ALLOWANCE;
        }
        Ok(Self {
            port,
            settings,
            timer: PreciseTimer::new()?,
            quiet_since: Instant::now(),
            buf: Box::new([0; 512]),
            stray: 0,
            tap: WireTap::detached(settings.line),
            bounds,
            timeouts: Box::new([ReplyTimeout::default(); 256]),
            late: Box::new([const { None }; 256]),
        })
    }

    /// Until when `pdu` must not be sent to `unit`: a reply to an earlier,
    /// different request to it that got none in time may still come (until
    /// the response timeout, the ceiling, has passed since it left), and a
    /// reply to that one could pass for this one's (same function, same
    /// length). `None` when it may go now. The same request again may go:
    /// the late reply is its answer. Broadcasts are never held.
    pub fn held_until(&self, unit: u8, pdu: &[u8], now: Instant) -> Option<Instant> {
        let late = self.late[usize::from(unit)].as_ref()?;
        (unit != 0 && late.until > now && late.pdu != pdu && could_pass_for(&late.pdu, pdu))
            .then_some(late.until)
    }

    /// The first moment after `now` a held request may go (the end of the
    /// earliest open late-reply window), if any is open.
    pub fn next_release(&self, now: Instant) -> Option<Instant> {
        self.late
            .iter()
            .flatten()
            .map(|late| late.until)
            .filter(|&until| until > now)
            .min()
    }

    /// The reply timeout `unit` gets now: learned, or the ceiling.
    pub fn reply_timeout(&self, unit: u8) -> Duration {
        self.timeouts[usize::from(unit)].timeout(&self.bounds)
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
        self.run(unit, pdu, max_attempts, Purpose::Transact).await
    }

    /// Sends `pdu` once to `unit`, a drive not known to answer (off, or not
    /// heard yet): no retry, and after a timeout in which nothing arrived
    /// only the guard a late reply needs (with [`Guard::Auto`]). Errors as
    /// for [`transact`](Self::transact).
    pub async fn probe(&mut self, unit: u8, pdu: &[u8]) -> Result<Report, PortFailure> {
        self.run(unit, pdu, Some(1), Purpose::Probe).await
    }

    /// Sends `pdu` once to `unit`, a unit that may not exist (a scan of the
    /// line): the full response timeout whatever was learned, nothing
    /// learned from it, and after a timeout the guard a reply starting at
    /// the timeout needs, so what a unit sends late is seen in the tap.
    /// Errors as for [`transact`](Self::transact).
    pub async fn scan(&mut self, unit: u8, pdu: &[u8]) -> Result<Report, PortFailure> {
        self.run(unit, pdu, Some(1), Purpose::Scan).await
    }

    async fn run(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
        purpose: Purpose,
    ) -> Result<Report, PortFailure> {
        let mut sent = false;
        self.attempts(unit, pdu, max_attempts, purpose, &mut sent)
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
        purpose: Purpose,
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
        let line = self.settings.line;
        let t35 = line.t3_5();
        let learn = self.settings.guard == Guard::Auto && purpose != Purpose::Scan;
        let expected = rtu_frame::expected_response_length(pdu).unwrap_or(rtu_frame::MAX_FRAME);
        let slot = usize::from(unit);
        self.stray = 0;
        let mut started = None;
        let mut busy = Duration::ZERO;
        let mut last_fault = None;
        let mut idle_before = Duration::ZERO;
        let mut late_replies = 0;
        // Karn: once an attempt got no reply in time, a reply may answer an
        // earlier attempt, so its turnaround is no clean sample.
        let mut retried_after_timeout = false;
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
            let wire_end = sent_at + line.wire_time(frame.len());

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
                    turnaround: None,
                    late_replies: 0,
                    reply_timeout: Duration::ZERO,
                });
            }

            // The learned timeout decides when to give up on the first
            // byte; the guard after it (the longest reply this request can
            // draw, t3.5, and the learned timeout again) is still this
            // request's time: nothing else has been sent, so a reply that
            // starts in it is this request's, taken and learned from. The
            // last attempt of a transaction waits the whole response
            // timeout: a drive is never reported silent sooner than
            // configured, and a reply the machine made late still counts.
            let ceiling = self.settings.response_timeout;
            let estimate = &self.timeouts[slot];
            let timeout = match purpose {
                Purpose::Probe => estimate.probe_timeout(&self.bounds),
                Purpose::Transact => estimate.timeout(&self.bounds),
                Purpose::Scan => ceiling,
            };
            let last_of_transaction = attempt == attempts_allowed && purpose == Purpose::Transact;
            let listen = if !learn || last_of_transaction {
                ceiling
            } else {
                // Never longer than a reply starting at the ceiling takes.
                (timeout + line.wire_time(expected) + t35 + timeout)
                    .min(ceiling + line.wire_time(expected) + t35)
            };
            let (received, first_byte) = self
                .receive(unit, pdu, wire_end + listen, wire_end + ceiling.max(listen))
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
            let turnaround = first_byte.map(|t| t.saturating_duration_since(wire_end));
            match checked {
                Ok(reply) => {
                    let outcome = if reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0) {
                        Outcome::Exception
                    } else {
                        Outcome::Ok
                    };
                    if let (true, Some(turnaround)) = (learn, turnaround) {
                        let estimate = &mut self.timeouts[slot];
                        if turnaround > timeout {
                            estimate.late(turnaround);
                            late_replies += 1;
                        } else if !retried_after_timeout {
                            estimate.sample(turnaround);
                        }
                    }
                    return Ok(Report {
                        outcome,
                        reply: Some(reply),
                        attempts: attempt,
                        fault: None,
                        on_wire: end - *started.get_or_insert(sent_at),
                        busy,
                        stray_bytes: self.stray,
                        idle_before,
                        turnaround,
                        late_replies,
                        reply_timeout: self.reply_timeout(unit),
                    });
                }
                Err(fault) => {
                    let guard_start = Instant::now();
                    match (self.settings.guard, &fault) {
                        // A unit scanned: keep the line as long as a reply
                        // starting at the timeout takes, so nothing it sends
                        // late lands in the next unit's read.
                        (Guard::Auto, Fault::Timeout) if purpose == Purpose::Scan => {
                            self.guard(line.wire_time(expected) + t35).await?;
                        }
                        (Guard::Auto, Fault::Timeout) => {
                            // Nothing came while a reply could start and end:
                            // one may still come, later, until the ceiling.
                            self.timeouts[slot].timed_out();
                            retried_after_timeout = true;
                            self.late[slot] = Some(LateWindow {
                                pdu: pdu.to_vec(),
                                until: wire_end
                                    + self.settings.response_timeout
                                    + line.wire_time(expected)
                                    + t35,
                            });
                            self.flush_input()?;
                        }
                        // A frame came and ended (bad CRC, wrong length or
                        // content): t3.5 of silence after it is enough, and
                        // the next attempt waits for it anyway.
                        (Guard::Auto, _) => {}
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
            turnaround: None,
            late_replies,
            reply_timeout: self.reply_timeout(unit),
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
    /// protocol fault, `Err` for a port failure; with the instant its first
    /// byte was read.
    ///
    /// `first_byte_by` is the wait for the reply's first byte. Once bytes
    /// flow, the deadline follows the wire: the bytes still to come at the
    /// character time, plus t3.5 and the [`DELIVERY_ALLOWANCE`], counted
    /// from the last bytes received, but never earlier than the timeout. A
    /// 125-register reply takes 265 ms at 9600 baud; a drive that starts it
    /// in time gets it through whatever the timeout.
    ///
    /// A whole frame from another unit is a late reply to an earlier
    /// request: it is discarded as stray bytes and the wait goes on, moved
    /// by the time that frame held the line, but never past `latest`.
    async fn receive(
        &mut self,
        unit: u8,
        request: &[u8],
        first_byte_by: Instant,
        latest: Instant,
    ) -> io::Result<(Result<usize, Fault>, Option<Instant>)> {
        let line = self.settings.line;
        let t35 = line.t3_5();
        let expected = rtu_frame::expected_response_length(request).unwrap_or(rtu_frame::MAX_FRAME);
        let mut len = 0;
        let mut last_byte = Instant::now();
        let mut first_byte = None;
        let mut first_byte_by = first_byte_by;
        let mut deadline = first_byte_by;
        loop {
            // A full buffer holds no Modbus frame (the longest is 256 bytes):
            // it is noise. Reading on would read into an empty slice, whose
            // Ok(0) means an unplugged adapter.
            if len >= self.buf.len() {
                self.quiet_since = last_byte;
                return Ok((
                    Err(Fault::Mismatch("reply longer than any Modbus frame")),
                    first_byte,
                ));
            }
            let complete = match rtu_frame::response_length(&self.buf[..len]) {
                FrameLength::Known(n) if len >= n => Some(n),
                FrameLength::Known(_) | FrameLength::NeedMore => None,
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
                            Some(len)
                        }
                    }
                }
            };
            if let Some(n) = complete {
                self.quiet_since = last_byte;
                if self.buf[0] == unit || last_byte >= latest {
                    return Ok((Ok(n), first_byte));
                }
                // Another unit's late reply: never ours. Discard it and wait
                // on, as long again as it held the line.
                self.stray += n;
                self.tap.stray(&self.buf[..n], last_byte);
                let held = first_byte.map_or(Duration::ZERO, |t| last_byte - t);
                self.buf.copy_within(n..len, 0);
                len -= n;
                first_byte = None;
                first_byte_by = (first_byte_by + held + t35).min(latest);
                deadline = first_byte_by;
                if len > 0 {
                    first_byte = Some(last_byte);
                }
                continue;
            }
            let need = match rtu_frame::response_length(&self.buf[..len]) {
                FrameLength::Known(n) => Some(n),
                _ => None,
            };
            if len > 0 {
                let remaining = if self.buf[0] == unit {
                    need.unwrap_or(expected)
                } else {
                    need.unwrap_or(rtu_frame::MAX_FRAME)
                }
                .saturating_sub(len);
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
                    first_byte.get_or_insert(last_byte);
                }
                Err(_) if len == 0 => return Ok((Err(Fault::Timeout), None)),
                Err(_) => {
                    self.quiet_since = last_byte;
                    let fault = if self.buf[0] == unit {
                        Fault::Mismatch("reply cut short")
                    } else {
                        Fault::Mismatch("reply from another unit")
                    };
                    return Ok((Err(fault), first_byte));
                }
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
