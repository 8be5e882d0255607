//! The HTTP listener: where it binds (loopback only without tokens), how
//! many connections it serves at once, and the socket options of each.
//!
//! The connection limit is a semaphore: a connection holds a permit for as
//! long as it lives, WebSocket or keep-alive included. Over the limit a
//! client gets a short `503 too-many-connections` and the socket is closed,
//! so a flood of clients cannot exhaust the small box's file descriptors or
//! memory while the clients already connected keep working.
//!
//! Permits must come back, so connections cannot live forever unattended:
//! one that moves no byte for `[http] idle_timeout_s` is closed (the HTTP
//! server sets no header timeout of its own), TCP keepalive finds peers
//! that vanished without a word (power cut, cable pulled), and
//! `TCP_USER_TIMEOUT` drops a peer that stops acknowledging data.

use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::time::{Instant, Sleep};

use axum::serve::Listener;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::problem::{Kind, Problem};

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

/// A TCP listener that serves at most `max` connections at once.
pub struct LimitedListener {
    inner: TcpListener,
    permits: Arc<Semaphore>,
    refusals: Arc<Semaphore>,
    send_buffer: usize,
    idle_timeout: Duration,
}

impl LimitedListener {
    /// Wraps `inner`; `send_buffer` bytes of kernel send buffer per
    /// connection (0: the system's); connections idle for `idle_timeout`
    /// are closed.
    pub fn new(inner: TcpListener, max: usize, send_buffer: usize, idle_timeout: Duration) -> Self {
        Self {
            inner,
            permits: Arc::new(Semaphore::new(max)),
            refusals: Arc::new(Semaphore::new(REFUSALS_IN_FLIGHT)),
            send_buffer,
            idle_timeout,
        }
    }

    fn configure(&self, stream: &TcpStream) {
        // Status replies are small: do not let Nagle hold them back.
        let _ = stream.set_nodelay(true);
        let socket = socket2::SockRef::from(stream);
        if self.send_buffer > 0 {
            let _ = socket.set_send_buffer_size(self.send_buffer);
        }
        let keepalive = socket2::TcpKeepalive::new()
            .with_time(KEEPALIVE_TIME)
            .with_interval(KEEPALIVE_INTERVAL)
            .with_retries(KEEPALIVE_RETRIES);
        let _ = socket.set_tcp_keepalive(&keepalive);
        let _ = socket.set_tcp_user_timeout(Some(USER_TIMEOUT));
    }
}

/// The answer to a connection over the limit, sent before closing it.
fn over_limit_response() -> Vec<u8> {
    let problem = Problem::new(
        Kind::TooManyConnections,
        "drivegate serves a limited number of connections at once ([http] max_connections); close idle ones or retry shortly",
    )
    .retry_after(1);
    let body = serde_json::to_string(&problem).unwrap_or_default();
    format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: {}\r\nretry-after: 1\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        super::problem::CONTENT_TYPE,
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
async fn refuse(mut stream: TcpStream) {
    let mut sink = [0u8; 1024];
    let _ = tokio::time::timeout(
        REFUSAL_WAIT,
        tokio::io::AsyncReadExt::read(&mut stream, &mut sink),
    )
    .await;
    let answer = async {
        stream.write_all(&over_limit_response()).await?;
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
            match self.permits.clone().try_acquire_owned() {
                Ok(permit) => {
                    self.configure(&stream);
                    return (LimitedStream::new(stream, permit, self.idle_timeout), addr);
                }
                Err(_) => {
                    tracing::debug!(client = %addr, "HTTP connection refused: connection limit reached");
                    if let Ok(slot) = self.refusals.clone().try_acquire_owned() {
                        tokio::spawn(async move {
                            refuse(stream).await;
                            drop(slot);
                        });
                    }
                }
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// A connection holding its permit until it closes, closed when idle.
pub struct LimitedStream {
    stream: TcpStream,
    _permit: OwnedSemaphorePermit,
    idle_timeout: Duration,
    last_activity: Instant,
    idle: Pin<Box<Sleep>>,
}

impl LimitedStream {
    /// The address the connection arrived at.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.stream.local_addr()
    }

    fn new(stream: TcpStream, permit: OwnedSemaphorePermit, idle_timeout: Duration) -> Self {
        let now = Instant::now();
        LimitedStream {
            stream,
            _permit: permit,
            idle_timeout,
            last_activity: now,
            idle: Box::pin(tokio::time::sleep_until(now + idle_timeout)),
        }
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
            self.last_activity = Instant::now();
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
            self.last_activity = Instant::now();
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
        let text = String::from_utf8(over_limit_response()).unwrap();
        assert!(text.starts_with("HTTP/1.1 503"));
        let body = text.split("\r\n\r\n").nth(1).unwrap();
        let p: Problem = serde_json::from_str(body).unwrap();
        assert_eq!(p.kind(), Kind::TooManyConnections);
    }
}
