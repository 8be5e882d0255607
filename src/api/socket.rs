//! What every WebSocket route shares (the stream, the monitor's live
//! feed): the upgrade with its size limits and a tracked session, the
//! bounded send, the ping that proves a quiet client alive, and the close
//! sent when the daemon stops.

use std::future::Future;
use std::time::Duration;

use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::response::Response;
use futures_util::SinkExt;
use futures_util::stream::{SplitSink, SplitStream};

use super::problem_response::Problem;
use super::state::ApiState;

/// The sending half of a session's socket.
pub type Sink = SplitSink<WebSocket, Message>;
/// The receiving half.
pub type Source = SplitStream<WebSocket>;

/// The upgrade, or the problem for a plain HTTP request to a WebSocket
/// route.
pub fn upgrade(
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<WebSocketUpgrade, Problem> {
    upgrade.map_err(|e| {
        Problem::invalid(format!(
            "this route is a WebSocket: connect with a WebSocket client ({})",
            e.body_text()
        ))
    })
}

/// Switches to the WebSocket protocol and runs `session` on the socket:
/// messages no larger than a request body (`[http] max_body_bytes`), and
/// the session tracked, so shutdown waits for it (the HTTP server does not
/// once a connection is upgraded).
pub fn accept<F, S>(state: &ApiState, upgrade: WebSocketUpgrade, session: S) -> Response
where
    S: FnOnce(WebSocket) -> F + Send + 'static,
    F: Future<Output = ()> + Send + 'static,
{
    let limit = state.config.max_body_bytes;
    let sessions = state.sessions.clone();
    upgrade
        .max_message_size(limit)
        .max_frame_size(limit)
        .on_upgrade(move |socket| sessions.track_future(session(socket)))
}

/// Sends one message; false when the socket is gone, the daemon stops, or
/// the client has not taken the message within the idle timeout: a hung
/// client whose kernel keeps the connection open (and acknowledges, with a
/// zero window) would otherwise hold the writer, and the session with its
/// connection slot and leases, for ever.
pub async fn send(state: &ApiState, sink: &mut Sink, message: Message) -> bool {
    let limit = state.config.idle_timeout;
    let deadline = tokio::time::Instant::now() + limit;
    let sending = sink.send(message);
    tokio::pin!(sending);
    // Most sends complete at once: no timer for them.
    tokio::select! {
        biased;
        sent = &mut sending => return sent.is_ok(),
        () = std::future::ready(()) => {}
    }
    // Blocked on a full socket. The reader half of the same socket may wait
    // for it to turn writable too (a read flushes what is pending and
    // answers pings), and a socket wakes only the last task that waited on
    // it: the send looks again every 50 ms, so a wake-up the reader took
    // cannot leave the client without messages for good.
    let mut again = tokio::time::interval(LOOK_AGAIN);
    loop {
        tokio::select! {
            sent = &mut sending => return sent.is_ok(),
            () = tokio::time::sleep_until(deadline) => {
                tracing::debug!("WebSocket client took no message for {limit:?}: closing");
                return false;
            }
            () = state.shutdown.cancelled() => return false,
            _ = again.tick() => {}
        }
    }
}

/// How often a send blocked on a full socket looks whether it can go on.
const LOOK_AGAIN: Duration = Duration::from_millis(50);

/// A ping every quarter of the idle timeout (at least every 100 ms apart),
/// the first one period from now: a healthy client's pongs keep even a
/// quiet socket open, and their absence tells the reader it has hung.
pub fn pings(state: &ApiState) -> tokio::time::Interval {
    let period = (state.config.idle_timeout / 4).max(Duration::from_millis(100));
    let mut ping = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    ping
}

/// The message a ping sends.
pub fn ping() -> Message {
    Message::Ping(Default::default())
}

/// Closes the socket with 1001 "going away" if its listener is closing
/// (the daemon stops, or a reload reopens the listener), waiting at most a
/// second for a client that does not read.
pub async fn close_if_stopping(state: &ApiState, sink: &mut Sink) {
    if state.shutdown.is_cancelled() {
        let close = Message::Close(Some(CloseFrame {
            code: 1001,
            reason: "drivegate is stopping or reopening this listener".into(),
        }));
        let _ = tokio::time::timeout(Duration::from_secs(1), sink.send(close)).await;
    }
}
