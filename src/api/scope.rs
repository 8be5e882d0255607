//! The scope's routes: arm a capture on a bus (operator: it changes how the
//! bus polls), read its state, trigger it by hand, cancel it, and fetch its
//! samples as JSON or CSV (viewer). Its progress and its trigger go out on
//! the WebSocket stream as `scope` messages (see [`publish_progress`]).

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use tokio_util::sync::CancellationToken;
use utoipa::ToSchema;

use super::caller::authorize;
use super::extract::{JsonBody, PathParams};
use super::hub::Hub;
use super::problem_response::ReadProblems;
use super::problem_response::{Kind, Problem, ProblemDetails};
use super::state::ApiState;
use super::stream_messages::StreamMessage;
use crate::control::{Caller, Operation};
use crate::plant::{Bus, Plant};
use crate::scope::field::{Field, RECORDED};
use crate::scope::result::{self, ScopeResult, ScopeState};
use crate::scope::spec::{Amount, CaptureSpec, SpecError};
use crate::scope::trigger::{Edge, Trigger};
use crate::scope::{Scope, ScopeError};

/// A length: `{"samples": n}` (per captured drive) or `{"seconds": s}`, as
/// read (the document shows it as [`AmountSchema`]).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AmountBody {
    /// Samples of each captured drive.
    #[serde(default)]
    pub samples: Option<u32>,
    /// Seconds.
    #[serde(default)]
    pub seconds: Option<f64>,
}

/// A length: `{"samples": N}` (per captured drive) or `{"seconds": S}`,
/// exactly one. (The document's view of [`AmountBody`], which reads it.)
#[derive(Debug, Deserialize, ToSchema)]
#[serde(untagged, deny_unknown_fields)]
#[allow(dead_code)]
pub enum AmountSchema {
    /// Samples of each captured drive.
    Samples {
        /// Samples of each captured drive.
        #[schema(minimum = 0)]
        samples: u32,
    },
    /// Seconds.
    Seconds {
        /// Seconds.
        #[schema(minimum = 0, maximum = 3600)]
        seconds: f64,
    },
}

impl AmountBody {
    fn amount(&self, what: &str) -> Result<Amount, Problem> {
        match (self.samples, self.seconds) {
            (Some(n), None) => Ok(Amount::Samples(n)),
            (None, Some(s)) => Ok(Amount::Seconds(s)),
            _ => Err(Problem::invalid(format!(
                "give the {what} as {{\"samples\": N}} (per captured drive) or {{\"seconds\": S}}, one of them"
            ))),
        }
    }
}

/// What starts the capture.
#[derive(Debug, Clone, PartialEq, Deserialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case", deny_unknown_fields)]
pub enum TriggerBody {
    /// A field of a captured drive rises through a level (from below it to
    /// at or above it between two samples).
    Rising {
        /// The drive watched (captured).
        drive: String,
        /// The field.
        field: Field,
        /// The level, in the field's unit.
        level: f64,
    },
    /// A field of a captured drive falls through a level.
    Falling {
        /// The drive watched (captured).
        drive: String,
        /// The field.
        field: Field,
        /// The level, in the field's unit.
        level: f64,
    },
    /// A captured drive reports a fault (its fault code leaves 0).
    Fault {
        /// The drive watched (captured).
        drive: String,
    },
    /// A captured drive stalls.
    Stall {
        /// The drive watched (captured).
        drive: String,
    },
    /// A write to the drive goes on the wire, from any face (REST,
    /// WebSocket, Modbus TCP, a lease's end, the shutdown), or a broadcast.
    Write {
        /// The drive written to (any drive of the bus).
        drive: String,
    },
    /// `POST .../scope/trigger`.
    Manual,
    /// At once.
    Immediate,
}

/// `POST /api/v1/buses/{bus}/scope` body.
#[derive(Debug, Clone, PartialEq, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ArmBody {
    /// Drives to capture (names, or units on a single bus), all on this bus.
    /// They get every poll while the capture runs; the other drives keep
    /// `[scope] floor_rate_hz`.
    pub drives: Vec<String>,
    /// Fields to keep (default: all).
    #[serde(default)]
    pub fields: Option<Vec<Field>>,
    /// What starts it.
    pub trigger: TriggerBody,
    /// What to keep from before the trigger (default: nothing).
    #[serde(default)]
    #[schema(value_type = Option<AmountSchema>)]
    pub pre_trigger: Option<AmountBody>,
    /// What to keep from the trigger on.
    #[schema(value_type = AmountSchema)]
    pub length: AmountBody,
    /// How long to wait for the trigger, s (default 300, at most `[scope]
    /// max_wait_s`); then the capture ends `timed-out` with its pre-trigger
    /// samples.
    #[serde(default)]
    #[schema(exclusive_minimum = 0, maximum = 86400)]
    pub wait_s: Option<f64>,
}

/// The scope of a bus: its limits and its current (or last) capture.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ScopeView {
    /// The bus.
    pub bus: String,
    /// Samples a capture may hold (`[scope] max_samples`).
    pub max_samples: usize,
    /// Memory the largest capture takes, bytes.
    pub max_memory_bytes: usize,
    /// Polls per second each drive not captured keeps (`[scope]
    /// floor_rate_hz`).
    pub floor_rate_hz: f64,
    /// Longest wait for a trigger, s (`[scope] max_wait_s`).
    pub max_wait_s: f64,
    /// The most samples per second the wire carries (status reads with no
    /// turnaround): the ceiling of a capture's rate, all drives together.
    pub wire_rate_hz: f64,
    /// The current or last capture, null before the first.
    pub capture: Option<ScopeState>,
}

const DEFAULT_WAIT: Duration = Duration::from_secs(300);

fn scope_problem(e: ScopeError) -> Problem {
    match e {
        ScopeError::Busy { .. } => Problem::new(Kind::ScopeBusy, e.to_string()),
        ScopeError::Invalid(SpecError::Range { range, hint }) => {
            let mut p = Problem::range(&range);
            p.detail.push_str(&hint);
            p
        }
        ScopeError::Invalid(SpecError::Invalid(m)) => Problem::invalid(m),
        ScopeError::None => Problem::new(
            Kind::NoCapture,
            format!("{e}: arm one with POST on this route's bus scope"),
        ),
        ScopeError::State(_) => Problem::new(Kind::CaptureNotRunning, e.to_string()),
    }
}

/// The drive name of `unit` on `bus`.
fn namer(bus: &Bus) -> impl Fn(u8) -> String + '_ {
    move |unit| {
        bus.config
            .drives
            .iter()
            .find(|d| d.unit() == unit)
            .map_or_else(|| format!("unit {unit}"), |d| d.name().to_string())
    }
}

fn current_state(bus: &Bus) -> Option<ScopeState> {
    let name = namer(bus);
    bus.scope()
        .with_capture(|c| result::state(c, bus.handle.name(), &name))
        .ok()
}

/// A drive of `bus` by name (or unit on a single bus).
fn unit_on(state: &ApiState, bus: &Bus, key: &str) -> Result<u8, Problem> {
    let target = state.target(key)?;
    if target.bus.name() != bus.handle.name() {
        return Err(Problem::invalid(format!(
            "drive \"{}\" is on bus \"{}\", not \"{}\": a capture takes the drives of one bus",
            target.drive.name,
            target.bus.name(),
            bus.handle.name()
        )));
    }
    Ok(target.drive.unit)
}

fn spec(state: &ApiState, bus: &Bus, body: &ArmBody) -> Result<CaptureSpec, Problem> {
    let mut units = Vec::new();
    for key in &body.drives {
        let unit = unit_on(state, bus, key)?;
        if !units.contains(&unit) {
            units.push(unit);
        }
    }
    let unit = |key: &str| unit_on(state, bus, key);
    let trigger = match &body.trigger {
        TriggerBody::Rising {
            drive,
            field,
            level,
        } => Trigger::Level {
            unit: unit(drive)?,
            field: field.0,
            level: *level,
            edge: Edge::Rising,
        },
        TriggerBody::Falling {
            drive,
            field,
            level,
        } => Trigger::Level {
            unit: unit(drive)?,
            field: field.0,
            level: *level,
            edge: Edge::Falling,
        },
        TriggerBody::Fault { drive } => Trigger::Fault { unit: unit(drive)? },
        TriggerBody::Stall { drive } => Trigger::Stall { unit: unit(drive)? },
        TriggerBody::Write { drive } => Trigger::Write { unit: unit(drive)? },
        TriggerBody::Manual => Trigger::Manual,
        TriggerBody::Immediate => Trigger::Immediate,
    };
    if let Trigger::Level { level, .. } = trigger
        && !level.is_finite()
    {
        return Err(Problem::invalid("the trigger level must be a number"));
    }
    let wait = match body.wait_s {
        None => DEFAULT_WAIT,
        Some(s) if s.is_finite() && s > 0.0 && s <= 1e6 => Duration::from_secs_f64(s),
        Some(s) => {
            let max = bus.scope().settings().max_wait.as_secs_f64();
            return Err(Problem::range(&crate::drive::RangeError {
                quantity: "trigger wait",
                value: s,
                min: 0.001,
                max,
                unit: "s",
            }));
        }
    };
    Ok(CaptureSpec {
        units,
        fields: body
            .fields
            .as_ref()
            .map_or_else(|| RECORDED.to_vec(), |f| f.iter().map(|f| f.0).collect()),
        trigger,
        pre_trigger: match &body.pre_trigger {
            Some(a) => a.amount("pre-trigger")?,
            None => Amount::Samples(0),
        },
        length: body.length.amount("length")?,
        wait,
    })
}

/// The scope of a bus: its limits, and the state of its current (or last)
/// capture.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/scope",
    tag = "scope",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "The scope", body = ScopeView),
        ReadProblems,
    )
)]
pub async fn get_scope(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<ScopeView>, Problem> {
    let bus = &*state.bus(&name)?;
    let scope = bus.scope();
    scope.tick(Instant::now());
    let limits = scope.limits();
    Ok(Json(ScopeView {
        bus: bus.handle.name().to_string(),
        max_samples: limits.max_samples,
        max_memory_bytes: limits.max_samples * std::mem::size_of::<crate::scope::capture::Sample>(),
        floor_rate_hz: scope.settings().floor_rate_hz,
        max_wait_s: limits.max_wait.as_secs_f64(),
        wire_rate_hz: (limits.wire_rate * 10.0).round() / 10.0,
        capture: current_state(bus),
    }))
}

/// Arms a capture (operator): its drives get every poll from now until it
/// ends, the other drives keep the floor rate, commands and emergency stops
/// keep their priority. One capture per bus at a time.
#[utoipa::path(
    post,
    path = "/api/v1/buses/{bus}/scope",
    tag = "scope",
    security(("bearer" = ["operator"])),
    params(("bus" = String, Path, description = "Bus name")),
    request_body(content = ArmBody, example = json!({
        "drives": ["conveyor"],
        "fields": ["speed_rpm", "current_a"],
        "trigger": {"type": "rising", "drive": "conveyor", "field": "speed_rpm", "level": 100},
        "pre_trigger": {"samples": 50},
        "length": {"seconds": 2.0}
    })),
    responses(
        (status = 201, description = "Armed", body = ScopeState),
        (status = 400, description = "`invalid-request`: a drive of another bus, a trigger on a drive not captured, a malformed body", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 401, description = "`unauthorized`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 403, description = "`forbidden`: needs the operator role", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 404, description = "`unknown-bus`, `unknown-drive`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 409, description = "`scope-busy`: a capture runs on this bus", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 408, description = "`request-timeout`: the body did not arrive within `[http] read_timeout_s`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 413, description = "`payload-too-large`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 415, description = "`unsupported-media-type`: send `Content-Type: application/json`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 422, description = "`out-of-range`: a length, wait or capture size beyond the limits; `valid_range` says which", body = ProblemDetails, content_type = "application/problem+json"),
    )
)]
pub async fn post_scope(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
    JsonBody(body): JsonBody<ArmBody>,
) -> Result<(StatusCode, Json<ScopeState>), Problem> {
    arm(&state, &caller, &name, &body).map(|armed| (StatusCode::CREATED, Json(armed)))
}

/// Arms a capture on bus `name` for `caller` (the REST route and the
/// stream's `scope-arm`).
pub fn arm(
    state: &ApiState,
    caller: &Caller,
    name: &str,
    body: &ArmBody,
) -> Result<ScopeState, Problem> {
    authorize(state, caller, Operation::Capture)?;
    let bus = &*state.bus(name)?;
    let spec = spec(state, bus, body)?;
    let scope = bus.scope();
    let id = scope.arm(spec, Instant::now()).map_err(scope_problem)?;
    bus.handle.wake();
    tracing::info!(who = %caller.who, bus = %bus.handle.name(), capture = id, "scope capture armed");
    current_state(bus).ok_or_else(|| Problem::new(Kind::Internal, "the capture just armed is gone"))
}

/// Cancels the running capture (operator); it keeps what it holds.
#[utoipa::path(
    delete,
    path = "/api/v1/buses/{bus}/scope",
    tag = "scope",
    security(("bearer" = ["operator"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "Cancelled", body = ScopeState),
        (status = 403, description = "`forbidden`: needs the operator role", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 409, description = "`capture-not-running`: it is over", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn delete_scope(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<ScopeState>, Problem> {
    cancel(&state, &caller, &name).map(Json)
}

/// Cancels the capture on bus `name` for `caller` (the REST route and the
/// stream's `scope-cancel`).
pub fn cancel(state: &ApiState, caller: &Caller, name: &str) -> Result<ScopeState, Problem> {
    authorize(state, caller, Operation::Capture)?;
    let bus = &*state.bus(name)?;
    let id = bus.scope().cancel(Instant::now()).map_err(scope_problem)?;
    tracing::info!(who = %caller.who, bus = %bus.handle.name(), capture = id, "scope capture cancelled");
    current_state(bus).ok_or_else(|| Problem::new(Kind::Internal, "the capture is gone"))
}

/// Triggers the armed capture now (operator), whatever its trigger.
#[utoipa::path(
    post,
    path = "/api/v1/buses/{bus}/scope/trigger",
    tag = "scope",
    security(("bearer" = ["operator"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "Triggered", body = ScopeState),
        (status = 403, description = "`forbidden`: needs the operator role", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 409, description = "`capture-not-running`: triggered already, or over", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn post_trigger(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<ScopeState>, Problem> {
    trigger(&state, &caller, &name).map(Json)
}

/// Triggers the capture on bus `name` for `caller` (the REST route and the
/// stream's `scope-trigger`).
pub fn trigger(state: &ApiState, caller: &Caller, name: &str) -> Result<ScopeState, Problem> {
    authorize(state, caller, Operation::Capture)?;
    let bus = &*state.bus(name)?;
    bus.scope()
        .trigger(Instant::now(), caller.origin.clone())
        .map_err(scope_problem)?;
    current_state(bus).ok_or_else(|| Problem::new(Kind::Internal, "the capture is gone"))
}

/// The samples of the current (or last) capture, one trace per drive,
/// columns ready to plot; while it runs, the samples so far.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/scope/result",
    tag = "scope",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "The capture", body = ScopeResult),
        (status = 404, description = "`no-capture`, `unknown-bus`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_result(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<ScopeResult>, Problem> {
    let bus = &*state.bus(&name)?;
    let scope = bus.scope();
    scope.tick(Instant::now());
    let name = namer(bus);
    // Copied out, then rendered: the bus thread never waits for the JSON.
    let capture = scope.snapshot().map_err(scope_problem)?;
    Ok(Json(result::result(&capture, bus.handle.name(), &name)))
}

/// The samples of the current (or last) capture as CSV: `time` (RFC 3339,
/// µs), `t_s` (s from the trigger), `drive`, `unit`, then one column per
/// field named with its unit (`speed_rpm`, `current_a`, ...).
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/scope/result.csv",
    tag = "scope",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "CSV, one row per sample in time order", content_type = "text/csv", body = String),
        (status = 404, description = "`no-capture`, `unknown-bus`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_result_csv(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Response, Problem> {
    let bus = &*state.bus(&name)?;
    let scope = bus.scope();
    scope.tick(Instant::now());
    let name = namer(bus);
    let capture = scope.snapshot().map_err(scope_problem)?;
    let (id, text) = (capture.id(), result::csv(&capture, &name));
    let mut response = text.into_response();
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/csv; charset=utf-8"),
    );
    if let Ok(v) = HeaderValue::from_str(&format!(
        "attachment; filename=\"{}-capture-{id}.csv\"",
        bus.handle.name()
    )) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok(response)
}

/// How often a running capture's progress goes out on the stream.
const PROGRESS_PERIOD: Duration = Duration::from_millis(100);

/// Publishes every bus's capture on the stream: a `scope` message when a
/// capture is armed, when it triggers and when it ends, and its progress
/// every 100 ms while it fills. Also lets time pass for it, so a wait runs
/// out even while its bus is down. Follows the plant: a bus a reload adds
/// or reopens gets its publisher, one it removes loses it. Ends with
/// `shutdown`.
pub fn publish_progress(plant: &Arc<Plant>, hub: &Arc<Hub>, shutdown: &CancellationToken) {
    let hub = hub.clone();
    plant.for_each_bus(shutdown, move |_, bus, stop| {
        publish_bus(bus.clone(), hub.clone(), stop);
    });
}

/// The publisher of one bus's captures, until `shutdown`.
fn publish_bus(bus: Arc<Bus>, hub: Arc<Hub>, shutdown: CancellationToken) {
    {
        tokio::spawn(async move {
            let bus: &Bus = &bus;
            let scope: &Scope = bus.scope();
            let mut last: Option<(u64, &'static str, usize)> = None;
            loop {
                if !scope.is_running() {
                    // One last message for the end, then wait for an arming.
                    publish_change(bus, &hub, &mut last);
                    tokio::select! {
                        () = scope.changed() => {}
                        () = tokio::time::sleep(Duration::from_secs(1)) => {}
                        () = shutdown.cancelled() => return,
                    }
                    continue;
                }
                scope.tick(Instant::now());
                publish_change(bus, &hub, &mut last);
                tokio::select! {
                    () = tokio::time::sleep(PROGRESS_PERIOD) => {}
                    () = shutdown.cancelled() => return,
                }
            }
        });
    }
}

/// Publishes the capture's state if it changed since `last`.
fn publish_change(bus: &Bus, hub: &Hub, last: &mut Option<(u64, &'static str, usize)>) {
    let Some(state) = current_state(bus) else {
        return;
    };
    let key = (
        state.id,
        state.state,
        state.pre_trigger_samples + state.post_trigger_samples,
    );
    if *last == Some(key) {
        return;
    }
    *last = Some(key);
    hub.publish(None, StreamMessage::Scope(state));
}
