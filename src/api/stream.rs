//! The WebSocket stream `GET /api/v1/stream`: a client subscribes to some
//! or all drives and receives every status as soon as it is polled, online
//! and offline events and lease expiries; it may send commands on the same
//! socket and gets replies correlated by the `id` it chose.
//!
//! Each session has three parts: a forwarder that takes the hub's messages
//! for the subscribed drives into a bounded buffer (`[http] stream_buffer`)
//! without ever waiting, a writer that drains that buffer into the socket,
//! and a reader that handles the client's messages. When the client reads
//! too slowly the buffer fills, further updates are skipped and counted,
//! and the client is told `{"type":"lagged","missed":N}` before the next
//! update it gets: a slow client never slows the bus or the other clients.
//!
//! The end of a lease taken over the socket is sent to it directly, beside
//! the forwarder: it is never skipped for a slow client, and needs no
//! subscription. Leases granted over the socket end when it closes. The
//! commands still in flight then are cancelled first (see [`InFlight`]), so
//! the stop a lease's end sends never overtakes the setpoint it covers.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use axum::extract::State;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::response::Response;
use futures_util::StreamExt;
use serde::Deserialize;
use tokio::sync::{Semaphore, broadcast, mpsc};
use tokio::task::JoinSet;
use tokio::time::{Instant, timeout_at};
use tokio_util::task::TaskTracker;
use utoipa::IntoParams;

use super::caller::StreamCaller;
use super::extract::Params;
use super::hub::{HubEvent, render};
use super::problem_response::{Problem, ReadProblems};
use super::socket::{self, Sink, Source, send};
use super::state::ApiState;
use super::stream_commands::{self, Command};
/// What a client sends on the stream (its home is [`super::stream_messages`]).
pub use super::stream_messages::ClientMessage;
use super::stream_messages::{DriveSelection, RestartDecision, ServerMessage, StreamMessage};
use crate::control::{Caller, ControlEvent, Face, SessionId};
use crate::faces_shared::messages::DriveMessage;
use crate::timestamp::rfc3339;

/// Replies (and other answers to the client's own messages) that may wait.
const REPLY_BUFFER: usize = 64;
/// Commands of one client in flight at once.
const COMMANDS_IN_FLIGHT: usize = 16;

/// Stream query parameters.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct StreamQuery {
    /// Subscribe at once: `all`, or drive names separated by commas.
    pub drives: Option<String>,
    /// The API token in the URL: discouraged (proxies and logs keep URLs),
    /// kept for old scripts; offer the subprotocols `drivegate` and
    /// `drivegate.bearer.<base64url token>` instead.
    pub access_token: Option<String>,
}

/// Drive indexes of a selection.
fn resolve(state: &ApiState, selection: &DriveSelection) -> Result<Vec<usize>, Problem> {
    let keys: Vec<&str> = match selection {
        DriveSelection::One(s) if s == "all" => {
            return Ok(state.plant.now().indexed_drives().map(|(i, _)| i).collect());
        }
        DriveSelection::One(s) => vec![s.as_str()],
        DriveSelection::Many(list) => list.iter().map(String::as_str).collect(),
    };
    keys.into_iter()
        .map(|k| state.target(k).map(|t| t.index))
        .collect()
}

/// Streams statuses, online/offline and lease events; takes commands.
///
/// Connect with a WebSocket client (the token in the Authorization header,
/// or from a browser as the subprotocol `drivegate.bearer.<base64url
/// token>` offered beside `drivegate`, which is answered), then send
/// `{"type":"subscribe","drives":"all"}` (or pass `?drives=all`). Messages
/// from the server are `ServerMessage`s; messages to it `ClientMessage`s.
#[utoipa::path(
    get,
    path = "/api/v1/stream",
    tag = "stream",
    security(("bearer" = ["viewer"])),
    params(StreamQuery),
    responses(
        (status = 101, description = "Switching to the WebSocket protocol; then ServerMessage JSON texts", body = ServerMessage),
        ReadProblems,
    )
)]
pub async fn stream(
    State(state): State<ApiState>,
    StreamCaller(caller): StreamCaller,
    Params(query): Params<StreamQuery>,
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<Response, Problem> {
    let upgrade = socket::upgrade(upgrade)?;
    let all = query.drives.as_deref() == Some("all");
    let initial = match query.drives.as_deref() {
        None | Some("") => Vec::new(),
        Some("all") => resolve(&state, &DriveSelection::One("all".to_string()))?,
        Some(list) => resolve(
            &state,
            &DriveSelection::Many(list.split(',').map(|s| s.trim().to_string()).collect()),
        )?,
    };
    let session_state = state.clone();
    Ok(socket::accept(&state, upgrade, move |socket| {
        session(session_state, caller, socket, (initial, all))
    }))
}

/// Which drives a session receives: one flag per drive of the plant, read
/// by the forwarder for every message without locking.
/// With `all`, drives a reload adds are in it too.
#[derive(Default)]
struct Selection {
    all: AtomicBool,
    drives: std::sync::RwLock<std::collections::BTreeSet<usize>>,
}

impl Selection {
    fn set(&self, indexes: &[usize], all: bool) {
        let mut drives = self.drives.write().unwrap_or_else(|p| p.into_inner());
        *drives = indexes.iter().copied().collect();
        self.all.store(all, Ordering::Relaxed);
    }

    fn wants(&self, drive: Option<usize>) -> bool {
        if self.all.load(Ordering::Relaxed) {
            return true;
        }
        let drives = self.drives.read().unwrap_or_else(|p| p.into_inner());
        match drive {
            Some(i) => drives.contains(&i),
            None => !drives.is_empty(),
        }
    }
}

async fn session(
    state: ApiState,
    caller: Caller,
    socket: WebSocket,
    (initial, all): (Vec<usize>, bool),
) {
    let _counted = state.metrics.faces().ws_client();
    // Its leases end when it closes. News of their end comes on an
    // unbounded channel, but only a lease of this client's own adds to it.
    let (guard, notices_rx) = state.control.open_session("its WebSocket closed", None);
    let connection = guard.id();
    let caller = caller.in_session(Face::WebSocket, connection);
    tracing::debug!(who = %caller.who, connection = connection.0, "stream client connected");

    let selection = Arc::new(Selection::default());
    selection.set(&initial, all);
    let missed = Arc::new(AtomicU64::new(0));
    let (events_tx, events_rx) = mpsc::channel(state.config.stream_buffer);
    let (replies_tx, replies_rx) = mpsc::channel(REPLY_BUFFER);
    let forwarder = tokio::spawn(forward(
        state.hub.subscribe(),
        connection,
        selection.clone(),
        missed.clone(),
        events_tx,
    ));
    if !initial.is_empty() {
        let _ = replies_tx.try_send(subscribed(&state, &initial));
    }

    let (sink, stream) = socket.split();
    let mut in_flight = InFlight::default();
    let writer = write_loop(&state, sink, replies_rx, notices_rx, events_rx, &missed);
    let reader = read_loop(
        &state,
        &caller,
        connection,
        stream,
        &selection,
        replies_tx,
        &mut in_flight,
    );
    tokio::select! {
        () = writer => {}
        () = reader => {}
    }
    forwarder.abort();
    // Only once no command of this session can reach the bus any more.
    in_flight.end().await;
    drop(guard);
    tracing::debug!(who = %caller.who, connection = connection.0, "stream client gone");
}

/// The session's commands in flight, each a task beside the reader.
///
/// When the socket closes they are cancelled before the session's leases
/// end: a command whose job still waits in the bus queue is then dropped
/// unsent (its caller has gone, as for an HTTP client that disconnects),
/// and one already on the wire completes before the stop, which is queued
/// only afterwards. Otherwise a setpoint queued at command priority would
/// reach the drive after the stop its lease's end sent at emergency
/// priority, and leave the motor running with no lease. Emergency brakes
/// are let finish instead: dropping one would leave the motor running, and
/// a brake confirmed first ends the lease, whose zero-speed stop would
/// release it.
#[derive(Default)]
struct InFlight {
    cancellable: JoinSet<()>,
    brakes: JoinSet<()>,
}

impl InFlight {
    /// Runs `task` (an emergency brake if `brake`), tracked by `tracker` so
    /// a graceful stop waits for it.
    fn spawn<F>(&mut self, tracker: &TaskTracker, brake: bool, task: F)
    where
        F: Future<Output = ()> + Send + 'static,
    {
        // Finished ones have nothing to report: forget them.
        while self.cancellable.try_join_next().is_some() {}
        while self.brakes.try_join_next().is_some() {}
        let task = tracker.track_future(task);
        if brake {
            self.brakes.spawn(task);
        } else {
            self.cancellable.spawn(task);
        }
    }

    /// Cancels the commands, lets the brakes finish, and returns when none
    /// is left.
    async fn end(mut self) {
        self.cancellable.shutdown().await;
        while self.brakes.join_next().await.is_some() {}
    }
}

/// Takes the hub's messages for the selected drives into the session's
/// bounded buffer; never waits, counts what does not fit. Messages the
/// session got directly (its own leases' ends) are skipped.
async fn forward(
    mut hub: broadcast::Receiver<HubEvent>,
    connection: SessionId,
    selection: Arc<Selection>,
    missed: Arc<AtomicU64>,
    events: mpsc::Sender<Utf8Bytes>,
) {
    loop {
        match hub.recv().await {
            Ok(event) => {
                if event.delivered_to == Some(connection) || !selection.wants(event.drive) {
                    continue;
                }
                match events.try_send(event.text) {
                    Ok(()) => {}
                    Err(mpsc::error::TrySendError::Full(_)) => {
                        missed.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(mpsc::error::TrySendError::Closed(_)) => return,
                }
            }
            Err(broadcast::error::RecvError::Lagged(n)) => {
                missed.fetch_add(n, Ordering::Relaxed);
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

/// Sends replies first, then news of the client's own leases, then
/// updates (each preceded by a `lagged` notice when some were skipped), and
/// a ping every quarter of the idle timeout, busy or not: a healthy
/// client's pongs keep even a quiet stream open, and their absence tells
/// the reader a client has hung (see [`read_loop`]); closes the socket when
/// the daemon stops.
async fn write_loop(
    state: &ApiState,
    mut sink: Sink,
    mut replies: mpsc::Receiver<Utf8Bytes>,
    mut notices: mpsc::UnboundedReceiver<Arc<ControlEvent>>,
    mut events: mpsc::Receiver<Utf8Bytes>,
    missed: &AtomicU64,
) {
    let mut ping = socket::pings(state);
    loop {
        let next = tokio::select! {
            biased;
            () = state.shutdown.cancelled() => None,
            Some(reply) = replies.recv() => Some(Message::Text(reply)),
            Some(notice) = notices.recv() => match render(&state.plant, &notice) {
                Some(text) => Some(Message::Text(text)),
                None => continue,
            },
            // Before updates: a stream always busy must still be pinged.
            _ = ping.tick() => Some(socket::ping()),
            Some(event) = events.recv() => {
                let n = missed.swap(0, Ordering::Relaxed);
                if n > 0 && !send(state, &mut sink, Message::Text(StreamMessage::Lagged { missed: n }.to_text())).await {
                    return;
                }
                Some(Message::Text(event))
            }
            else => None,
        };
        match next {
            Some(message) => {
                if !send(state, &mut sink, message).await {
                    return;
                }
            }
            None => break,
        }
    }
    socket::close_if_stopping(state, &mut sink).await;
}

fn subscribed(state: &ApiState, indexes: &[usize]) -> Utf8Bytes {
    let drives: Vec<String> = indexes
        .iter()
        .filter_map(|&i| state.plant.now().drive_at(i).map(|d| d.name.clone()))
        .collect();
    let restart = state
        .control
        .restart_notes()
        .into_iter()
        .filter(|n| drives.contains(&n.drive))
        .map(|n| RestartDecision {
            drive: n.drive,
            decision: n.decision.name().to_string(),
            who: n.who,
            text: n.text,
            at: rfc3339(n.at),
        })
        .collect();
    StreamMessage::Subscribed { drives, restart }.to_text()
}

/// Handles the client's messages until it closes the socket, or sends
/// nothing at all, not even the pong to a ping, for the idle timeout: a
/// hung client that still holds its socket open (its kernel keeps the TCP
/// connection alive and takes the pings) would otherwise hold a connection
/// slot for ever. Time spent waiting for a free command slot or for room
/// for an answer counts as silence too: both wait on a client that does
/// not read its replies.
async fn read_loop(
    state: &ApiState,
    caller: &Caller,
    connection: SessionId,
    mut stream: Source,
    selection: &Selection,
    replies: mpsc::Sender<Utf8Bytes>,
    commands: &mut InFlight,
) {
    let in_flight = Arc::new(Semaphore::new(COMMANDS_IN_FLIGHT));
    let silence = state.config.idle_timeout;
    let mut deadline = Instant::now() + silence;
    let gone = |what: &str| {
        tracing::debug!(who = %caller.who, connection = connection.0, "stream client {what} for {silence:?}: closing");
    };
    loop {
        let Ok(next) = timeout_at(deadline, stream.next()).await else {
            gone("sent nothing, not even a pong,");
            return;
        };
        deadline = Instant::now() + silence;
        let answer = match next {
            Some(Ok(Message::Text(text))) => match serde_json::from_str(text.as_str()) {
                Err(e) => not_understood(&e),
                Ok(ClientMessage::Subscribe { drives }) => subscribe(state, selection, &drives),
                Ok(ClientMessage::Command {
                    id,
                    op,
                    drive,
                    bus,
                    body,
                }) => {
                    let permit = match timeout_at(deadline, in_flight.clone().acquire_owned()).await
                    {
                        Ok(Ok(permit)) => permit,
                        Ok(Err(_)) => return,
                        Err(_) => {
                            gone("left every command slot taken (it reads no replies)");
                            return;
                        }
                    };
                    let command = Command {
                        op,
                        drive,
                        bus,
                        body,
                    };
                    let brake = command.survives_its_caller();
                    let tracker = state.sessions.clone();
                    let (state, caller, replies) = (state.clone(), caller.clone(), replies.clone());
                    // Commands run beside the reader, so a slow one (a scan,
                    // a timeout) does not hold up lease renewals sent after it.
                    commands.spawn(&tracker, brake, async move {
                        let result = stream_commands::run(&state, &caller, command).await;
                        let reply = ServerMessage::from(DriveMessage::reply(id, result));
                        let _ = replies.send(reply.to_text()).await;
                        drop(permit);
                    });
                    continue;
                }
            },
            Some(Ok(Message::Binary(_))) => {
                error(Problem::invalid("send JSON text messages, not binary ones"))
            }
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            Some(Ok(Message::Close(_)) | Err(_)) | None => return,
        };
        match timeout_at(deadline, replies.send(answer)).await {
            Ok(Ok(())) => {}
            Ok(Err(_)) => return,
            Err(_) => {
                gone("read no answer");
                return;
            }
        }
    }
}

fn error(problem: Problem) -> Utf8Bytes {
    StreamMessage::Error { problem }.to_text()
}

fn not_understood(e: &serde_json::Error) -> Utf8Bytes {
    error(Problem::invalid(format!(
        "not a valid stream message: {e}; send {{\"type\":\"subscribe\",\"drives\":\"all\"}} or {{\"type\":\"command\",\"id\":1,\"op\":\"activate\",\"drive\":\"NAME\"}}"
    )))
}

/// Takes the drives of `drives` from now on: answered with `subscribed`.
fn subscribe(state: &ApiState, selection: &Selection, drives: &DriveSelection) -> Utf8Bytes {
    match resolve(state, drives) {
        Ok(indexes) => {
            let all = matches!(drives, DriveSelection::One(s) if s == "all");
            selection.set(&indexes, all);
            subscribed(state, &indexes)
        }
        Err(problem) => error(problem),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selection_flags() {
        let s = Selection::default();
        assert!(!s.wants(None));
        s.set(&[1], false);
        assert!(s.wants(Some(1)) && !s.wants(Some(0)) && s.wants(None));
        assert!(!s.wants(Some(7)));
        // "all" takes the drives a reload adds too.
        s.set(&[0, 1], true);
        assert!(s.wants(Some(7)));
    }
}
