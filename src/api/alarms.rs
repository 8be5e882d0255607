//! `GET /api/v1/alarms` and `POST /api/v1/alarms/{id}/ack`: the alarm list
//! the core keeps ([`crate::control::alarms`]), and its acknowledgement,
//! which the core authorises (an operator's work) and audits. The same
//! alarm shape goes on the stream (`alarm-raised`, `alarm-cleared`,
//! `alarm-acknowledged`).

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::{Params, PathParams};
use super::problem_response::ReadProblems;
use super::problem_response::{Kind, Problem, ProblemDetails};
use super::state::ApiState;
use crate::control::{AlarmError, Caller, Rule};
pub use crate::faces_shared::alarms::AlarmView;
use crate::faces_shared::writes::forbidden;
use crate::timestamp::parse_time;

/// Which alarms; every filter is optional.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct AlarmQuery {
    /// `true`: only active ones; `false`: only cleared ones.
    pub active: Option<bool>,
    /// `true`: only those not acknowledged yet; `false`: only acknowledged
    /// ones.
    pub unacknowledged: Option<bool>,
    /// Only this drive's (its name).
    pub drive: Option<String>,
    /// Only those raised, repeated, cleared or acknowledged at or after
    /// this time: RFC 3339 (`2026-11-25T01:00:00Z`) or Unix milliseconds.
    pub since: Option<String>,
}

/// The alarm list.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AlarmList {
    /// The alarms the filters let through, newest first.
    pub alarms: Vec<AlarmView>,
    /// Active alarms in the whole list (whatever the filters).
    pub active: u64,
    /// Alarms not acknowledged in the whole list (whatever the filters):
    /// the console shows its banner while this is not 0.
    pub unacknowledged: u64,
    /// Alarms kept at most (`[safety] alarms_kept`): past it the oldest
    /// cleared and acknowledged ones are dropped first.
    pub kept_at_most: usize,
}

/// The alarms, newest first: faults, stalls, drives offline, buses down,
/// communication-loss stops, stops not confirmed and writes refused by a
/// safety rule, with what they mean and what to check; kept across
/// restarts in `[safety] state_dir`.
#[utoipa::path(
    get,
    path = "/api/v1/alarms",
    tag = "alarms",
    security(("bearer" = ["viewer"])),
    params(AlarmQuery),
    responses(
        (status = 200, description = "The alarms, newest first, and the counts of the whole list", body = AlarmList),
        ReadProblems,
    )
)]
pub async fn list_alarms(
    State(state): State<ApiState>,
    _caller: Caller,
    Params(mut query): Params<AlarmQuery>,
) -> Result<Json<AlarmList>, Problem> {
    // An empty filter (`?drive=`, as a form sends it) is no filter.
    query.drive = query.drive.filter(|d| !d.is_empty());
    query.since = query.since.filter(|t| !t.is_empty());
    let since = match &query.since {
        None => None,
        Some(text) => Some(
            parse_time(text)
                .map(crate::control::journal::format::unix_ms)
                .ok_or_else(|| {
                    Problem::invalid(format!(
                        "since = {text:?} is not a time: give RFC 3339 (2026-11-25T01:00:00Z) or Unix milliseconds"
                    ))
                })?,
        ),
    };
    if let Some(drive) = &query.drive {
        // A drive that is not configured (any more) may still have alarms.
        let known = state.plant.now().drives().any(|d| &d.name == drive)
            || state
                .control
                .alarms()
                .list()
                .iter()
                .any(|a| a.drive.as_ref() == Some(drive));
        if !known {
            return Err(Problem::new(
                Kind::UnknownDrive,
                format!(
                    "{}, and none of that name has alarms",
                    crate::plant::unknown_drive(
                        drive,
                        &state
                            .plant
                            .now()
                            .drives()
                            .map(|d| d.name.clone())
                            .collect::<Vec<_>>()
                    )
                ),
            ));
        }
    }
    let alarms = state.control.alarms();
    let summary = alarms.summary();
    let list = alarms
        .list()
        .iter()
        .rev()
        .filter(|a| query.active.is_none_or(|want| a.active() == want))
        .filter(|a| {
            query
                .unacknowledged
                .is_none_or(|want| a.ack.is_none() == want)
        })
        .filter(|a| query.drive.is_none() || a.drive == query.drive)
        .filter(|a| {
            since.is_none_or(|s| {
                a.raised_ms >= s
                    || a.last_ms >= s
                    || a.cleared_ms.is_some_and(|c| c >= s)
                    || a.ack.as_ref().is_some_and(|k| k.at_ms >= s)
            })
        })
        .map(AlarmView::from)
        .collect();
    Ok(Json(AlarmList {
        alarms: list,
        active: summary.active.values().sum(),
        unacknowledged: summary.unacknowledged,
        kept_at_most: alarms.kept_at_most(),
    }))
}

/// Acknowledges an alarm (operator): the alarm says who and when, the
/// audit log has a line, and the stream an `alarm-acknowledged` message.
/// Acknowledging an alarm already acknowledged keeps the first
/// acknowledgement and answers it. An active alarm stays active until its
/// condition ends.
#[utoipa::path(
    post,
    path = "/api/v1/alarms/{id}/ack",
    tag = "alarms",
    security(("bearer" = ["operator"])),
    params(("id" = u64, Path, description = "The alarm's number")),
    responses(
        (status = 200, description = "The alarm, acknowledged", body = AlarmView),
        (status = 400, description = "`invalid-request`: the id is not a number", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 401, description = "`unauthorized`", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 403, description = "`forbidden`: needs the operator role", body = ProblemDetails, content_type = "application/problem+json"),
        (status = 404, description = "`not-found`: no such alarm (or it was dropped to keep the list within its bound)", body = ProblemDetails, content_type = "application/problem+json"),
    )
)]
pub async fn post_ack(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(id): PathParams<u64>,
) -> Result<Json<AlarmView>, Problem> {
    acknowledge(&state, &caller, id).await.map(Json)
}

/// The stream's `alarm-ack` body: `{"alarm": id}`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AckBody {
    /// The alarm's number.
    pub alarm: u64,
}

/// Acknowledges alarm `id` for `caller` through the core (the REST route
/// and the stream's `alarm-ack`).
pub async fn acknowledge(state: &ApiState, caller: &Caller, id: u64) -> Result<AlarmView, Problem> {
    match state.control.acknowledge_alarm(caller, id).await {
        Ok(alarm) => Ok(AlarmView::from(&alarm)),
        Err(AlarmError::Refused(refusal)) => match refusal.rule {
            Rule::Role { needed, .. } => Err(forbidden(caller, needed)),
            _ => Err(Problem::new(Kind::Forbidden, refusal.detail)),
        },
        Err(AlarmError::Unknown(e)) => Err(Problem::new(Kind::NotFound, e.to_string())),
    }
}
