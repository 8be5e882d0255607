//! The bus monitor's live feed: every frame on the wire of a bus over a
//! WebSocket, filtered, paused and resumed by the client.
//!
//! The feed reads the bus's ring behind the bus thread, every 50 ms, and
//! sends what it found in one message. A client that reads slowly holds
//! up only itself: the frames it had not read when the ring came round are
//! lost to it, and the next message says how many (`lost`).

use std::time::Duration;

use axum::extract::State;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::response::Response;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, watch};
use utoipa::{IntoParams, ToSchema};

use super::caller::StreamCaller;
use super::extract::{Params, PathParams};
use super::problem_response::ReadProblems;
use super::problem_response::{Problem, ProblemDetails};
use super::socket::{self, Sink, Source, send};
use super::state::ApiState;
use super::state::monitor_of;
use crate::monitor::feed::Feed;
use crate::monitor::filter::{FilterText, FrameFilter};
use crate::monitor::view::FrameView;

/// How often the live feed looks for new frames.
const FEED_PERIOD: Duration = Duration::from_millis(50);
/// Frames one live message holds at most.
const FEED_BATCH: usize = 500;
/// Frames a live client gets from before it connected, by default.
const DEFAULT_BACKLOG: usize = 100;

/// Live feed query parameters: the filters of `frames`, and:
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct LiveQuery {
    /// Units: `1,3-4`.
    pub unit: Option<String>,
    /// Function codes: `3,0x06`.
    pub function: Option<String>,
    /// Outcomes (and `retry`).
    pub outcome: Option<String>,
    /// Sources: `modbus-tcp,http`.
    pub source: Option<String>,
    /// The client behind the source.
    pub who: Option<String>,
    /// Frames from before the connection to send first (default 100, at
    /// most the ring).
    pub backlog: Option<usize>,
    /// The API token in the URL: discouraged (proxies and logs keep URLs),
    /// kept for old scripts; offer the subprotocols `drivegate` and
    /// `drivegate.bearer.<base64url token>` instead.
    pub access_token: Option<String>,
}

/// A message the live feed sends.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum MonitorMessage {
    /// New frames that pass the filter (possibly none, when only `lost`
    /// has news).
    Frames {
        /// The bus.
        bus: String,
        /// The frames, oldest first.
        frames: Vec<FrameView>,
        /// Frames lost since the previous message: this client read too
        /// slowly, and the ring overwrote them first.
        lost: u64,
        /// Frames lost since the client connected.
        lost_total: u64,
    },
    /// The filter and pause state now in force (after a `filter`, `pause`
    /// or `resume`, and once at the start).
    State {
        /// Units (empty: all).
        units: Vec<u8>,
        /// Function codes (empty: all).
        functions: Vec<u8>,
        /// Outcomes (empty: all).
        outcomes: Vec<String>,
        /// Only retries.
        retries_only: bool,
        /// Sources (empty: all).
        sources: Vec<String>,
        /// The client, if filtered.
        who: Option<String>,
        /// True while paused: frames wait in the ring (and are lost if the
        /// ring comes round before `resume`).
        paused: bool,
    },
    /// A message from the client could not be understood.
    Error {
        /// What was wrong.
        #[schema(value_type = ProblemDetails)]
        problem: Problem,
    },
}

impl MonitorMessage {
    fn text(&self) -> Utf8Bytes {
        serde_json::to_string(self)
            .unwrap_or_else(|e| format!("{{\"type\":\"error\",\"detail\":\"{e}\"}}"))
            .into()
    }

    fn state(filter: &FrameFilter, paused: bool) -> Self {
        MonitorMessage::State {
            units: filter.units.clone(),
            functions: filter.functions.clone(),
            outcomes: filter
                .outcomes
                .iter()
                .map(|o| o.name().to_string())
                .collect(),
            retries_only: filter.retries_only,
            sources: filter.sources.iter().map(|s| s.to_string()).collect(),
            who: filter.who.clone(),
            paused,
        }
    }
}

/// A message a live client sends.
#[derive(Debug, Clone, PartialEq, Deserialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case", deny_unknown_fields)]
pub enum MonitorClientMessage {
    /// Replaces the filter (same syntax as the query parameters; an absent
    /// field lets all through).
    Filter {
        /// Units: `1,3-4`.
        #[serde(default)]
        unit: Option<String>,
        /// Function codes.
        #[serde(default)]
        function: Option<String>,
        /// Outcomes (and `retry`).
        #[serde(default)]
        outcome: Option<String>,
        /// Sources.
        #[serde(default)]
        source: Option<String>,
        /// The client behind the source.
        #[serde(default)]
        who: Option<String>,
    },
    /// Stops sending; frames wait in the ring.
    Pause,
    /// Sends again, from where it paused.
    Resume,
}

/// Every frame on the wire of a bus, live (WebSocket).
///
/// Connect with a WebSocket client (the token in the Authorization header,
/// or from a browser as the subprotocol `drivegate.bearer.<base64url
/// token>` offered beside `drivegate`); the server sends `state`, then
/// `frames` messages
/// (every 50 ms while there are new frames), each with `lost`: frames this
/// client lost by reading too slowly. Send `filter`, `pause`, `resume`.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/monitor/live",
    tag = "monitor",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name"), LiveQuery),
    responses(
        (status = 101, description = "Switching to the WebSocket protocol; then MonitorMessage JSON texts", body = MonitorMessage),
        (status = 409, description = "`monitor-off`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn live(
    State(state): State<ApiState>,
    StreamCaller(caller): StreamCaller,
    PathParams(name): PathParams<String>,
    Params(query): Params<LiveQuery>,
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<Response, Problem> {
    let upgrade = socket::upgrade(upgrade)?;
    let bus = &*state.bus(&name)?;
    let monitor = monitor_of(bus)?.clone();
    let filter = FrameFilter::parse(&FilterText {
        units: query.unit.as_deref(),
        functions: query.function.as_deref(),
        outcomes: query.outcome.as_deref(),
        sources: query.source.as_deref(),
        who: query.who.as_deref(),
    })
    .map_err(Problem::invalid)?;
    let backlog = query
        .backlog
        .unwrap_or(DEFAULT_BACKLOG)
        .min(monitor.capacity());
    let bus_name = bus.handle.name().to_string();
    let session_state = state.clone();
    tracing::debug!(who = %caller.who, bus = %bus_name, "monitor client connected");
    Ok(socket::accept(&state, upgrade, move |socket| {
        let feed = Feed::new(monitor, filter, backlog);
        session(session_state, bus_name, feed, socket)
    }))
}

/// What a client asked for: a new filter, pause or resume.
#[derive(Debug)]
struct Asked {
    filter: Option<FrameFilter>,
    paused: Option<bool>,
}

/// A client's message as what it asks for, or the problem with it.
fn parse(text: &str) -> Result<Asked, Problem> {
    let message = serde_json::from_str::<MonitorClientMessage>(text).map_err(|e| {
        Problem::invalid(format!(
            "not a valid monitor message: {e}; send {{\"type\":\"filter\",\"unit\":\"1,2\",\"outcome\":\"timeout\"}}, {{\"type\":\"pause\"}} or {{\"type\":\"resume\"}}"
        ))
    })?;
    Ok(match message {
        MonitorClientMessage::Filter {
            unit,
            function,
            outcome,
            source,
            who,
        } => Asked {
            filter: Some(
                FrameFilter::parse(&FilterText {
                    units: unit.as_deref(),
                    functions: function.as_deref(),
                    outcomes: outcome.as_deref(),
                    sources: source.as_deref(),
                    who: who.as_deref(),
                })
                .map_err(Problem::invalid)?,
            ),
            paused: None,
        },
        MonitorClientMessage::Pause => Asked {
            filter: None,
            paused: Some(true),
        },
        MonitorClientMessage::Resume => Asked {
            filter: None,
            paused: Some(false),
        },
    })
}

/// The reader: the client's messages become the filter and pause it
/// asks for, or an error to send it. Its silence (not even a pong to our
/// pings for `idle`) ends the session.
async fn read(
    mut stream: Source,
    idle: Duration,
    asked: watch::Sender<(FrameFilter, bool)>,
    errors: mpsc::Sender<Utf8Bytes>,
) {
    loop {
        let Ok(Some(Ok(message))) = tokio::time::timeout(idle, stream.next()).await else {
            return;
        };
        let text = match message {
            Message::Text(text) => text,
            Message::Close(_) => return,
            _ => continue,
        };
        match parse(text.as_str()) {
            Ok(Asked { filter, paused }) => asked.send_modify(|(f, p)| {
                if let Some(filter) = filter {
                    *f = filter;
                }
                if let Some(paused) = paused {
                    *p = paused;
                }
            }),
            Err(problem) => {
                let text = MonitorMessage::Error { problem }.text();
                if errors.send(text).await.is_err() {
                    return;
                }
            }
        }
    }
}

async fn session(state: ApiState, bus: String, mut feed: Feed, socket: WebSocket) {
    let (mut sink, stream) = socket.split();
    let (control_tx, mut control) = watch::channel((feed.filter().clone(), false));
    let (errors_tx, mut errors) = mpsc::channel::<Utf8Bytes>(8);
    let reader = tokio::spawn(read(
        stream,
        state.config.idle_timeout,
        control_tx,
        errors_tx,
    ));

    let mut tick = tokio::time::interval(FEED_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut ping = socket::pings(&state);
    let mut paused = false;
    let mut lost_total = 0u64;
    // A `state` message to send before anything else: the first one, and
    // the answer to each filter, pause or resume.
    let mut pending_state = Some(MonitorMessage::state(feed.filter(), false).text());
    let reader_done = reader;
    tokio::pin!(reader_done);
    loop {
        if let Some(text) = pending_state.take()
            && !send(&state, &mut sink, Message::Text(text)).await
        {
            break;
        }
        tokio::select! {
            biased;
            () = state.shutdown.cancelled() => break,
            _ = &mut reader_done => break,
            Some(error) = errors.recv() => {
                if !send(&state, &mut sink, Message::Text(error)).await {
                    break;
                }
                continue;
            }
            Ok(()) = control.changed() => {
                let (filter, p) = control.borrow_and_update().clone();
                paused = p;
                pending_state = Some(MonitorMessage::state(&filter, paused).text());
                feed.set_filter(filter);
                continue;
            }
            _ = ping.tick() => {
                if !send(&state, &mut sink, socket::ping()).await {
                    break;
                }
                continue;
            }
            _ = tick.tick() => {}
        }
        if !paused && !send_news(&state, &mut sink, &bus, &mut feed, &mut lost_total).await {
            break;
        }
    }
    reader_done.abort();
    socket::close_if_stopping(&state, &mut sink).await;
    tracing::debug!(bus = %bus, "monitor client gone");
}

/// Sends everything new, in messages of at most FEED_BATCH frames; false
/// once the client is gone.
async fn send_news(
    state: &ApiState,
    sink: &mut Sink,
    bus: &str,
    feed: &mut Feed,
    lost_total: &mut u64,
) -> bool {
    while feed.has_news() {
        let batch = feed.poll(FEED_BATCH);
        *lost_total += batch.lost;
        if batch.frames.is_empty() && batch.lost == 0 {
            continue;
        }
        let clock = feed_clock(feed);
        let message = MonitorMessage::Frames {
            bus: bus.to_string(),
            frames: batch
                .frames
                .iter()
                .map(|r| FrameView::new(r, &clock))
                .collect(),
            lost: batch.lost,
            lost_total: *lost_total,
        };
        if !send(state, sink, Message::Text(message.text())).await {
            return false;
        }
    }
    true
}

fn feed_clock(feed: &Feed) -> crate::monitor::view::WallClock {
    *feed.monitor().clock()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_messages_parse() {
        let m: MonitorClientMessage =
            serde_json::from_str(r#"{"type":"filter","unit":"1","outcome":"timeout"}"#).unwrap();
        assert!(matches!(m, MonitorClientMessage::Filter { .. }));
        let m: MonitorClientMessage = serde_json::from_str(r#"{"type":"pause"}"#).unwrap();
        assert_eq!(m, MonitorClientMessage::Pause);
        assert!(
            serde_json::from_str::<MonitorClientMessage>(r#"{"type":"filter","x":1}"#).is_err()
        );
    }

    #[test]
    fn a_message_asks_for_a_filter_or_a_pause_or_says_what_is_wrong() {
        let asked = parse(r#"{"type":"filter","unit":"1,2","outcome":"timeout"}"#).unwrap();
        assert!(asked.filter.is_some());
        assert_eq!(asked.paused, None);
        let asked = parse(r#"{"type":"pause"}"#).unwrap();
        assert!(asked.filter.is_none());
        assert_eq!(asked.paused, Some(true));
        assert_eq!(parse(r#"{"type":"resume"}"#).unwrap().paused, Some(false));
        let problem = parse(r#"{"type":"dance"}"#).unwrap_err();
        assert!(
            problem
                .details()
                .detail
                .starts_with("not a valid monitor message: "),
            "{problem:?}"
        );
        assert!(parse(r#"{"type":"filter","unit":"x"}"#).is_err());
    }
}
