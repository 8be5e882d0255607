//! The simulated RS-485 wire: frames requests from the master's bytes (on a
//! pty, or on TCP as a serial device server serves them) and puts replies
//! back at the pace of the configured baud rate.
//!
//! A pty carries bytes in microseconds whatever the baud rate, so the wire's
//! timing is modelled here, in one place:
//! - A request occupies the wire from the moment its first byte is read (or
//!   from the end of the previous activity, if the master sent it too early)
//!   for `wire_time(len)`.
//! - Requests are framed by [`request_length`] when the function code tells
//!   the length, else by 3.5 characters of silence; a partial frame followed
//!   by that silence is dropped.
//! - The reply starts no earlier than the end of the request's wire time +
//!   t3.5 + the drive's turnaround (+ injected lateness); its byte `i` is on
//!   the wire at `reply_start + wire_time(i + 1)` and is handed over as the
//!   [`Delivery`] says: a UART's, the first and the last byte as they arrive
//!   (the bytes between with the last, or in pieces a master framing by
//!   silence still takes for one frame), a USB adapter's in late chunks.
//!   Bytes already due when a wakeup comes late are written together; the
//!   wire's own timing (and so the silence the master owes) does not change.
//! - A request that is not answered ends the activity at the later of its
//!   own end (from its first byte's arrival) and the previous activity's: a
//!   request heard over a reply overlapped it on the wire.
//! - A request whose first byte arrives less than t3.5 after the end of the
//!   previous activity (the last reply byte's scheduled end, or the end of the
//!   previous request when it had no reply) is a gap violation. The check is
//!   strict: pty latency only makes bytes arrive later, so a master that
//!   waits t3.5 after the last byte it received never trips it.
//!
//! The wire keeps reading while it waits, so arrival times stay exact even
//! while a reply is being paced out or a late reply is pending; requests are
//! still answered one after the other, as a drive does.

use std::io;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::bus::Bus;
use super::bus::lock;
use super::config::SimConfig;
use super::delivery::Delivery;
use super::pty::Pty;
use super::tcp::{Disconnects, TcpLine};
use crate::clock::PreciseTimer;
use crate::modbus::rtu_frame::{
    FrameLength, MAX_FRAME, MIN_FRAME, request_length, response_length,
};
use crate::modbus::timing::LineTiming;

/// Bytes kept waiting to be framed; beyond this the line is garbage.
const RX_LIMIT: usize = 4 * MAX_FRAME;

/// Received bytes not yet framed, with the time each was read.
struct Rx {
    bytes: Vec<u8>,
    arrivals: Vec<Instant>,
}

impl Rx {
    fn new() -> Self {
        Rx {
            bytes: Vec::with_capacity(RX_LIMIT),
            arrivals: Vec::with_capacity(RX_LIMIT),
        }
    }

    fn push(&mut self, data: &[u8], at: Instant) {
        self.bytes.extend_from_slice(data);
        self.arrivals.resize(self.bytes.len(), at);
    }

    fn consume(&mut self, n: usize) {
        let n = n.min(self.bytes.len());
        self.bytes.drain(..n);
        self.arrivals.drain(..n);
    }

    fn clear(&mut self) {
        self.bytes.clear();
        self.arrivals.clear();
    }
}

/// When a reply is given up instead of sent.
#[derive(Debug, Clone, Copy)]
enum GiveUp {
    /// Sent however late.
    Never,
    /// Not sent when its first byte would go out more than this late.
    Late(Duration),
    /// As `Late`, and not sent when the master has begun another frame
    /// before the reply's first byte: the master gave up waiting for it
    /// (its own timeout, possibly learned and shorter than the simulator's
    /// lag), so sending it would only cross that frame.
    LateOrOvertaken(Duration),
}

/// What became of a paced reply.
#[derive(Debug, Clone, Copy)]
enum Paced {
    /// Sent; the scheduled end of its last byte on the wire, and whether its
    /// first byte went out more than t1.5 after its time (the machine kept
    /// this thread from running): the master may have given up on it and
    /// spoken over it, so its end says nothing of the master's silence.
    Sent { end: Instant, behind: bool },
    /// Not sent: the simulator fell too far behind.
    Late,
    /// Not sent: the master had begun another frame.
    Overtaken,
}

/// Where the master is.
enum Line {
    /// Behind a pty, as on a serial adapter.
    Pty(Pty),
    /// On TCP, as behind a serial device server.
    Tcp(TcpLine),
}

impl Line {
    async fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self {
            Line::Pty(pty) => pty.master().read(buf).await,
            Line::Tcp(tcp) => tcp.read(buf).await,
        }
    }

    async fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        match self {
            Line::Pty(pty) => pty.master().write_all(bytes).await,
            Line::Tcp(tcp) => tcp.write_all(bytes).await,
        }
    }

    /// The baud rate the master set on its end of the pty (the pty's two
    /// ends share one termios), if it can be read.
    fn master_baud(&mut self) -> Option<u32> {
        match self {
            Line::Pty(pty) => tokio_serial::SerialPort::baud_rate(pty.master()).ok(),
            Line::Tcp(_) => None,
        }
    }
}

/// The wire task's state.
pub(crate) struct Wire {
    line_io: Line,
    /// Where masters connect: the pty's path, or `tcp://ip:port`.
    endpoint: std::path::PathBuf,
    /// TCP connections accepted, as last counted.
    connections: u64,
    bus: Arc<Mutex<Bus>>,
    line: LineTiming,
    turnaround: Duration,
    /// See [`SimConfig::max_lag`](super::config::SimConfig::max_lag).
    max_lag: Option<Duration>,
    timer: PreciseTimer,
    rx: Rx,
    tx: Vec<u8>,
    /// When each byte of `tx` is handed to the master.
    release: Vec<Instant>,
    delivery: Delivery,
    /// Draws the delivery's jitter (its own stream: the faults' draws stay
    /// the same whatever the delivery).
    rng: ChaCha8Rng,
    /// End of the last wire activity.
    quiet_from: Option<Instant>,
    /// See [`SimConfig::echo`].
    echo: bool,
    /// See [`SimConfig::check_master_baud`].
    check_master_baud: bool,
}

impl Wire {
    /// Opens the pty (or listens on `config.listen`) and prepares the
    /// timing for `config`; must run inside the simulator's runtime.
    pub(crate) fn new(config: &SimConfig, bus: Arc<Mutex<Bus>>) -> io::Result<Self> {
        let line_io = match config.listen {
            Some(address) => Line::Tcp(TcpLine::bind(address)?),
            None => Line::Pty(Pty::open()?),
        };
        let endpoint = match &line_io {
            Line::Pty(pty) => pty.path().to_path_buf(),
            Line::Tcp(tcp) => tcp.endpoint().into(),
        };
        Ok(Wire {
            line_io,
            endpoint,
            connections: 0,
            bus,
            line: LineTiming::new_8n1(config.baud),
            turnaround: Duration::from_secs_f64(config.turnaround_ms.max(0.0) / 1000.0),
            max_lag: config.max_lag,
            timer: PreciseTimer::new()?,
            rx: Rx::new(),
            tx: Vec::with_capacity(MAX_FRAME),
            release: Vec::with_capacity(MAX_FRAME),
            delivery: config.delivery,
            rng: ChaCha8Rng::seed_from_u64(config.seed ^ 0xDE11_7E12),
            quiet_from: None,
            echo: config.echo,
            check_master_baud: config.check_master_baud,
        })
    }

    /// Where masters connect: the pty slave's path, or `tcp://ip:port`.
    pub(crate) fn path(&self) -> &std::path::Path {
        &self.endpoint
    }

    /// On TCP, the handle that closes the master's connection on request.
    pub(crate) fn disconnects(&self) -> Option<Arc<Disconnects>> {
        match &self.line_io {
            Line::Tcp(tcp) => Some(tcp.disconnects()),
            Line::Pty(_) => None,
        }
    }

    /// Serves requests until an I/O error (or until the caller drops it).
    pub(crate) async fn serve(mut self) -> io::Result<()> {
        loop {
            let len = self.next_frame().await?;
            self.answer(len).await?;
        }
    }

    /// Waits until the received bytes hold a whole frame; returns its length.
    async fn next_frame(&mut self) -> io::Result<usize> {
        loop {
            let Some(&first) = self.rx.arrivals.first() else {
                self.read_until(None, false).await?;
                continue;
            };
            let length = request_length(&self.rx.bytes);
            if let FrameLength::Known(n) = length
                && n <= MAX_FRAME
                && self.rx.bytes.len() >= n
            {
                return Ok(n);
            }
            if self.rx.bytes.len() > MAX_FRAME {
                // No frame is that long: the line carries garbage.
                self.drop_partial();
                continue;
            }
            // Wait for the rest, or for the silence that ends the frame.
            let start = self.quiet_from.map_or(first, |q| first.max(q));
            let wire_end = start + self.line.wire_time(self.rx.bytes.len());
            let last = self.rx.arrivals.last().copied().unwrap_or(first);
            let silence = wire_end.max(last) + self.line.t3_5();
            if self.read_until(Some(silence), false).await? {
                continue;
            }
            match length {
                FrameLength::BySilence if self.rx.bytes.len() >= MIN_FRAME => {
                    return Ok(self.rx.bytes.len());
                }
                _ => self.drop_partial(),
            }
        }
    }

    fn drop_partial(&mut self) {
        self.rx.clear();
        lock(&self.bus).stats_mut().truncated_frames += 1;
    }

    /// Hands the first `len` received bytes to the drives and puts their
    /// answer on the wire.
    async fn answer(&mut self, len: usize) -> io::Result<()> {
        let Some(&arrival) = self.rx.arrivals.first() else {
            return Ok(());
        };
        let t3_5 = self.line.t3_5();
        let violation = self.quiet_from.is_some_and(|q| arrival < q + t3_5);
        let start = self.quiet_from.map_or(arrival, |q| arrival.max(q));
        let wire_end = start + self.line.wire_time(len);
        let outcome = {
            let mut bus = lock(&self.bus);
            if violation {
                bus.stats_mut().gap_violations += 1;
            }
            let silence = self
                .quiet_from
                .map(|q| arrival.saturating_duration_since(q));
            if let Some(gap) = silence {
                bus.record_gap(gap);
            }
            bus.request(&self.rx.bytes[..len], Instant::now(), silence, &mut self.tx)
        };
        self.rx.consume(len);
        if !outcome.reply {
            // Unanswered, the request's bytes end the activity where they
            // ended on the wire: a request heard over the end of the last
            // reply (the master gave up on a reply this thread sent late)
            // overlapped it, it did not follow it.
            let heard_end = arrival + self.line.wire_time(len);
            self.quiet_from = Some(self.quiet_from.map_or(heard_end, |q| q.max(heard_end)));
            return Ok(());
        }
        if let Some(master_baud) = self.master_baud_if_other() {
            let read = super::uart::resample(&self.tx, self.line.baud(), master_baud);
            self.tx = read;
        }
        // A drive answers once it has parted the request from what follows:
        // t3.5 by the spec, sooner for a drive with a shorter frame gap.
        let reply_start =
            wire_end + outcome.frame_gap.unwrap_or(t3_5) + self.turnaround + outcome.late;
        // The daemon's own simulator gives a reply up once the master has
        // (see `SimConfig::max_lag`); a reply made late on purpose is sent
        // however late, as a late drive's is.
        let give_up = match self.max_lag {
            Some(max_lag) if outcome.late.is_zero() => GiveUp::LateOrOvertaken(max_lag),
            Some(max_lag) => GiveUp::Late(max_lag),
            None => GiveUp::Never,
        };
        let (reply_end, behind) = match self.send_paced(reply_start, give_up).await? {
            Paced::Sent { end, behind } => (end, behind),
            unsent => {
                let mut bus = lock(&self.bus);
                let stats = bus.stats_mut();
                stats.replies -= 1;
                stats.stalled += 1;
                // Overtaken: the master gave up on the reply and spoke; this
                // thread was behind the wire (kept from running when the
                // request came, or since), so the time it noted for the
                // request's end says nothing of the master's silence.
                self.quiet_from = match unsent {
                    Paced::Overtaken => None,
                    _ => Some(wire_end),
                };
                return Ok(());
            }
        };
        // A reply sent late: the master's wait for it may have ended before
        // it came, so the master's next silence is judged from the end of
        // its own request only, which it surely heard.
        self.quiet_from = Some(if behind { wire_end } else { reply_end });
        if let Some(noise) = outcome.noise {
            // Noise is not a frame: it does not move the end of activity.
            self.tx.clear();
            self.tx.extend_from_slice(noise.bytes());
            self.send_paced(reply_end + t3_5, GiveUp::Never).await?;
        }
        Ok(())
    }

    /// Writes `tx` one character time per byte from `start`, handed over as
    /// the delivery says; returns the scheduled end of the last byte on the
    /// wire, or why nothing was sent (`give_up`).
    async fn send_paced(&mut self, start: Instant, give_up: GiveUp) -> io::Result<Paced> {
        let len = self.tx.len();
        // A master reads a reply it knows the length of to that length; only
        // one it cannot (noise included) needs its bytes without a silence.
        let by_length = matches!(response_length(&self.tx), FrameLength::Known(n) if n == len);
        self.delivery.schedule(
            &self.line,
            start,
            len,
            by_length,
            &mut self.rng,
            &mut self.release,
        );
        let last = self.release.last().copied().unwrap_or(start);
        let mut sent = 0;
        let mut behind = false;
        while sent < len {
            let now = Instant::now();
            if sent == 0 {
                if let GiveUp::Late(max_lag) | GiveUp::LateOrOvertaken(max_lag) = give_up
                    && now > self.release[0] + max_lag
                {
                    tracing::info!(
                        behind_ms = (now - self.release[0]).as_millis() as u64,
                        "the simulator fell behind (the machine kept it from running): reply not sent"
                    );
                    return Ok(Paced::Late);
                }
                if let GiveUp::LateOrOvertaken(_) = give_up
                    && self.master_spoke().await?
                {
                    tracing::debug!(
                        "the master spoke before the reply began (it gave up waiting): reply not sent"
                    );
                    return Ok(Paced::Overtaken);
                }
            }
            let due = sent + self.release[sent..].partition_point(|&t| t <= now);
            if due > sent {
                if sent == 0 {
                    behind = now > self.release[0] + self.line.t1_5();
                }
                self.line_io.write_all(&self.tx[sent..due]).await?;
                sent = due;
            } else {
                // Only the last byte's time decides when the master may go on:
                // it is timed precisely, the others are allowed a little late.
                let next = self.release[sent];
                self.read_until(Some(next), next == last).await?;
            }
        }
        Ok(Paced::Sent {
            end: start + self.line.wire_time(len),
            behind,
        })
    }

    /// True when the master has sent bytes since the request being answered
    /// (read now, without waiting, what has arrived and not been read).
    async fn master_spoke(&mut self) -> io::Result<bool> {
        use futures_util::FutureExt;
        let mut buf = [0u8; 256];
        if let Some(read) = self.line_io.read(&mut buf).now_or_never() {
            let n = read?;
            if n > 0 {
                self.heard(&buf[..n], Instant::now()).await?;
            }
        }
        Ok(!self.rx.bytes.is_empty())
    }

    /// Reads what arrives until `deadline` (forever if `None`); true when
    /// bytes came in before it. A `precise` deadline is kept to microseconds
    /// (spinning its last stretch), others may be a little late.
    async fn read_until(&mut self, deadline: Option<Instant>, precise: bool) -> io::Result<bool> {
        let mut buf = [0u8; 256];
        let master = &mut self.line_io;
        let n = match deadline {
            None => master.read(&mut buf).await?,
            Some(deadline) => {
                tokio::select! {
                    read = master.read(&mut buf) => read?,
                    slept = async {
                        if precise {
                            self.timer.sleep_until(deadline).await
                        } else {
                            self.timer.sleep_until_relaxed(deadline).await
                        }
                    } => {
                        slept?;
                        return Ok(false);
                    }
                }
            }
        };
        if n == 0 {
            // The pty's slave side is held open, so this does not happen;
            // if it does, do not spin.
            tokio::time::sleep(Duration::from_millis(10)).await;
            return Ok(false);
        }
        self.heard(&buf[..n], Instant::now()).await?;
        Ok(true)
    }

    /// Takes bytes the master sent, read at `at`: echoed if the adapter
    /// echoes, heard at the wire's rate, kept for framing.
    async fn heard(&mut self, bytes: &[u8], at: Instant) -> io::Result<()> {
        if self.echo {
            self.line_io.write_all(bytes).await?;
        }
        match self.master_baud_if_other() {
            Some(master_baud) => {
                let heard = super::uart::resample(bytes, master_baud, self.line.baud());
                self.push_received(&heard, at);
            }
            None => self.push_received(bytes, at),
        }
        Ok(())
    }

    /// With [`SimConfig::check_master_baud`], the master's rate when it is
    /// not the wire's.
    fn master_baud_if_other(&mut self) -> Option<u32> {
        if !self.check_master_baud {
            return None;
        }
        self.line_io
            .master_baud()
            .filter(|&baud| baud != self.line.baud())
    }

    /// Keeps bytes read at `at` for framing.
    fn push_received(&mut self, bytes: &[u8], at: Instant) {
        if let Line::Tcp(tcp) = &self.line_io
            && tcp.accepted() != self.connections
        {
            // A new master: what the last one left half sent is not its.
            self.connections = tcp.accepted();
            self.rx.clear();
            lock(&self.bus).stats_mut().connections = self.connections;
        }
        if self.rx.bytes.len() + bytes.len() > RX_LIMIT {
            self.drop_partial();
        }
        self.rx.push(bytes, at);
    }
}
