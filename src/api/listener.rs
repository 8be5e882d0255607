//! The HTTP listener: where it binds (loopback only without tokens), how
//! many connections it serves at once, and from one address, and the
//! socket options of each.
//!
//! The connection limit is a semaphore: a connection holds a permit for as
//! long as it lives, WebSocket or keep-alive included. Over the limit a
//! client gets a short `503 too-many-connections` and the socket is closed,
//! so a flood of clients cannot exhaust the small box's file descriptors or
//! memory while the clients already connected keep working. One address
//! (an IPv6 host by its /64) holds at most `max_connections_per_address`
//! of them, so one client, or one attacker's host, cannot take every slot
//! and lock the others (the admin included) out; its refusals are logged
//! once per burst.
//!
//! Permits must come back, so connections cannot live forever unattended:
//! one that has not sent a whole request head within `[http]
//! header_timeout_ms` is closed by the server (`super::server`), one that
//! moves no byte for `[http] idle_timeout_s` is closed here, TCP keepalive
//! finds peers that vanished without a word (power cut, cable pulled), and
//! `TCP_USER_TIMEOUT` drops a peer that stops acknowledging data.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::time::{Instant, Sleep};

use axum::serve::Listener;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::problem_response::{Kind, Problem};
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
    /// Connections at once from one address (an IPv6 host by its /64).
    pub per_address: usize,
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

/// A TCP listener that serves at most `max` connections at once, and
/// `per_address` from one address.
pub struct LimitedListener {
    inner: TcpListener,
    limits: Limits,
    permits: Arc<Semaphore>,
    addresses: Arc<Addresses>,
    refusals: Arc<Semaphore>,
    bursts: Bursts,
    metrics: Arc<Metrics>,
}

impl LimitedListener {
    /// Wraps `inner` with `limits`, counting in `metrics`.
    pub fn new(inner: TcpListener, limits: Limits, metrics: Arc<Metrics>) -> Self {
        Self {
            inner,
            limits,
            permits: Arc::new(Semaphore::new(limits.max)),
            addresses: Arc::default(),
            refusals: Arc::new(Semaphore::new(REFUSALS_IN_FLIGHT)),
            bursts: Bursts::default(),
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

    /// Refuses `stream` from `addr` for `why`: counted, logged once per
    /// burst, answered 503 while few refusals are in flight (a flood is
    /// closed unanswered).
    fn refuse(&mut self, stream: TcpStream, addr: SocketAddr, why: Refusal) {
        let (reason, key) = match why {
            Refusal::Limit => ("limit", None),
            Refusal::PerAddress => ("per_address", Some(super::throttle::key(addr.ip()))),
        };
        self.metrics.security().http_refused(reason);
        if self.bursts.begins(key, std::time::Instant::now()) {
            match why {
                Refusal::Limit => tracing::warn!(
                    listener = %self.inner.local_addr().map_or_else(|e| e.to_string(), |a| a.to_string()),
                    "HTTP connections refused: {} are open ([http] max_connections); new ones are answered 503 until some close (logged once per burst, counted in drivegate_http_connections_refused_total)",
                    self.limits.max
                ),
                Refusal::PerAddress => tracing::warn!(
                    client = %addr.ip(),
                    listener = %self.inner.local_addr().map_or_else(|e| e.to_string(), |a| a.to_string()),
                    "HTTP connections from {} refused: it holds {} already ([http] max_connections_per_address); its new ones are answered 503 until some close (logged once per burst, counted in drivegate_http_connections_refused_total)",
                    addr.ip(),
                    self.limits.per_address
                ),
            }
        } else {
            tracing::debug!(client = %addr, "HTTP connection refused ({reason})");
        }
        if let Ok(slot) = self.refusals.clone().try_acquire_owned() {
            tokio::spawn(async move {
                refuse(stream, why).await;
                drop(slot);
            });
        }
    }
}

/// Why a connection was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refusal {
    /// `max_connections` are open.
    Limit,
    /// Its address holds `max_connections_per_address`.
    PerAddress,
}

/// The answer to a connection refused for `why`, sent before closing it.
fn over_limit_response(why: Refusal) -> Vec<u8> {
    let detail = match why {
        Refusal::Limit => {
            "drivegate serves a limited number of connections at once ([http] max_connections); close idle ones or retry shortly"
        }
        Refusal::PerAddress => {
            "your address holds as many connections as one address may ([http] max_connections_per_address); close idle ones or retry shortly"
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
async fn refuse(mut stream: TcpStream, why: Refusal) {
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
                    // Out of descriptors or similar: wait instead of spinning.
                    if !matches!(
                        e.kind(),
                        io::ErrorKind::ConnectionAborted | io::ErrorKind::ConnectionReset
                    ) {
                        tracing::warn!("accepting an HTTP connection failed: {e}");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    continue;
                }
            };
            // The address's share first: a full one must not take a
            // permit another address could use.
            let Some(address) = self.addresses.take(addr.ip(), self.limits.per_address) else {
                self.refuse(stream, addr, Refusal::PerAddress);
                continue;
            };
            let Ok(permit) = self.permits.clone().try_acquire_owned() else {
                drop(address);
                self.refuse(stream, addr, Refusal::Limit);
                continue;
            };
            self.configure(&stream);
            let held = Held {
                _permit: permit,
                _address: address,
                _open: self.metrics.security().http_connection(),
            };
            return (
                LimitedStream::new(stream, held, self.limits.idle_timeout),
                addr,
            );
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// What a connection holds until it closes: its permit, its address's
/// share, its place in the open-connections gauge.
struct Held {
    _permit: OwnedSemaphorePermit,
    _address: AddressSlot,
    _open: OpenConnection,
}

/// How many connections each address holds (IPv6 hosts by their /64).
#[derive(Debug, Default)]
struct Addresses(Mutex<HashMap<IpAddr, usize>>);

impl Addresses {
    /// One more connection from `ip`, unless it holds `max` already.
    fn take(self: &Arc<Self>, ip: IpAddr, max: usize) -> Option<AddressSlot> {
        let key = super::throttle::key(ip);
        let mut held = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let n = held.entry(key).or_insert(0);
        if *n >= max {
            return None;
        }
        *n += 1;
        Some(AddressSlot {
            table: self.clone(),
            key,
        })
    }
}

/// One connection's share of its address; given back when dropped.
#[derive(Debug)]
struct AddressSlot {
    table: Arc<Addresses>,
    key: IpAddr,
}

impl Drop for AddressSlot {
    fn drop(&mut self) {
        let mut held = self.table.0.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = held.get_mut(&self.key) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                held.remove(&self.key);
            }
        }
    }
}

/// A refusal burst ends after this long without a refusal (of that
/// address, or of the limit): the next one is logged again.
const BURST_GAP: std::time::Duration = std::time::Duration::from_secs(10);

/// When each address (`None`: the whole listener's limit) was last
/// refused, so a burst of refusals is logged once.
#[derive(Debug, Default)]
struct Bursts(HashMap<Option<IpAddr>, std::time::Instant>);

impl Bursts {
    /// Notes a refusal of `key` at `now`; true when it begins a burst.
    fn begins(&mut self, key: Option<IpAddr>, now: std::time::Instant) -> bool {
        if self.0.len() > 4096 {
            self.0.retain(|_, at| now.duration_since(*at) < BURST_GAP);
        }
        let last = self.0.insert(key, now);
        last.is_none_or(|at| now.duration_since(at) >= BURST_GAP)
    }
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
    stream: TcpStream,
    _held: Held,
    activity: Arc<Activity>,
    idle_timeout: Duration,
    last_activity: Instant,
    idle: Pin<Box<Sleep>>,
}

impl LimitedStream {
    /// The address the connection arrived at.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.stream.local_addr()
    }

    /// What is known of its requests.
    pub fn activity(&self) -> Arc<Activity> {
        self.activity.clone()
    }

    fn new(stream: TcpStream, held: Held, idle_timeout: Duration) -> Self {
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
        for why in [Refusal::Limit, Refusal::PerAddress] {
            let text = String::from_utf8(over_limit_response(why)).unwrap();
            assert!(text.starts_with("HTTP/1.1 503"));
            let body = text.split("\r\n\r\n").nth(1).unwrap();
            let p: Problem = serde_json::from_str(body).unwrap();
            assert_eq!(p.kind(), Kind::TooManyConnections);
        }
        assert!(
            String::from_utf8(over_limit_response(Refusal::PerAddress))
                .unwrap()
                .contains("max_connections_per_address")
        );
    }

    #[test]
    fn an_address_holds_its_share_and_gets_it_back() {
        let table = Arc::new(Addresses::default());
        let a: IpAddr = "127.0.0.1".parse().unwrap();
        let held: Vec<_> = (0..3).map(|_| table.take(a, 3).unwrap()).collect();
        assert!(table.take(a, 3).is_none());
        // Another address is not concerned; an IPv6 host counts by its /64.
        assert!(table.take("127.0.0.2".parse().unwrap(), 3).is_some());
        let v6 = table.take("2001:db8::1".parse().unwrap(), 1).unwrap();
        assert!(table.take("2001:db8::ffff".parse().unwrap(), 1).is_none());
        drop(v6);
        drop(held);
        assert!(table.0.lock().unwrap().is_empty());
        assert!(table.take(a, 3).is_some());
    }

    #[test]
    fn a_burst_of_refusals_is_logged_once() {
        let mut bursts = Bursts::default();
        let t = std::time::Instant::now();
        let a = Some("127.0.0.1".parse().unwrap());
        assert!(bursts.begins(a, t));
        assert!(!bursts.begins(a, t + std::time::Duration::from_secs(9)));
        assert!(!bursts.begins(a, t + std::time::Duration::from_secs(18)));
        assert!(bursts.begins(None, t));
        assert!(bursts.begins(a, t + std::time::Duration::from_secs(30)));
    }
}
