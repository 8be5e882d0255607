//! `GET /api/v1/whoami`: the name and role of the presented token, so a
//! client (the console) can show only the controls that role may use. The
//! daemon still checks the role of every request.

use axum::Json;
use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;

use super::auth::Caller;
use super::openapi::ReadProblems;
use super::problem::Problem;
use super::roles::Role;
use super::state::ApiState;

/// Who a token is.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct WhoAmI {
    /// The token's name (the client's address when no tokens are
    /// configured): the `who` of the audit log.
    pub who: String,
    /// Its role.
    pub role: Role,
    /// False when no tokens are configured: every local client is admin.
    pub tokens_required: bool,
}

/// The presented token's name and role.
#[utoipa::path(
    get,
    path = "/api/v1/whoami",
    tag = "drives",
    security(("bearer" = ["viewer"])),
    responses(
        (status = 200, description = "The token's name and role", body = WhoAmI),
        ReadProblems,
    )
)]
pub async fn whoami(
    State(state): State<ApiState>,
    caller: Caller,
) -> Result<Json<WhoAmI>, Problem> {
    Ok(Json(WhoAmI {
        who: caller.who.to_string(),
        role: caller.role,
        tokens_required: !state.tokens.is_empty(),
    }))
}
