//! One client connection: frames in, replies out, in request order.
//!
//! Requests are read and queued on the bus as soon as they arrive (up to
//! `max_pipelined` at once), so a pipelining client's requests wait in the
//! bus queue, where they take turns with every other client, rather than in
//! the socket. A write waits at most the bus's `queue_timeout_ms` from the
//! moment its last byte was read ([`super::arrivals`]), its wait for room
//! in the pipeline included: one its client gave up on is not sent. Replies are written in the order the requests came, whatever
//! order the buses finish them in: Modbus TCP clients may match replies by
//! transaction id, but many PLCs expect them in order.
//!
//! The connection ends when:
//! - the client closes it or it fails: requests still queued are cancelled,
//!   so the bus drops them before they reach the wire (the socket is read
//!   even while the pipeline is full, so a close is noticed);
//! - a malformed frame arrives: nothing after it is parsed (MBAP cannot be
//!   resynchronised), the requests accepted before it are answered, then the
//!   connection is closed and counted;
//! - nothing is pending and no whole request came for the idle timeout (a
//!   client that sends half a frame and stalls is idle too), or a reply could
//!   not be written for that long (a client that does not read);
//! - the daemon stops.
//!
//! The connection is a session of the control core: whatever the client
//! sends tells the core it is alive (which renews the leases of a network's
//! communication-loss function; requests are read even while the pipeline
//! is full), and its end, once the requests still queued are cancelled,
//! ends them with their stop.

use std::collections::VecDeque;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use bytes::{Buf, BytesMut};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::{Instant, Sleep};
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use super::arrivals::Arrivals;
use super::gateway::{Answer, Client, Gateway, Pending};
use super::mbap::{self, MAX_FRAME};
use crate::control::SessionGuard;
use crate::metrics::Metrics;

/// Bytes of unparsed requests a connection may buffer (about 250 frames)
/// beyond the ones queued on the bus.
const READ_BUFFER: usize = 64 * 1024;

/// Limits of one connection.
#[derive(Debug, Clone, Copy)]
pub struct ConnectionSettings {
    /// Close after this long with nothing pending and no whole request.
    pub idle_timeout: Duration,
    /// Requests waiting for the bus at once.
    pub max_pipelined: usize,
}

/// A request whose reply has not been written yet.
struct InFlight {
    transaction: u16,
    unit: u8,
    reply: Reply,
}

enum Reply {
    Ready(Vec<u8>),
    Pending(Pending),
}

impl InFlight {
    async fn ready(&mut self) {
        if let Reply::Pending(p) = &mut self.reply {
            p.wait().await;
        }
    }

    fn try_ready(&mut self) -> bool {
        match &mut self.reply {
            Reply::Ready(_) => true,
            Reply::Pending(p) => p.try_ready(),
        }
    }
}

/// The requests whose replies are not written yet, oldest first.
#[derive(Default)]
struct Pipeline {
    queue: VecDeque<InFlight>,
    /// A malformed frame came: nothing after it is parsed.
    malformed: bool,
    /// When the bytes still in the read buffer arrived.
    arrivals: Arrivals,
}

impl Pipeline {
    /// Takes every whole request in `buf`, up to the pipeline limit: each
    /// handed to the gateway (queued on the bus, or answered at once), the
    /// idle timer restarted. A malformed frame ends the parsing, counted
    /// and logged.
    async fn take(
        &mut self,
        buf: &mut BytesMut,
        (gateway, client): (&Gateway, &Client),
        max_pipelined: usize,
        mut idle: Pin<&mut Sleep>,
        idle_timeout: Duration,
    ) {
        while !self.malformed && self.queue.len() < max_pipelined {
            match mbap::parse(buf) {
                Ok(Some((frame, used))) => {
                    buf.advance(used);
                    let received = self
                        .arrivals
                        .take(used)
                        .unwrap_or_else(std::time::Instant::now);
                    idle.as_mut().reset(Instant::now() + idle_timeout);
                    let reply = match gateway
                        .handle(client, (frame.transaction, frame.unit), frame.pdu, received)
                        .await
                    {
                        Answer::Now(pdu) => Reply::Ready(pdu),
                        Answer::Pending(p) => Reply::Pending(p),
                        Answer::Silent => continue,
                    };
                    self.queue.push_back(InFlight {
                        transaction: frame.transaction,
                        unit: frame.unit,
                        reply,
                    });
                }
                Ok(None) => break,
                Err(e) => {
                    gateway.metrics().faces().tcp_malformed();
                    warn!(client = %client.peer, "malformed Modbus TCP frame: {e}; closing the connection after answering the {} request(s) before it", self.queue.len());
                    self.malformed = true;
                    buf.clear();
                    self.arrivals.clear();
                }
            }
        }
    }

    /// The replies ready at the head of the queue, in request order,
    /// encoded into `out` (emptied first).
    fn ready_replies(&mut self, out: &mut Vec<u8>, metrics: &Metrics) {
        out.clear();
        while let Some(front) = self.queue.front_mut() {
            if !front.try_ready() {
                break;
            }
            let Some(done) = self.queue.pop_front() else {
                break;
            };
            let pdu = match done.reply {
                Reply::Ready(pdu) => pdu,
                Reply::Pending(p) => p.finish(metrics),
            };
            mbap::encode(done.transaction, done.unit, &pdu, out);
        }
    }

    /// Cancels the requests still queued, so the bus drops them unsent;
    /// how many were left.
    fn cancel(self, metrics: &Metrics) -> usize {
        let left = self.queue.len();
        for request in self.queue {
            match request.reply {
                Reply::Pending(p) => p.cancel(metrics),
                Reply::Ready(_) => {}
            }
        }
        left
    }
}

/// Why a connection ended, for the log.
#[derive(Debug)]
enum End {
    ClientClosed,
    Failed(std::io::Error),
    Malformed,
    Idle,
    NotReading,
    Shutdown,
}

impl End {
    /// Our side closed it, so the client may still be sending: its input
    /// is drained before the socket closes.
    fn closed_by_us(&self) -> bool {
        matches!(
            self,
            End::Malformed | End::Idle | End::NotReading | End::Shutdown
        )
    }

    /// Logs the end of `client`'s connection, with the requests `cancelled`.
    fn log(&self, client: &Client, cancelled: usize, idle_timeout: Duration) {
        match self {
            End::Malformed => {}
            End::Idle => debug!(client = %client.peer, "closed after {:?} idle", idle_timeout),
            End::NotReading => {
                warn!(client = %client.peer, "closed: the client did not take its replies for {:?}", idle_timeout)
            }
            End::Failed(e) => debug!(client = %client.peer, cancelled, "connection failed: {e}"),
            End::ClientClosed => {
                debug!(client = %client.peer, cancelled, "client closed the connection")
            }
            End::Shutdown => {
                debug!(client = %client.peer, cancelled, "closed: the daemon is stopping")
            }
        }
    }
}

/// Serves one connection (plain TCP, or TLS for Modbus/TCP Security)
/// until it ends.
pub async fn serve<S: AsyncRead + AsyncWrite + Send + 'static>(
    stream: S,
    client: Client,
    session: SessionGuard,
    gateway: Arc<Gateway>,
    settings: ConnectionSettings,
    shutdown: CancellationToken,
) {
    let metrics = gateway.metrics().clone();
    let (mut rd, mut wr) = tokio::io::split(stream);
    let mut buf = BytesMut::with_capacity(2 * MAX_FRAME);
    let mut pipeline = Pipeline::default();
    let mut out = Vec::with_capacity(MAX_FRAME);
    let idle = tokio::time::sleep(settings.idle_timeout);
    tokio::pin!(idle);

    let end = loop {
        pipeline
            .take(
                &mut buf,
                (&gateway, &client),
                settings.max_pipelined,
                idle.as_mut(),
                settings.idle_timeout,
            )
            .await;
        if pipeline.malformed && pipeline.queue.is_empty() {
            break End::Malformed;
        }
        // Keep reading while the pipeline is full, into a bounded buffer, so
        // a client that disconnects is noticed and its queued requests are
        // cancelled; past the bound, TCP flow control holds the client back.
        let reading = buf.len() < READ_BUFFER;
        if reading {
            buf.reserve(MAX_FRAME);
        }
        tokio::select! {
            biased;
            () = shutdown.cancelled() => break End::Shutdown,
            () = head_ready(&mut pipeline.queue), if !pipeline.queue.is_empty() => {
                pipeline.ready_replies(&mut out, &metrics);
                let write = tokio::time::timeout(settings.idle_timeout, wr.write_all(&out));
                tokio::select! {
                    r = write => match r {
                        Ok(Ok(())) => idle.as_mut().reset(Instant::now() + settings.idle_timeout),
                        Ok(Err(e)) => break End::Failed(e),
                        Err(_) => break End::NotReading,
                    },
                    () = shutdown.cancelled() => break End::Shutdown,
                }
            }
            r = rd.read_buf(&mut buf), if reading => match r {
                Ok(0) => break End::ClientClosed,
                // After a malformed frame the bytes mean nothing: read only
                // to notice the client leaving.
                Ok(_) if pipeline.malformed => buf.clear(),
                // The client is alive, even while its requests wait for
                // room in the pipeline behind a slow bus (a wait that
                // counts against the bus's queue timeout, from now).
                Ok(n) => {
                    pipeline.arrivals.read(n, std::time::Instant::now());
                    session.active();
                }
                Err(e) => break End::Failed(e),
            },
            () = &mut idle, if pipeline.queue.is_empty() => break End::Idle,
        }
    };
    let cancelled = pipeline.cancel(&metrics);
    // Only once none of its queued writes can reach the bus: a setpoint
    // landing after the stop would set the motor going again.
    drop(session);
    let _ = wr.shutdown().await;
    if end.closed_by_us() {
        drain(&mut rd).await;
    }
    end.log(&client, cancelled, settings.idle_timeout);
}

/// Reads and discards what the client still sends, briefly, after our side
/// was shut down: closing a socket with unread input makes the kernel send
/// a reset, which can destroy replies the client has not read yet.
async fn drain<R: AsyncRead + Unpin>(rd: &mut R) {
    let mut sink = [0u8; 1024];
    let mut left: usize = 64 * 1024;
    let until = Instant::now() + Duration::from_millis(500);
    while left > 0 {
        match tokio::time::timeout_at(until, rd.read(&mut sink)).await {
            Ok(Ok(n)) if n > 0 => left = left.saturating_sub(n),
            _ => break,
        }
    }
}

/// Waits until the oldest request's reply is ready.
async fn head_ready(queue: &mut VecDeque<InFlight>) {
    match queue.front_mut() {
        Some(front) => front.ready().await,
        None => std::future::pending().await,
    }
}
