//! The configuration file itself, for an admin to read, check and change
//! from the console or any client (the core's `Operation::Configure`):
//!
//! - `GET /api/v1/config/file`: the running file with its comments, its
//!   `ETag` (the SHA-256 of its text), whether drivegate may write it and
//!   the previous versions kept;
//! - `POST /api/v1/config/check`: a text checked as `check-config` checks
//!   it, each finding at its line and column, its lines against the file
//!   and what applying it would change in the plant's terms; nothing is
//!   written;
//! - `PUT /api/v1/config/file` with `If-Match`: the text written whole or
//!   not at all (`config::file`: the previous versions kept) and reloaded;
//!   a file changed since the version `If-Match` names is refused, naming
//!   the change that was made meanwhile and by whom.
//!
//! The core checks the role and audits each change with its lines
//! (`Control::reload`); this module only reads, compares and renders.

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoResponses, ToSchema};

use super::caller::authorize;
use super::config::{ReloadReply, render};
use super::config_check::{Remark, remarks};
use super::extract::JsonBody;
use super::problem_response::{Kind, Problem, ProblemDetails};
use super::state::ApiState;
use crate::config::edit::sha256_hex;
use crate::config::text_diff::{self, Hunk};
use crate::config::{Config, file};
use crate::control::config_edits::between;
use crate::control::reload::NewText;
use crate::control::{Caller, Operation};
use crate::timestamp::rfc3339;

/// A previous version of the file, kept beside it.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct GenerationView {
    /// Its path.
    pub path: String,
    /// When it was the file (RFC 3339).
    pub modified: Option<String>,
}

/// The last change written through drivegate.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct EditView {
    /// Who: the face and the token's name (`http commissioning`).
    pub by: String,
    /// When (RFC 3339).
    pub at: String,
    /// What, in words.
    pub what: String,
    /// Its lines, in a few words.
    pub lines: String,
}

/// The configuration file as it is on disk.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct ConfigFileReply {
    /// Its path.
    pub file: String,
    /// Its text, comments and all.
    pub text: String,
    /// SHA-256 (hex) of the text, also the `ETag`: send it back as
    /// `If-Match` with a change.
    pub sha256: String,
    /// False when the file on disk is not what runs (edited since the last
    /// reload, or refused by it): applying it, or a change of it, reloads it.
    pub running: bool,
    /// Whether drivegate may write the file.
    pub writable: bool,
    /// Why it may not, in words (a change is then offered as a download).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub not_writable: Option<String>,
    /// The previous versions kept beside it, newest first.
    pub generations: Vec<GenerationView>,
    /// The last change written through drivegate since it started.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_change: Option<EditView>,
}

/// A configuration text.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TextBody {
    /// The whole file.
    pub text: String,
}

/// What the checks found in a text.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct CheckReply {
    /// True when it passes `check-config`'s checks.
    pub valid: bool,
    /// Why it does not, each at its line and column (the parser stops at
    /// the first; line 0: the file as a whole).
    pub problems: Vec<Remark>,
    /// What is valid but probably a mistake.
    pub warnings: Vec<Remark>,
    /// What applying it would change, in the plant's terms (as a reload
    /// answers); empty when it does not pass.
    pub changes: Vec<String>,
    /// Its lines against the file on disk.
    pub diff: Vec<Hunk>,
    /// SHA-256 (hex) of the file on disk it was compared with.
    pub sha256: String,
}

/// What an apply did.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct ApplyReply {
    /// The configuration file.
    pub file: String,
    /// SHA-256 (hex) of the file now, also the `ETag`.
    pub sha256: String,
    /// The lines written, against the file before.
    pub diff: Vec<Hunk>,
    /// What the reload that followed applied.
    pub reload: ReloadReply,
}

/// Errors of the file's routes.
#[derive(IntoResponses)]
pub enum FileProblems {
    /// `invalid-request`: malformed JSON.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: only an admin may read or change the file.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `no-config-file`: drivegate was started without `--config`;
    /// `config-read-only`: drivegate may not write the file (nothing was
    /// written: save the text and put it in place by hand);
    /// `config-changed`: the file changed on disk during the apply.
    #[response(status = 409, content_type = "application/problem+json")]
    Conflict(ProblemDetails),
    /// `config-edited`: the file changed since the version `If-Match`
    /// names; the detail names the change, who made it and when.
    #[response(status = 412, content_type = "application/problem+json")]
    Edited(ProblemDetails),
    /// `unsupported-media-type`: send `Content-Type: application/json`.
    #[response(status = 415, content_type = "application/problem+json")]
    NotJson(ProblemDetails),
    /// `config-invalid`: the text does not pass `check-config` (the
    /// detail says where: `file:line:column`); nothing was written.
    #[response(status = 422, content_type = "application/problem+json")]
    Invalid(ProblemDetails),
    /// `if-match-required`: send the `ETag` of the version the change was
    /// made on as `If-Match`.
    #[response(status = 428, content_type = "application/problem+json")]
    IfMatch(ProblemDetails),
}

/// The file drivegate runs from, or `no-config-file`.
pub(super) fn path_of(state: &ApiState) -> Result<std::path::PathBuf, Problem> {
    state.control.config_file().ok_or_else(|| {
        Problem::new(
            Kind::NoConfigFile,
            "no configuration file: drivegate was started without --config",
        )
    })
}

/// The file's text now.
pub(super) async fn read(path: &std::path::Path) -> Result<String, Problem> {
    tokio::fs::read_to_string(path).await.map_err(|e| {
        Problem::new(
            Kind::Internal,
            format!("cannot read {}: {e}", path.display()),
        )
    })
}

/// `"<sha256>"`.
fn etag(sha256: &str) -> HeaderValue {
    HeaderValue::from_str(&format!("\"{sha256}\"")).unwrap_or(HeaderValue::from_static("\"\""))
}

/// Reads the configuration file with its comments (admin): its text, its
/// `ETag`, whether it is what runs, whether drivegate may write it and the
/// previous versions kept.
#[utoipa::path(
    get,
    path = "/api/v1/config/file",
    tag = "config",
    security(("bearer" = ["admin"])),
    responses(
        (status = 200, description = "The file", body = ConfigFileReply,
         headers(("ETag" = String, description = "The SHA-256 of the text, quoted"))),
        FileProblems,
    )
)]
pub async fn get_file(State(state): State<ApiState>, caller: Caller) -> Result<Response, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    let path = path_of(&state)?;
    let text = read(&path).await?;
    let sha256 = sha256_hex(&text);
    let running_now = state.control.follow_config().borrow().clone();
    let running = match (Config::parse(&text, "file"), running_now) {
        (Ok(on_disk), Some(running)) => on_disk == *running,
        _ => false,
    };
    let not_writable = file::may_write(&path).err().map(|e| {
        format!(
            "drivegate may not write {} ({e}): a change is offered as a file to download, to put in place by hand (sudoedit {}) and reload (systemctl reload drivegate)",
            path.display(),
            path.display()
        )
    });
    let last_change = state.control.config_edits().pop().map(|e| EditView {
        by: e.by,
        at: rfc3339(e.at),
        what: e.what,
        lines: e.lines,
    });
    let reply = ConfigFileReply {
        file: path.display().to_string(),
        generations: file::generations(&path)
            .into_iter()
            .map(|g| GenerationView {
                path: g.path.display().to_string(),
                modified: g.modified.map(rfc3339),
            })
            .collect(),
        text,
        running,
        writable: not_writable.is_none(),
        not_writable,
        last_change,
        sha256: sha256.clone(),
    };
    let mut response = Json(reply).into_response();
    response.headers_mut().insert(header::ETAG, etag(&sha256));
    Ok(response)
}

/// Checks a configuration text as `drivegate check-config` would (admin),
/// without writing anything: each problem at its line and column, the
/// warnings, its lines against the file on disk and what applying it would
/// change in the plant's terms.
#[utoipa::path(
    post,
    path = "/api/v1/config/check",
    tag = "config",
    security(("bearer" = ["admin"])),
    request_body = TextBody,
    responses(
        (status = 200, description = "What the checks found (a text that does not pass is an answer too)", body = CheckReply),
        FileProblems,
    )
)]
pub async fn post_check(
    State(state): State<ApiState>,
    caller: Caller,
    JsonBody(body): JsonBody<TextBody>,
) -> Result<Json<CheckReply>, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    let path = path_of(&state)?;
    let on_disk = read(&path).await?;
    let origin = path.display().to_string();
    // Certificates and token files are read: off the runtime's threads.
    let text = body.text;
    let (checked, text) = tokio::task::spawn_blocking(move || (remarks(&text, &origin), text))
        .await
        .map_err(|e| Problem::new(Kind::Internal, e.to_string()))?;
    let running = state.control.follow_config().borrow().clone();
    let changes = match (&checked.config, running) {
        (Some(new), Some(running)) => crate::config::diff::diff(&running, new).lines(),
        _ => Vec::new(),
    };
    Ok(Json(CheckReply {
        valid: checked.config.is_some(),
        problems: checked.problems,
        warnings: checked.warnings,
        changes,
        diff: text_diff::diff(&on_disk, &text),
        sha256: sha256_hex(&on_disk),
    }))
}

/// Writes a new text into the configuration file and reloads it (admin).
/// Send the `ETag` of the version it was made on as `If-Match`: when the
/// file changed since, nothing is written and the answer names the change
/// made meanwhile. The file is replaced whole (a temporary file in its
/// directory, synced, renamed over it), its previous versions kept beside
/// it with its owner and mode; a text that does not pass `check-config`
/// changes nothing. Answers the lines written and what the reload
/// applied, in words.
#[utoipa::path(
    put,
    path = "/api/v1/config/file",
    tag = "config",
    security(("bearer" = ["admin"])),
    params(("If-Match" = String, Header, description = "The ETag of the file the text was made from")),
    request_body = TextBody,
    responses(
        (status = 200, description = "Written and reloaded", body = ApplyReply,
         headers(("ETag" = String, description = "The SHA-256 of the new text, quoted"))),
        FileProblems,
    )
)]
pub async fn put_file(
    State(state): State<ApiState>,
    caller: Caller,
    headers: HeaderMap,
    JsonBody(body): JsonBody<TextBody>,
) -> Result<Response, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    // A change made on no version is refused as such first, whatever the
    // daemon runs with.
    let base = if_match(&headers)?;
    let path = path_of(&state)?;
    let on_disk = read(&path).await?;
    if sha256_hex(&on_disk) != base {
        return Err(edited(&state, &path, &base, &on_disk));
    }
    let reply = apply(
        &state,
        &caller,
        &path,
        &on_disk,
        body.text,
        "configuration edited",
    )
    .await?;
    let sha256 = reply.sha256.clone();
    let mut response = Json(reply).into_response();
    response.headers_mut().insert(header::ETAG, etag(&sha256));
    Ok(response)
}

/// Writes `text` (made from `on_disk`, the file as read) into the file at
/// `path` for `caller` and reloads, through the core; `what` names the
/// change in the audit log. A file drivegate may not write is refused
/// before anything is tried.
pub async fn apply(
    state: &ApiState,
    caller: &Caller,
    path: &std::path::Path,
    on_disk: &str,
    text: String,
    what: &str,
) -> Result<ApplyReply, Problem> {
    if let Err(e) = file::may_write(path) {
        return Err(Problem::new(
            Kind::ConfigReadOnly,
            format!(
                "drivegate may not write {} ({e}); nothing was written: save the new text, put it in place by hand (sudoedit {}) and reload (systemctl reload drivegate)",
                path.display(),
                path.display()
            ),
        ));
    }
    let sha256 = sha256_hex(&text);
    let write = NewText::new(on_disk, text, what);
    let diff = write.hunks.clone();
    let result = state.control.reload(caller, Some(write)).await;
    if let Err(crate::control::reload::Refused::Changed(_)) = &result {
        let now = read(path).await?;
        return Err(edited(state, path, &sha256_hex(on_disk), &now));
    }
    let Json(reload) = render(caller, result)?;
    Ok(ApplyReply {
        file: path.display().to_string(),
        sha256,
        diff,
        reload,
    })
}

/// The version `If-Match` names (its quotes and a weak `W/` taken off).
fn if_match(headers: &HeaderMap) -> Result<String, Problem> {
    headers
        .get(header::IF_MATCH)
        .and_then(|v| v.to_str().ok())
        .map(|v| v.trim().trim_start_matches("W/").trim_matches('"').to_string())
        .filter(|v| !v.is_empty())
        .ok_or_else(|| {
            Problem::new(
                Kind::IfMatchRequired,
                "send the ETag GET /api/v1/config/file answered as If-Match: a change is made on a version of the file, and refused if the file changed since",
            )
        })
}

/// `2026-11-29 00:03:02 UTC`: a time a person reads in a sentence.
fn utc(at: std::time::SystemTime) -> String {
    let t = rfc3339(at);
    format!(
        "{} {} UTC",
        t.get(..10).unwrap_or(""),
        t.get(11..19).unwrap_or("")
    )
}

/// The refusal of a change made on the version `base` of a file that is
/// `now`: who changed it meanwhile and what, as far as drivegate knows.
fn edited(state: &ApiState, path: &std::path::Path, base: &str, now: &str) -> Problem {
    let edits = state.control.config_edits();
    let said = match between(&edits, base, &sha256_hex(now)) {
        Some(steps) if !steps.is_empty() => steps
            .iter()
            .map(|e| format!("{} at {}: {} ({})", e.by, utc(e.at), e.what, e.lines))
            .collect::<Vec<_>>()
            .join("; then "),
        _ => {
            let lines = file::version_with_sha(path, base)
                .map(|old| text_diff::summary(&text_diff::diff(&old, now)))
                .filter(|l| !l.is_empty())
                .map_or_else(String::new, |l| format!(": {l}"));
            format!("changed on disk, not through drivegate{lines}")
        }
    };
    Problem::new(
        Kind::ConfigEdited,
        format!(
            "{} changed since you read it, and nothing was written: {said}. Read the file again and make your change on it",
            path.display()
        ),
    )
}
