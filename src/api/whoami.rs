//! `GET /api/v1/whoami`: the name and role of the presented token, so a
//! client (the console) can show only the controls that role may use, and
//! whether this daemon needs a token at all. The daemon still checks the
//! role of every request.
//!
//! Asked without a token where tokens are configured, it answers 200 with
//! no name and no role, and `tokens_required`: a client learns that it must
//! ask its user for a token without provoking an error. A token that is not
//! valid is 401, as everywhere.

use axum::Json;
use axum::extract::State;
use axum::http::HeaderMap;
use axum::http::header::AUTHORIZATION;
use serde::Serialize;
use utoipa::ToSchema;

use super::problem_response::Problem;
use super::problem_response::ReadProblems;
use super::state::ApiState;
use crate::control::{Caller, Role};

/// Who a token is.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct WhoAmI {
    /// The token's name (the client's address when no tokens are
    /// configured): the `who` of the audit log. `null` when no token was
    /// sent.
    pub who: Option<String>,
    /// Its role; `null` when no token was sent.
    pub role: Option<Role>,
    /// True when this daemon needs a token (false: every local client is
    /// admin).
    pub tokens_required: bool,
    /// The lease a jog from the console asks for, ms (`[safety]
    /// jog_lease_ms`): the motor runs on this long after the last renewal.
    pub jog_lease_ms: u64,
}

/// The presented token's name and role, and whether a token is needed.
#[utoipa::path(
    get,
    path = "/api/v1/whoami",
    tag = "drives",
    security((), ("bearer" = ["viewer"])),
    responses(
        (status = 200, description = "The token's name and role (both null when no token was sent)", body = WhoAmI),
        ReadProblems,
    )
)]
pub async fn whoami(
    State(state): State<ApiState>,
    headers: HeaderMap,
    caller: Result<Caller, Problem>,
) -> Result<Json<WhoAmI>, Problem> {
    let tokens_required = !state.tokens.is_empty();
    let jog_lease_ms = u64::try_from(state.control.jog_lease().as_millis()).unwrap_or(u64::MAX);
    if tokens_required && !headers.contains_key(AUTHORIZATION) {
        return Ok(Json(WhoAmI {
            who: None,
            role: None,
            tokens_required,
            jog_lease_ms,
        }));
    }
    let caller = caller?;
    Ok(Json(WhoAmI {
        who: Some(caller.who.to_string()),
        role: Some(caller.role),
        tokens_required,
        jog_lease_ms,
    }))
}
