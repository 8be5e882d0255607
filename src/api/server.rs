//! The HTTP server loop: hyper's HTTP/1 on each accepted connection, with a
//! deadline on every request head, the client's address for the handlers,
//! upgrades for the stream, and a graceful stop.
//!
//! A deadline is the defence against idle and slow clients ("slow-loris"):
//! one that connects and sends nothing, or a request a byte at a time,
//! would keep its connection, and one of the `max_connections` slots, for
//! ever; enough of them and no one else gets in. hyper can time out a
//! request head only with a timer, which axum's `serve` does not give it:
//! here it gets tokio's and `[http] header_timeout_ms`. The head of each
//! request, the first as the later ones on a kept-alive connection, must
//! arrive whole within it (so a kept-alive connection left unused that long
//! is closed too); the body then has `read_timeout_s` (see
//! [`super::extract`]). A connection closed for a head it owed (none sent
//! whole yet, or the next one begun) is counted in
//! `drivegate_http_header_timeouts_total`.
//!
//! Under `[http.tls]` every connection is TLS: the handshake runs in the
//! connection's own task (a slow one holds up nobody else) within the
//! header deadline (then the head has its own), with the configuration current when it starts, so a reloaded
//! certificate serves new connections while the open ones carry on. A
//! client that speaks plain HTTP fails the handshake and gets no answer.

use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use axum::serve::Listener;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::ServiceExt;

use super::listener::{ClientAddr, LimitedListener, ServedAt};
use crate::metrics::Metrics;
use crate::tls::Reloadable;

/// The listener's TLS, when `[http.tls]` is set.
#[derive(Clone)]
pub struct Tls {
    /// The server configuration, reloadable.
    pub config: Arc<Reloadable>,
    /// Where failed handshakes are counted.
    pub metrics: Arc<Metrics>,
}

/// Serves `app` on the connections of `listener` until `shutdown` fires,
/// then lets the requests in progress finish and waits for their
/// connections to close. Upgraded connections (the stream) are the
/// sessions' own and are not waited for here. A request head must arrive
/// whole within `header_timeout`.
pub async fn serve(
    mut listener: LimitedListener,
    app: Router,
    header_timeout: Duration,
    tls: Option<Tls>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) {
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(header_timeout);
    let connections = TaskTracker::new();
    loop {
        let (stream, addr) = tokio::select! {
            // A closed listener's socket fails its accepts: the stop first.
            biased;
            () = shutdown.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        let local = stream.local_addr().ok();
        let activity = stream.activity();
        let heads = activity.clone();
        let service = app
            .clone()
            .map_request(move |mut request: axum::http::Request<Incoming>| {
                heads.request();
                let extensions = request.extensions_mut();
                extensions.insert(ConnectInfo(ClientAddr(addr)));
                if let Some(local) = local {
                    extensions.insert(ServedAt(local));
                }
                request
            });
        let http = http.clone();
        let shutdown = shutdown.clone();
        let tls = tls.clone();
        let metrics = metrics.clone();
        connections.spawn(async move {
            let service = TowerToHyperService::new(service);
            let served = match tls {
                None => serve_one(&http, stream, service, &shutdown).await,
                Some(tls) => {
                    let acceptor = tokio_rustls::TlsAcceptor::from(tls.config.current());
                    let handshake = tokio::select! {
                        h = tokio::time::timeout(header_timeout, acceptor.accept(stream)) => h,
                        () = shutdown.cancelled() => return,
                    };
                    match handshake {
                        Ok(Ok(stream)) => serve_one(&http, stream, service, &shutdown).await,
                        Ok(Err(e)) => {
                            tls.metrics.security().tls_handshake_failed("http");
                            tracing::debug!(client = %addr, "TLS handshake failed: {e}");
                            return;
                        }
                        Err(_) => {
                            tls.metrics.security().tls_handshake_failed("http");
                            tracing::debug!(client = %addr, "TLS handshake not done within {header_timeout:?}");
                            return;
                        }
                    }
                }
            };
            if let Err(e) = served {
                if e.is_timeout() && activity.head_owed() {
                    metrics.security().http_header_timeout();
                }
                // Timeouts, resets and malformed requests: the client's doing.
                tracing::debug!(client = %addr, "HTTP connection ended: {e}");
            }
        });
    }
    drop(listener);
    connections.close();
    connections.wait().await;
}

/// Serves the requests of one connection (plain or TLS) until it closes,
/// or gracefully once `shutdown` fires.
async fn serve_one<I, S>(
    http: &hyper::server::conn::http1::Builder,
    io: I,
    service: S,
    shutdown: &CancellationToken,
) -> Result<(), hyper::Error>
where
    I: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
    S: hyper::service::Service<
            axum::http::Request<Incoming>,
            Response = axum::response::Response,
            Error = std::convert::Infallible,
        > + Send
        + 'static,
    S::Future: Send + 'static,
{
    let connection = http
        .serve_connection(TokioIo::new(io), service)
        .with_upgrades();
    tokio::pin!(connection);
    tokio::select! {
        served = connection.as_mut() => served,
        () = shutdown.cancelled() => {
            connection.as_mut().graceful_shutdown();
            connection.await
        }
    }
}
