//! `POST /api/v1/drives/{drive}/replacement`: a guided client (the
//! console's replace-a-drive page) tells the audit log that it started,
//! finished or abandoned the replacement of a drive, so the procedure's
//! own writes (address, settings, calibration) sit between a start and
//! an end line. The core checks the role and writes the line
//! ([`crate::control::replacement`]); nothing on the bus changes.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::extract::{JsonBody, PathParams};
use super::problem_response::WriteProblems;
use super::problem_response::{Kind, Problem};
use super::state::ApiState;
use crate::control::replacement::ReplacementEvent;
use crate::control::{Caller, Rule};
use crate::faces_shared::writes::forbidden;
use crate::timestamp::rfc3339;

/// The longest `detail`, in characters: a sentence, not a file.
pub const DETAIL_MAX: usize = 500;

/// Where the procedure is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ReplacementEventName {
    /// The procedure started.
    Started,
    /// Every step done: the new drive holds the settings.
    Finished,
    /// Left before its end.
    Abandoned,
}

impl From<ReplacementEventName> for ReplacementEvent {
    fn from(e: ReplacementEventName) -> Self {
        match e {
            ReplacementEventName::Started => ReplacementEvent::Started,
            ReplacementEventName::Finished => ReplacementEvent::Finished,
            ReplacementEventName::Abandoned => ReplacementEvent::Abandoned,
        }
    }
}

/// A note on a drive replacement.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReplacementNote {
    /// Started, finished or abandoned.
    pub event: ReplacementEventName,
    /// In words, up to 500 characters on one line: where the settings
    /// came from, what a step found, the time it took.
    #[serde(default)]
    pub detail: String,
}

/// The note as the audit log has it.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ReplacementNoted {
    /// Drive name.
    pub drive: String,
    /// Started, finished or abandoned.
    pub event: ReplacementEventName,
    /// Who (the token's name).
    pub who: String,
    /// The detail logged.
    pub detail: String,
    /// When (RFC 3339, UTC).
    pub at: String,
}

/// Notes the start, end or abandonment of a drive's replacement in the
/// audit log (admin). The procedure's writes are audited as they happen;
/// this ties them together.
#[utoipa::path(
    post,
    path = "/api/v1/drives/{drive}/replacement",
    tag = "drives",
    security(("bearer" = ["admin"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = ReplacementNote, example = json!({"event": "started", "detail": "settings from the declaration"})),
    responses(
        (status = 200, description = "Logged", body = ReplacementNoted),
        WriteProblems,
    )
)]
pub async fn post_replacement(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(note): JsonBody<ReplacementNote>,
) -> Result<Json<ReplacementNoted>, Problem> {
    record(&state, &caller, &key, note).map(Json)
}

/// Notes `note` on drive `key` for `caller` (the REST route and the
/// stream's `replacement` command).
pub fn record(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    note: ReplacementNote,
) -> Result<ReplacementNoted, Problem> {
    let target = state.target(key)?;
    let length = note.detail.chars().count();
    if length > DETAIL_MAX {
        return Err(Problem::invalid(format!(
            "detail is {length} characters long: at most {DETAIL_MAX}"
        )));
    }
    if note.detail.chars().any(char::is_control) {
        return Err(Problem::invalid(
            "detail has a control character (a line break, a tab): give it on one line",
        ));
    }
    state
        .control
        .note_replacement(caller, target.index, note.event.into(), &note.detail)
        .map_err(|refusal| match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        })?;
    Ok(ReplacementNoted {
        drive: target.drive.name.clone(),
        event: note.event,
        who: caller.who.to_string(),
        detail: note.detail,
        at: rfc3339(std::time::SystemTime::now()),
    })
}
