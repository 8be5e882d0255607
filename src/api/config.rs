//! `POST /api/v1/config/reload`: applies the changed configuration file
//! without a restart, as `systemctl reload drivegate` does. The core
//! checks the role (admin) and audits; this route renders what it did.

use axum::Json;
use axum::extract::State;
use serde::Serialize;
use utoipa::{IntoResponses, ToSchema};

use super::auth::Caller;
use super::auth::forbidden;
use super::problem::ProblemDetails;
use super::problem::{Kind, Problem};
use super::state::ApiState;
use crate::control::reload::{Applied, Refused};
use crate::control::{Rule, reload::ReloadResult};

/// What a reload applied.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ReloadReply {
    /// What changed, one line each: drives added, removed and changed,
    /// buses added, removed and reopened (with why), tokens changed,
    /// sections applied, what applies only at the next start; `no change`
    /// when the file is the running one.
    pub changes: Vec<String>,
    /// Drives that were removed while moving, and what stopped them.
    pub stopped: Vec<String>,
    /// What could not be done: a bus whose port did not open stays out of
    /// the plant until the next reload.
    pub problems: Vec<String>,
}

impl From<Applied> for ReloadReply {
    fn from(a: Applied) -> Self {
        ReloadReply {
            changes: a.changes,
            stopped: a.stopped,
            problems: a.problems,
        }
    }
}

/// Errors of a reload.
#[derive(IntoResponses)]
pub enum ReloadProblems {
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: only an admin may reload.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `config-changed`: the file changed on disk since it was read;
    /// `no-config-file`: drivegate was started without `--config`.
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
        Err(Refused::Unavailable(why)) => Err(Problem::new(Kind::NoConfigFile, why)),
        Err(Refused::Refused(refusal)) => Err(match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        }),
    }
}
