//! `POST /api/v1/config/reload`: applies the changed configuration file
//! without a restart, as `systemctl reload drivegate` does; `POST
//! /api/v1/config/drives`: the console scan's "add to configuration",
//! drives written into the file (comments kept) and reloaded. The core
//! checks the role (admin) and audits; these routes render what it did.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoResponses, ToSchema};

use super::caller::authorize;
use super::extract::JsonBody;
use super::problem_response::ProblemDetails;
use super::problem_response::{Kind, Problem};
use super::state::ApiState;
use crate::config::Config;
use crate::config::edit::{NewDrive, add_drives, drive_tables, sha256_hex};
use crate::control::reload::{Applied, NewText, Refused};
use crate::control::{Caller, Operation, Rule, reload::ReloadResult};
use crate::faces_shared::writes::forbidden;

/// What a reload applied.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ReloadReply {
    /// What changed, one line each: drives added, removed and changed,
    /// buses added, removed and reopened (with why), tokens changed,
    /// sections applied, what applies only at the next start; `no change`
    /// when the file is the running one.
    pub changes: Vec<String>,
    /// Every drive whose motion the reload changed, and why: drives that
    /// were removed while moving (or whose bus moved to another port) and
    /// what stopped them, and drives that report another motion after
    /// their bus reopened than before it.
    pub stopped: Vec<String>,
    /// Drives whose polling paused while their bus reopened (its port,
    /// baud rate or transport changed), and for how long; a change applied
    /// in place pauses nothing.
    pub paused: Vec<String>,
    /// What could not be done: a bus whose port did not open stays out of
    /// the plant until the next reload.
    pub problems: Vec<String>,
}

impl From<Applied> for ReloadReply {
    fn from(a: Applied) -> Self {
        ReloadReply {
            changes: a.changes,
            stopped: a.stopped,
            paused: a.paused,
            problems: a.problems,
        }
    }
}

/// Errors of a reload.
#[derive(IntoResponses)]
pub enum ReloadProblems {
    /// `invalid-request`: malformed JSON, a unit out of range, no drives.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: only an admin may reload.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `config-changed`: the file changed on disk since it was read;
    /// `no-config-file`: drivegate was started without `--config`;
    /// `config-read-only`: drivegate may not write its file (nothing was
    /// written).
    #[response(status = 409, content_type = "application/problem+json")]
    Conflict(ProblemDetails),
    /// `config-invalid`: the file does not pass `drivegate check-config`
    /// (the detail says where: `file:line:column`); the running
    /// configuration stays.
    #[response(status = 422, content_type = "application/problem+json")]
    Invalid(ProblemDetails),
}

/// Reloads the configuration file (admin): drives and buses added or
/// removed, poll rates, tokens, Modbus TCP clients, safety and scope
/// settings. Drives that did not change keep running, with their leases
/// and streams; a removed drive that moves gets its lease's stop (or
/// `[safety] on_shutdown`). A file that does not pass the check changes
/// nothing. Answers what was applied, in words.
#[utoipa::path(
    post,
    path = "/api/v1/config/reload",
    tag = "config",
    security(("bearer" = ["admin"])),
    responses(
        (status = 200, description = "What the reload applied", body = ReloadReply),
        ReloadProblems,
    )
)]
pub async fn post_reload(
    State(state): State<ApiState>,
    caller: Caller,
) -> Result<Json<ReloadReply>, Problem> {
    render(&caller, state.control.reload(&caller, None).await)
}

/// The answer of a reload, or its refusal as a problem.
pub fn render(caller: &Caller, result: ReloadResult) -> Result<Json<ReloadReply>, Problem> {
    match result {
        Ok(applied) => Ok(Json(applied.into())),
        Err(Refused::Invalid(why)) => Err(Problem::new(
            Kind::ConfigInvalid,
            format!("the configuration was not reloaded, the running one stays: {why}"),
        )),
        Err(Refused::Changed(why)) => Err(Problem::new(Kind::ConfigChanged, why)),
        Err(Refused::NotWritten(why)) => Err(Problem::new(Kind::ConfigReadOnly, why)),
        Err(Refused::Unavailable(why)) => Err(Problem::new(Kind::NoConfigFile, why)),
        Err(Refused::Refused(refusal)) => Err(match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        }),
    }
}

/// A drive a scan found, to add.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DriveToAdd {
    /// Its unit address, 1 to 255.
    #[schema(minimum = 1, maximum = 255)]
    #[serde(deserialize_with = "crate::faces_shared::integers::integer")]
    pub unit: i64,
    /// Its name, unique over all buses: 1 to 64 letters, digits, `-`,
    /// `_` or `.`.
    pub name: String,
}

/// Drives to add to a bus of the configuration file.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AddDrivesBody {
    /// The bus (a `[[bus]]` of the file).
    pub bus: String,
    /// The drives, each as a `[[bus.drive]]` with its unit and name.
    pub drives: Vec<DriveToAdd>,
    /// Only show what would be written, and the file's SHA-256 to send
    /// back with the write.
    #[serde(default)]
    pub dry_run: bool,
    /// The SHA-256 (hex) a dry run answered: the write is refused if the
    /// file changed on disk since. Needed unless `dry_run`.
    #[serde(default)]
    pub base_sha256: Option<String>,
}

/// What adding drives wrote (or would write).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct AddDrivesReply {
    /// The configuration file.
    pub file: String,
    /// The `[[bus.drive]]` tables added to the bus, as TOML.
    pub tables: String,
    /// SHA-256 (hex) of the file as it was read: send it back as
    /// `base_sha256` to write.
    pub sha256: String,
    /// The reload that followed the write; null for a dry run.
    pub reload: Option<ReloadReply>,
}

/// Adds drives (a scan's finds) to a bus of the configuration file,
/// keeping its comments and layout, then reloads it (admin). With
/// `dry_run`, only answers the tables and the file's SHA-256. Refused when
/// the file changed on disk since the dry run, or when the result would
/// not pass `drivegate check-config` (nothing is written then).
#[utoipa::path(
    post,
    path = "/api/v1/config/drives",
    tag = "config",
    security(("bearer" = ["admin"])),
    request_body = AddDrivesBody,
    responses(
        (status = 200, description = "What was (or would be) written, and the reload", body = AddDrivesReply),
        ReloadProblems,
        (status = 415, description = "`unsupported-media-type`: send `Content-Type: application/json`", body = ProblemDetails, content_type = "application/problem+json"),
    )
)]
pub async fn post_drives(
    State(state): State<ApiState>,
    caller: Caller,
    JsonBody(body): JsonBody<AddDrivesBody>,
) -> Result<Json<AddDrivesReply>, Problem> {
    authorize(&state, &caller, Operation::Reload)?;
    let Some(path) = state.control.config_file() else {
        return Err(Problem::new(
            Kind::NoConfigFile,
            "no configuration file to write: drivegate was started without --config",
        ));
    };
    let file = path.display().to_string();
    let mut drives = Vec::with_capacity(body.drives.len());
    for d in &body.drives {
        let unit = crate::drive::RangeError::check_int("unit", d.unit, 1, 255, "")?;
        drives.push(NewDrive {
            unit: u8::try_from(unit).map_err(|_| Problem::invalid("unit out of range"))?,
            name: d.name.clone(),
        });
    }
    if drives.is_empty() {
        return Err(Problem::invalid("no drives to add: give at least one"));
    }
    let text = tokio::fs::read_to_string(&path)
        .await
        .map_err(|e| Problem::new(Kind::ConfigInvalid, format!("cannot read {file}: {e}")))?;
    let sha256 = sha256_hex(&text);
    let invalid = |why: String| {
        Problem::new(
            Kind::ConfigInvalid,
            format!("nothing was written, the configuration stays: {why}"),
        )
    };
    let new = add_drives(&text, &body.bus, &drives).map_err(invalid)?;
    Config::parse(&new, &file).map_err(|e| invalid(e.to_string()))?;
    let mut reply = AddDrivesReply {
        file,
        tables: drive_tables(&drives),
        sha256,
        reload: None,
    };
    if body.dry_run {
        return Ok(Json(reply));
    }
    let Some(base) = body.base_sha256 else {
        return Err(Problem::invalid(
            "base_sha256 is needed to write: send the sha256 a dry run answered",
        ));
    };
    let names: Vec<&str> = drives.iter().map(|d| d.name.as_str()).collect();
    let mut write = NewText::new(
        &text,
        new,
        format!("drives added to bus {}: {}", body.bus, names.join(", ")),
    );
    // The text was made from the file read now; the client's dry run read
    // the one it answered, which the reloader compares with the disk.
    write.base_sha256 = base;
    let Json(reloaded) = render(&caller, state.control.reload(&caller, Some(write)).await)?;
    reply.reload = Some(reloaded);
    Ok(Json(reply))
}
