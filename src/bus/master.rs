//! The Modbus RTU master of one serial line.
//!
//! Rules it enforces, because RTU frames carry no length and no transaction id:
//! - one frame in flight; each request goes out in one write, only after the
//!   line has been silent for t3.5, or the addressed drive's own gap with
//!   `[bus] interframe` ([`interframe`](super::interframe): tried shorter only
//!   on polls, back to the spec at the drive's first fault); bytes seen
//!   meanwhile are stray: counted, discarded, and the silence starts again;
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
//!   timeout decides when to give up: the line has then been silent for
//!   longer than t3.5, so the retry (the same request, whose answer a late
//!   reply is) goes at once. A probe's guard after it (the longest reply
//!   the request can draw on the wire, t3.5, and the timeout again) is
//!   still the probe's own: a reply that starts in it is taken. A frame
//!   from another unit (a late reply to an earlier request) is discarded
//!   and the wait goes on. A corrupted reply that ended needs only t3.5.
//!   The last attempt of a transaction waits the whole ceiling;
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

mod line;
mod retune;

use std::io;
use std::time::{Duration, Instant};

pub use super::fault::Fault;
use super::interframe::{Gaps, Interframe, Limits, SERIAL_ADAPTER_LATENCY, Silence, Use};
use super::port::Rs485Settings;
use super::reply_timeout::{Bounds, ReplyTimeout};
use super::stats::Outcome;
use super::tap::WireTap;
use super::transport::Transport;
use crate::clock::PreciseTimer;
use crate::modbus::function::EXCEPTION_BIT;
use crate::modbus::reply::{self, Mismatch};
use crate::modbus::rtu_frame;
use crate::modbus::timing::LineTiming;

/// Time allowed, beyond the wire's own pace, for the rest of a reply to
/// reach the master once it has begun: USB adapters hand bytes over in
/// packets up to 16 ms apart (FTDI's default latency timer), and the system
/// may run the reader late. A reply that pauses longer is cut short.
pub const DELIVERY_ALLOWANCE: Duration = Duration::from_millis(20);

/// How long before the line is free the scheduler picks the next job: the
/// choice and the frame are ready when the silence ends. The scheduler's
/// timer ([`PreciseTimer`], armed its learned wake-up latency early) wakes
/// the bus thread this long before the end, and the rest, shorter than a
/// wake-up would come, is waited out awake: one wake-up a transaction,
/// not a second timer for the last stretch. An emergency that arrives in
/// this last stretch goes on the next turn.
pub const PICK_AHEAD: Duration = Duration::from_micros(25);

/// The default least learned reply timeout (`reply_timeout_floor_ms`): a
/// drive answering in 0.5 ms at 115200 baud is waited for at least this
/// long, and a reply that starts later still is taken in the guard after it.
pub const DEFAULT_REPLY_TIMEOUT_FLOOR: Duration = Duration::from_millis(3);

/// What a transaction is for, which decides how long it waits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Purpose {
    /// A request to a drive: its learned timeout, the ceiling on the last
    /// attempt; the silence before it as [`Use`] says.
    Transact(Use),
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
    /// The silence before each request (`[bus] interframe`).
    pub interframe: Interframe,
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
            interframe: Interframe::Spec,
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
    /// The silence the drive's requests get after this transaction.
    pub interframe: Duration,
    /// Times the drive's learned gap fell back to the spec, since start.
    pub interframe_fallbacks: u64,
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
    /// The silence before each unit's requests.
    gaps: Gaps,
}

/// What the attempts of one transaction have added up to so far.
#[derive(Debug, Default)]
struct Run {
    /// When its first byte went out.
    started: Option<Instant>,
    /// When the wait for the last reply ended.
    ended: Option<Instant>,
    busy: Duration,
    last_fault: Option<Fault>,
    idle_before: Duration,
    late_replies: u8,
    /// The turnaround of the reply taken.
    turnaround: Option<Duration>,
    /// Karn: once an attempt got no reply in time, a reply may answer an
    /// earlier attempt, so its turnaround is no clean sample.
    retried_after_timeout: bool,
    /// The reply taken began sooner after its request than any drive can
    /// answer (3.5 character times): it answers an earlier attempt.
    early_reply: bool,
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
        let mut interframe = settings.interframe;
        if matches!(port, Transport::Tcp { .. }) {
            // A serial device server hands bytes over a network: the wire's
            // timing reaches us late by as much as its packets and the
            // network's jitter, which its own turnarounds only partly show.
            bounds.margin = DELIVERY_ALLOWANCE;
            // Nor can the silences be timed from here: a learned gap would
            // be the network's, not the drive's.
            if interframe == Interframe::Auto {
                interframe = Interframe::Spec;
            }
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
            gaps: Gaps::new(
                interframe,
                Limits::for_line(settings.line, SERIAL_ADAPTER_LATENCY),
            ),
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

    /// The silence `unit`'s requests get now (the spec's, a fixed one, or
    /// the drive's learned gap).
    pub fn interframe(&self, unit: u8) -> Duration {
        self.gaps.confirmed(unit)
    }

    /// True when a poll of `unit` would try a shorter silence than its
    /// gap now (with `interframe = "auto"`): a poll in idle time helps it
    /// learn.
    pub fn wants_trial(&self, unit: u8, now: Instant) -> bool {
        self.gaps.wants_trial(unit, now)
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
        self.transact_as(unit, pdu, max_attempts, Use::Command)
            .await
    }

    /// [`transact`](Self::transact) for a request of kind `use_`: a poll
    /// may try a shorter silence before it, an emergency keeps to a gap
    /// answered lately (see [`interframe`](super::interframe)).
    pub async fn transact_as(
        &mut self,
        unit: u8,
        pdu: &[u8],
        max_attempts: Option<u8>,
        use_: Use,
    ) -> Result<Report, PortFailure> {
        self.run(unit, pdu, max_attempts, Purpose::Transact(use_))
            .await
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
        self.stray = 0;
        let mut run = Run::default();
        for attempt in 1..=attempts_allowed {
            let silence = match purpose {
                Purpose::Transact(use_) => self.gaps.silence(unit, use_, Instant::now()),
                Purpose::Probe => self.gaps.silence(unit, Use::Command, Instant::now()),
                // A unit that may not exist: the spec, which every drive knows.
                Purpose::Scan => Silence {
                    gap: self.gaps.limits().spec,
                    trial: false,
                },
            };
            self.wait_for_silence(silence.gap, Duration::ZERO, true)
                .await?;
            let quiet_since = self.quiet_since;
            let sent_at = self.send(&frame, sent).await?;
            let left = sent_at.saturating_duration_since(quiet_since);
            if run.started.is_none() {
                run.idle_before = left;
            }
            self.tap.request(unit, &frame, sent_at, attempt, left);
            run.started.get_or_insert(sent_at);
            let wire_end = sent_at + self.settings.line.wire_time(frame.len());
            if unit == 0 {
                return Ok(self.broadcast(sent_at, wire_end, attempt, run));
            }
            let last = attempt == attempts_allowed && matches!(purpose, Purpose::Transact(_));
            match self
                .exchange(unit, pdu, purpose, last, sent_at, &mut run)
                .await?
            {
                Ok((outcome, reply)) if run.early_reply && run.retried_after_timeout => {
                    // The late answer to the attempt that timed out: the
                    // drive understood the silence before that one.
                    self.gaps.answered_late(unit, Instant::now());
                    return Ok(self.report(unit, outcome, Some(reply), attempt, None, run));
                }
                Ok((outcome, reply)) => {
                    self.gaps
                        .answered(unit, left, silence.trial, Instant::now());
                    return Ok(self.report(unit, outcome, Some(reply), attempt, None, run));
                }
                Err(fault) => {
                    self.gaps.failed(unit, silence.trial, Instant::now());
                    run.last_fault = Some(fault);
                }
            }
        }
        let fault = run.last_fault.clone().unwrap_or(Fault::Timeout);
        run.turnaround = None;
        run.ended = None;
        Ok(self.report(
            unit,
            fault_outcome(&fault),
            None,
            attempts_allowed,
            Some(fault),
            run,
        ))
    }

    /// A broadcast went out: nobody answers, the drives get their time.
    fn broadcast(&mut self, sent_at: Instant, wire_end: Instant, attempt: u8, run: Run) -> Report {
        self.quiet_since = wire_end + self.settings.broadcast_delay;
        Report {
            outcome: Outcome::Ok,
            reply: Some(Vec::new()),
            attempts: attempt,
            fault: None,
            on_wire: wire_end - sent_at,
            busy: run.busy + (self.quiet_since - sent_at) + self.settings.line.t3_5(),
            stray_bytes: self.stray,
            idle_before: run.idle_before,
            turnaround: None,
            late_replies: 0,
            reply_timeout: Duration::ZERO,
            interframe: self.gaps.limits().spec,
            interframe_fallbacks: 0,
        }
    }

    /// The report of a transaction to `unit` that ended so.
    fn report(
        &self,
        unit: u8,
        outcome: Outcome,
        reply: Option<Vec<u8>>,
        attempts: u8,
        fault: Option<Fault>,
        run: Run,
    ) -> Report {
        Report {
            outcome,
            reply,
            attempts,
            fault,
            on_wire: run.started.map_or(Duration::ZERO, |s| {
                run.ended.unwrap_or_else(Instant::now) - s
            }),
            busy: run.busy,
            stray_bytes: self.stray,
            idle_before: run.idle_before,
            turnaround: run.turnaround,
            late_replies: run.late_replies,
            reply_timeout: self.reply_timeout(unit),
            interframe: self.gaps.confirmed(unit),
            interframe_fallbacks: self.gaps.fallbacks(unit),
        }
    }

    /// Waits for the reply to the request that went out at `sent_at`,
    /// checks it and learns from it: the reply PDU, or the attempt's fault
    /// (after the guard it calls for).
    async fn exchange(
        &mut self,
        unit: u8,
        pdu: &[u8],
        purpose: Purpose,
        last: bool,
        sent_at: Instant,
        run: &mut Run,
    ) -> io::Result<Result<(Outcome, Vec<u8>), Fault>> {
        let line = self.settings.line;
        let t35 = line.t3_5();
        // The frame: unit, PDU, CRC.
        let wire_end = sent_at + line.wire_time(pdu.len() + 3);
        let learn = self.settings.guard == Guard::Auto && purpose != Purpose::Scan;
        let expected = rtu_frame::expected_response_length(pdu).unwrap_or(rtu_frame::MAX_FRAME);
        // The learned timeout decides when to give up on the first byte. A
        // transaction's attempt then retries at once (the line has been
        // silent longer than t3.5, and a late reply answers the retry's
        // same request); a probe keeps the line as long as a reply
        // starting then takes, and the timeout again, as its own. The last
        // attempt of a transaction waits the whole response timeout: a
        // drive is never reported silent sooner than configured.
        let ceiling = self.settings.response_timeout;
        let estimate = &self.timeouts[usize::from(unit)];
        let timeout = match purpose {
            Purpose::Probe => estimate.probe_timeout(&self.bounds),
            Purpose::Transact(_) => estimate.timeout(&self.bounds),
            Purpose::Scan => ceiling,
        };
        let listen = match purpose {
            _ if !learn || last => ceiling,
            Purpose::Transact(_) => timeout,
            // Never longer than a reply starting at the ceiling takes.
            _ => (timeout + line.wire_time(expected) + t35 + timeout)
                .min(ceiling + line.wire_time(expected) + t35),
        };
        let (received, first_byte) = self
            .receive(unit, pdu, wire_end + listen, wire_end + ceiling.max(listen))
            .await?;
        // The line is busy with our own frame until it has left the wire,
        // whatever was read meanwhile (a late reply, handed over at once).
        self.quiet_since = self.quiet_since.max(wire_end);
        let end = Instant::now();
        run.ended = Some(end);
        run.busy += (end - sent_at) + t35;
        let framed = received.as_ref().ok().copied();
        let checked = received.and_then(|len| {
            reply::check(unit, pdu, &self.buf[..len]).map_err(|m| match m {
                Mismatch::Crc => Fault::Crc,
                other => Fault::Mismatch(other.describe()),
            })
        });
        self.tap
            .reply(framed.map(|n| &self.buf[..n]), end, checked.as_ref().err());
        let turnaround = first_byte.map(|t| t.saturating_duration_since(wire_end));
        run.early_reply = first_byte.is_some_and(|t| t < wire_end + line.char_time() * 7 / 2);
        match checked {
            Ok(reply) => {
                let outcome = if reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0) {
                    Outcome::Exception
                } else {
                    Outcome::Ok
                };
                if let (true, Some(turnaround)) = (learn, turnaround) {
                    let estimate = &mut self.timeouts[usize::from(unit)];
                    if turnaround > timeout {
                        estimate.late(turnaround);
                        run.late_replies += 1;
                    } else if !run.retried_after_timeout {
                        estimate.sample(turnaround);
                    }
                }
                run.turnaround = turnaround;
                Ok(Ok((outcome, reply)))
            }
            Err(fault) => {
                let guard_start = Instant::now();
                self.after_fault(unit, pdu, purpose, last, &fault, wire_end, run)
                    .await?;
                run.busy += guard_start.elapsed();
                Ok(Err(fault))
            }
        }
    }

    /// What the line needs after an attempt to `unit` failed with `fault`:
    /// its request ended on the wire at `wire_end`.
    #[allow(clippy::too_many_arguments)]
    async fn after_fault(
        &mut self,
        unit: u8,
        pdu: &[u8],
        purpose: Purpose,
        last: bool,
        fault: &Fault,
        wire_end: Instant,
        run: &mut Run,
    ) -> io::Result<()> {
        let line = self.settings.line;
        let t35 = line.t3_5();
        let expected = rtu_frame::expected_response_length(pdu).unwrap_or(rtu_frame::MAX_FRAME);
        let slot = usize::from(unit);
        match (self.settings.guard, fault) {
            // A unit scanned: keep the line as long as a reply starting at
            // the timeout takes, so nothing it sends late lands in the next
            // unit's read.
            (Guard::Auto, Fault::Timeout) if purpose == Purpose::Scan => {
                self.guard(line.wire_time(expected) + t35).await?;
            }
            (Guard::Auto, Fault::Timeout) => {
                // Nothing came while a reply could start: one may still
                // come, later, until the ceiling; until then nothing it
                // could pass for the answer to goes to that drive.
                self.timeouts[slot].timed_out();
                run.retried_after_timeout = true;
                self.late[slot] = Some(LateWindow {
                    pdu: pdu.to_vec(),
                    until: wire_end
                        + self.settings.response_timeout
                        + line.wire_time(expected)
                        + t35,
                });
                if matches!(purpose, Purpose::Transact(_)) && !last {
                    // Silent since the request ended, longer than t3.5:
                    // the retry may go now.
                    self.quiet_since = wire_end;
                } else {
                    self.flush_input()?;
                }
            }
            // A frame came and ended (bad CRC, wrong length or content):
            // t3.5 of silence after it is enough, and the next attempt
            // waits for it anyway.
            (Guard::Auto, _) => {}
            (Guard::Fixed(time), _) => self.guard(time).await?,
        }
        Ok(())
    }

    /// When the line may carry the next request: the least gap any request
    /// may get (t3.5 with the spec's silences) after the end of the last
    /// frame (later after a broadcast's turnaround).
    pub fn line_free_at(&self) -> Instant {
        self.quiet_since + self.gaps.least()
    }

    /// Waits until the line may carry the next request (t3.5 of silence),
    /// less [`PICK_AHEAD`]. The scheduler calls this *before* it picks the
    /// next job, so a command that arrives during the silence goes next
    /// instead of waiting for one more poll; [`transact`](Self::transact)
    /// then waits out the rest. Returns the stray bytes discarded meanwhile.
    pub async fn settle(&mut self) -> io::Result<usize> {
        self.stray = 0;
        self.wait_for_silence(self.gaps.least(), PICK_AHEAD, true)
            .await?;
        Ok(std::mem::take(&mut self.stray))
    }
}
