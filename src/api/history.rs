//! `GET /api/v1/drives/{drive}/history`: a drive's trend over the last
//! `[history] minutes`, as columns a chart takes as they are: one array of
//! times and, per field asked, arrays of minimum, maximum and mean.
//! Recent points are single samples at the poll rate (`span_ms` 0),
//! older ones one-second buckets ([`crate::history`]).

use std::collections::BTreeMap;
use std::time::SystemTime;

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::{Params, PathParams};
use super::problem_response::Problem;
use super::problem_response::ReadProblems;
use super::state::ApiState;
use crate::control::Caller;
use crate::drive::StatusField;
use crate::history::store::{KEPT, Point};
use crate::history::unix_ms;
use crate::timestamp::{parse_time, rfc3339};

/// Points an answer holds when `max_points` is not given: an hour of
/// buckets plus a minute at 100 reads a second.
const DEFAULT_MAX_POINTS: usize = 10_000;
/// Points an answer may hold.
const MAX_POINTS: usize = 100_000;

/// What to return.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct HistoryQuery {
    /// Fields, comma-separated: `speed_rpm`, `current_a`, `voltage_v`,
    /// `temperature_c`, `angle_deg` (default: all).
    pub fields: Option<String>,
    /// From this time: RFC 3339 (`2026-11-25T01:00:00Z`) or Unix
    /// milliseconds (default: as far back as kept).
    pub since: Option<String>,
    /// Up to this time, as `since` (default: now).
    pub until: Option<String>,
    /// Points at most (default 10000, at most 100000): more are merged,
    /// runs of neighbours into one point (their minimum, maximum and mean).
    #[param(minimum = 1, maximum = 100_000)]
    pub max_points: Option<usize>,
}

/// One field's columns, in engineering units, one value per point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct HistoryColumn {
    /// The lowest value in each point.
    pub min: Vec<f64>,
    /// The highest value in each point.
    pub max: Vec<f64>,
    /// The mean of each point's samples.
    pub mean: Vec<f64>,
}

/// A drive's history, as columns.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct HistoryReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// The range asked for, after the defaults (RFC 3339, UTC).
    pub since: String,
    /// The end of that range.
    pub until: String,
    /// Minutes kept (`[history] minutes`).
    pub minutes: u64,
    /// Seconds kept at full rate (`[history] full_rate_s`).
    pub full_rate_s: u64,
    /// Each point's time, Unix ms, oldest first (a bucket's start).
    pub t_ms: Vec<i64>,
    /// What each point covers, ms: 0 for one sample at the poll rate,
    /// 1000 for a one-second bucket, more for points merged to keep within
    /// `max_points`.
    pub span_ms: Vec<i64>,
    /// Status reads in each point.
    pub samples: Vec<u32>,
    /// Every STATUS flag seen in each point (OR of the raw STATUS words:
    /// bit 5 stalled, bits 2..0 a fault code when one point holds one).
    pub flags_any: Vec<u16>,
    /// The fields asked for, by name.
    pub fields: BTreeMap<String, HistoryColumn>,
}

fn time_param(name: &str, text: &str) -> Result<i64, Problem> {
    parse_time(text).map(unix_ms).ok_or_else(|| {
        Problem::invalid(format!(
            "{name} = {text:?} is not a time: give RFC 3339 (2026-11-25T01:00:00Z) or Unix milliseconds"
        ))
    })
}

fn fields_param(text: Option<&str>) -> Result<Vec<StatusField>, Problem> {
    let Some(text) = text else {
        return Ok(KEPT.to_vec());
    };
    let mut out = Vec::new();
    for name in text.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        let kept = StatusField::from_name(name).filter(|f| KEPT.contains(f));
        let field = kept.ok_or_else(|| {
            let known: Vec<&str> = KEPT.iter().map(|f| f.name()).collect();
            Problem::invalid(format!(
                "no field {name:?} in the history: the fields are {}",
                known.join(", ")
            ))
        })?;
        if !out.contains(&field) {
            out.push(field);
        }
    }
    if out.is_empty() {
        return Err(Problem::invalid(
            "fields is empty: name at least one, or leave it out for all",
        ));
    }
    Ok(out)
}

/// A drive's status over the last `[history] minutes` (default 60): the
/// most recent `[history] full_rate_s` seconds as polled, older ones in
/// one-second buckets with each field's minimum, maximum and mean.
#[utoipa::path(
    get,
    path = "/api/v1/drives/{drive}/history",
    tag = "drives",
    security(("bearer" = ["viewer"])),
    params(
        ("drive" = String, Path, description = "Drive name, or its unit number on a single bus"),
        HistoryQuery,
    ),
    responses(
        (status = 200, description = "The history as columns, oldest first (empty arrays when nothing was kept yet)", body = HistoryReply),
        (status = 422, description = "`out-of-range`: `max_points` outside 1 to 100000", body = super::problem_response::ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_history(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(key): PathParams<String>,
    Params(mut query): Params<HistoryQuery>,
) -> Result<Json<HistoryReply>, Problem> {
    let target = state.target(&key)?;
    // An empty parameter (`?since=`, as a form sends it) is one not given.
    let given = |p: &Option<String>| p.clone().filter(|t| !t.is_empty());
    (query.fields, query.since, query.until) = (
        given(&query.fields),
        given(&query.since),
        given(&query.until),
    );
    let fields = fields_param(query.fields.as_deref())?;
    let now = unix_ms(SystemTime::now());
    let settings = state.history.settings();
    let window_ms = i64::try_from(settings.minutes * 60_000).unwrap_or(i64::MAX);
    let since = match &query.since {
        Some(t) => time_param("since", t)?,
        None => now - window_ms,
    };
    let until = match &query.until {
        Some(t) => time_param("until", t)?,
        None => now,
    };
    if until < since {
        return Err(Problem::invalid(format!(
            "until ({}) is before since ({})",
            rfc3339(crate::control::journal::format::from_unix_ms(
                until.max(0) as u64
            )),
            rfc3339(crate::control::journal::format::from_unix_ms(
                since.max(0) as u64
            ))
        )));
    }
    let max_points = match query.max_points {
        None => DEFAULT_MAX_POINTS,
        Some(n) if (1..=MAX_POINTS).contains(&n) => n,
        Some(n) => {
            return Err(Problem::range(&crate::drive::RangeError {
                quantity: "max_points",
                value: n as f64,
                min: 1.0,
                max: MAX_POINTS as f64,
                unit: "",
            }));
        }
    };
    let bus = target.bus.name().to_string();
    let points = state
        .history
        .query(&bus, target.drive.unit, since, until, max_points);
    let at = |ms: i64| {
        rfc3339(crate::control::journal::format::from_unix_ms(
            ms.max(0) as u64
        ))
    };
    Ok(Json(HistoryReply {
        drive: target.drive.name.clone(),
        bus,
        unit: target.drive.unit,
        since: at(since),
        until: at(until),
        minutes: settings.minutes,
        full_rate_s: settings.full_rate_s,
        t_ms: points.iter().map(|p| p.t_ms).collect(),
        span_ms: points.iter().map(|p| p.span_ms).collect(),
        samples: points.iter().map(|p| p.n).collect(),
        flags_any: points.iter().map(|p| p.flags_any).collect(),
        fields: fields
            .iter()
            .map(|f| (f.name().to_string(), column(*f, &points)))
            .collect(),
    }))
}

/// `field`'s columns (a field the history keeps: one value per point).
fn column(field: StatusField, points: &[Point]) -> HistoryColumn {
    HistoryColumn {
        min: points.iter().filter_map(|p| p.min_of(field)).collect(),
        max: points.iter().filter_map(|p| p.max_of(field)).collect(),
        mean: points.iter().filter_map(|p| p.mean_of(field)).collect(),
    }
}
