//! The HTTP listener: where it binds (loopback only without tokens), how
//! many connections it serves at once, and from one address, and the
//! socket options of each.
//!
//! A connection holds its place in the listener's budget
//! (`crate::connections`) for as long as it lives, WebSocket or keep-alive
//! included. Addresses share every free slot; near `max_connections`, or
//! near the process's file limit, the heaviest address gives way first
//! (an IPv6 host counts by its /64): its new connections get a short `503
//! too-many-connections` and are closed, and once the listener is full a
//! quiet connection of it is closed for a client of a lighter address, so
//! one client, or one attacker's host, cannot lock the others (the admin
//! included) out, and a flood cannot exhaust the small box's file
//! descriptors or memory. `max_connections_per_address`, when set, is a
//! hard cap. Refusals are counted per address and logged once per address
//! and second at most; accept errors back off.
//!
//! Permits must come back, so connections cannot live forever unattended:
//! one that has not sent a whole request head within `[http]
//! header_timeout_ms` is closed by the server (`super::server`), one that
//! moves no byte for `[http] idle_timeout_s` is closed here, TCP keepalive
//! finds peers that vanished without a word (power cut, cable pulled), and
//! `TCP_USER_TIMEOUT` drops a peer that stops acknowledging data.

use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::time::{Instant, Sleep};

use axum::serve::Listener;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;

use super::problem_response::{Kind, Problem};
use crate::connections::accept::AcceptErrors;
use crate::connections::{Guarded, Listener as Budget, Refused};
use crate::metrics::{Metrics, OpenConnection};

/// Where to bind: `listen`, or with no tokens the loopback address of the
/// same family and port (an open API must not be reachable from the plant
/// network).
pub fn bind_address(listen: SocketAddr, has_tokens: bool) -> SocketAddr {
    if has_tokens || listen.ip().is_loopback() {
        return listen;
    }
    let loopback = match listen.ip() {
        IpAddr::V4(_) => IpAddr::V4(Ipv4Addr::LOCALHOST),
        IpAddr::V6(_) => IpAddr::V6(Ipv6Addr::LOCALHOST),
    };
    SocketAddr::new(loopback, listen.port())
}

/// Keepalive probes start after this much silence...
const KEEPALIVE_TIME: Duration = Duration::from_secs(30);
/// ... and repeat this often ...
const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(10);
/// ... this many times before the connection is dropped.
const KEEPALIVE_RETRIES: u32 = 3;
/// Data unacknowledged for this long drops the connection.
const USER_TIMEOUT: Duration = Duration::from_secs(60);

/// What the listener allows.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Connections at once.
    pub max: usize,
    /// A hard cap on the connections of one address (an IPv6 host by its
    /// /64), when configured.
    pub per_address: Option<usize>,
    /// Kernel send buffer per connection, bytes (0: the system's).
    pub send_buffer: usize,
    /// A connection that moves no byte for this long is closed.
    pub idle_timeout: Duration,
}

impl Limits {
    /// The limits of `[http]`.
    pub fn of(http: &crate::config::HttpConfig) -> Self {
        Limits {
            max: http.max_connections,
            per_address: http.max_connections_per_address,
            send_buffer: http.send_buffer_bytes,
            idle_timeout: http.idle_timeout,
        }
    }
}

/// A TCP listener whose connections each hold a place in its budget.
pub struct LimitedListener {
    inner: TcpListener,
    limits: Limits,
    budget: Arc<Budget>,
    refusals: Arc<Semaphore>,
    errors: AcceptErrors,
    metrics: Arc<Metrics>,
}

impl LimitedListener {
    /// Wraps `inner` with `limits`, counting in `metrics`.
    pub fn new(inner: TcpListener, limits: Limits, metrics: Arc<Metrics>) -> Self {
        let budget = metrics.listeners().listener(
            crate::connections::words::HTTP,
            crate::connections::Limits {
                max: limits.max,
                per_address: limits.per_address,
            },
        );
        if let Ok(bound) = inner.local_addr() {
            budget.set_bound(bound);
        }
        Self {
            inner,
            limits,
            budget,
            refusals: Arc::new(Semaphore::new(REFUSALS_IN_FLIGHT)),
            errors: AcceptErrors::new(crate::connections::words::HTTP),
            metrics,
        }
    }

    fn configure(&self, stream: &TcpStream) {
        // Status replies are small: do not let Nagle hold them back.
        let _ = stream.set_nodelay(true);
        let socket = socket2::SockRef::from(stream);
        if self.limits.send_buffer > 0 {
            let _ = socket.set_send_buffer_size(self.limits.send_buffer);
        }
        let keepalive = socket2::TcpKeepalive::new()
            .with_time(KEEPALIVE_TIME)
            .with_interval(KEEPALIVE_INTERVAL)
            .with_retries(KEEPALIVE_RETRIES);
        let _ = socket.set_tcp_keepalive(&keepalive);
        let _ = socket.set_tcp_user_timeout(Some(USER_TIMEOUT));
    }

    /// Refuses `stream` for `why` (counted and logged by the budget):
    /// answered 503 while few refusals are in flight (a flood is closed
    /// unanswered).
    fn refuse(&self, stream: TcpStream, addr: SocketAddr, why: Refused) {
        self.metrics.security().http_refused(why.label());
        tracing::debug!(client = %addr, "HTTP connection refused ({})", why.label());
        if let Ok(slot) = self.refusals.clone().try_acquire_owned() {
            tokio::spawn(async move {
                refuse(stream, why).await;
                drop(slot);
            });
        }
    }
}

/// The answer to a connection refused for `why`, sent before closing it.
fn over_limit_response(why: Refused) -> Vec<u8> {
    let detail = match why {
        Refused::Limit | Refused::Heaviest => {
            "drivegate serves a limited number of connections at once ([http] max_connections), and yours is the address holding the most; close idle ones or retry shortly"
        }
        Refused::PerAddress => {
            "your address holds as many connections as one address may ([http] max_connections_per_address); close idle ones or retry shortly"
        }
        Refused::Files => {
            "drivegate is near its limit of open files, and yours is the address holding the most connections; close idle ones or retry shortly"
        }
    };
    let problem = Problem::new(Kind::TooManyConnections, detail).retry_after(1);
    let body = serde_json::to_string(&problem).unwrap_or_default();
    format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: {}\r\nretry-after: 1\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        super::problem_response::CONTENT_TYPE,
        body.len()
    )
    .into_bytes()
}

/// Refusals answered at once; beyond this (a flood) connections over the
/// limit are closed without an answer.
const REFUSALS_IN_FLIGHT: usize = 64;

/// How long a refused client has to start its request before the 503.
const REFUSAL_WAIT: Duration = Duration::from_millis(500);

/// Answers 503 once the client's request has begun (or after
/// [`REFUSAL_WAIT`]), then reads what the client sent until it closes (or
/// 1 s), so the answer is not lost to a reset. An HTTP client takes an
/// answer that comes before its request for a broken server, not a refusal.
async fn refuse(mut stream: TcpStream, why: Refused) {
    let mut sink = [0u8; 1024];
    let _ = tokio::time::timeout(
        REFUSAL_WAIT,
        tokio::io::AsyncReadExt::read(&mut stream, &mut sink),
    )
    .await;
    let answer = async {
        stream.write_all(&over_limit_response(why)).await?;
        stream.shutdown().await?;
        while tokio::io::AsyncReadExt::read(&mut stream, &mut sink).await? > 0 {}
        Ok::<(), io::Error>(())
    };
    let _ = tokio::time::timeout(Duration::from_secs(1), answer).await;
}

impl Listener for LimitedListener {
    type Io = LimitedStream;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            let (stream, addr) = match self.inner.accept().await {
                Ok(pair) => pair,
                Err(e) => {
                    // Out of descriptors or similar: back off, not spin.
                    let pause = self.errors.failed(&e);
                    tokio::time::sleep(pause).await;
                    continue;
                }
            };
            self.errors.accepted();
            let ticket = match self.budget.admit(addr.ip()) {
                Ok(ticket) => ticket,
                Err(why) => {
                    self.refuse(stream, addr, why);
                    continue;
                }
            };
            self.configure(&stream);
            let held = Held {
                _open: self.metrics.security().http_connection(),
            };
            return (
                LimitedStream::new(Guarded::new(stream, ticket), held, self.limits.idle_timeout),
                addr,
            );
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// What a connection holds until it closes besides its place in the
/// budget: its place in the open-connections gauge.
struct Held {
    _open: OpenConnection,
}

/// What the server tells of a connection's requests, and the stream of
/// its reads and writes: a connection closed for its request head is one
/// that never sent a whole first head, or had begun its next one; a
/// kept-alive connection left unused is not.
#[derive(Debug, Default)]
pub struct Activity {
    requests: AtomicU64,
    read_since_answer: AtomicBool,
}

impl Activity {
    /// A request head arrived whole.
    pub fn request(&self) {
        self.requests.fetch_add(1, Ordering::Relaxed);
    }

    /// The connection owed a request head: it has sent none whole yet, or
    /// sent bytes of its next one.
    pub fn head_owed(&self) -> bool {
        self.requests.load(Ordering::Relaxed) == 0 || self.read_since_answer.load(Ordering::Relaxed)
    }
}

/// A connection holding its permit until it closes, closed when idle.
pub struct LimitedStream {
    stream: Guarded<TcpStream>,
    _held: Held,
    activity: Arc<Activity>,
    idle_timeout: Duration,
    last_activity: Instant,
    idle: Pin<Box<Sleep>>,
}

impl LimitedStream {
    /// The address the connection arrived at.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.stream.get_ref().local_addr()
    }

    /// What is known of its requests.
    pub fn activity(&self) -> Arc<Activity> {
        self.activity.clone()
    }

    fn new(stream: Guarded<TcpStream>, held: Held, idle_timeout: Duration) -> Self {
        let now = Instant::now();
        LimitedStream {
            stream,
            _held: held,
            activity: Arc::default(),
            idle_timeout,
            last_activity: now,
            idle: Box::pin(tokio::time::sleep_until(now + idle_timeout)),
        }
    }

    fn wrote(&mut self) {
        self.last_activity = Instant::now();
        self.activity
            .read_since_answer
            .store(false, Ordering::Relaxed);
    }

    /// While a read waits: fails the read once nothing moved for the idle
    /// timeout. The timer is armed lazily: activity only moves
    /// `last_activity`, and a timer that fires early is re-armed.
    fn poll_idle(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        loop {
            let deadline = self.last_activity + self.idle_timeout;
            if Instant::now() >= deadline {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    "connection idle for too long",
                )));
            }
            if self.idle.deadline() != deadline {
                self.idle.as_mut().reset(deadline);
            }
            if self.idle.as_mut().poll(cx).is_pending() {
                return Poll::Pending;
            }
        }
    }
}

impl AsyncRead for LimitedStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                if buf.filled().len() > before {
                    self.last_activity = Instant::now();
                    self.activity
                        .read_since_answer
                        .store(true, Ordering::Relaxed);
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => self.poll_idle(cx),
        }
    }
}

impl AsyncWrite for LimitedStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let written = Pin::new(&mut self.stream).poll_write(cx, buf);
        if matches!(written, Poll::Ready(Ok(n)) if n > 0) {
            self.wrote();
        }
        written
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let written = Pin::new(&mut self.stream).poll_write_vectored(cx, bufs);
        if matches!(written, Poll::Ready(Ok(n)) if n > 0) {
            self.wrote();
        }
        written
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

/// The client's address, as handlers see it (`ConnectInfo<ClientAddr>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClientAddr(pub SocketAddr);

/// The address a connection arrived at (a request extension): on a
/// listener bound to every interface, the one the client used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServedAt(pub SocketAddr);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_api_binds_loopback_only() {
        let any: SocketAddr = "0.0.0.0:8080".parse().unwrap();
        assert_eq!(bind_address(any, false).to_string(), "127.0.0.1:8080");
        assert_eq!(bind_address(any, true), any);
        let any6: SocketAddr = "[::]:8080".parse().unwrap();
        assert_eq!(bind_address(any6, false).to_string(), "[::1]:8080");
        let lo: SocketAddr = "127.0.0.1:0".parse().unwrap();
        assert_eq!(bind_address(lo, false), lo);
    }

    #[test]
    fn over_limit_answer_is_a_problem() {
        for why in Refused::ALL {
            let text = String::from_utf8(over_limit_response(why)).unwrap();
            assert!(text.starts_with("HTTP/1.1 503"));
            let body = text.split("\r\n\r\n").nth(1).unwrap();
            let p: Problem = serde_json::from_str(body).unwrap();
            assert_eq!(p.kind(), Kind::TooManyConnections);
        }
        assert!(
            String::from_utf8(over_limit_response(Refused::PerAddress))
                .unwrap()
                .contains("max_connections_per_address")
        );
    }
}
