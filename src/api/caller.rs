//! Who a request comes from: the token it presents checked against the
//! configured ones ([`super::auth`]), an address that guesses paused
//! ([`super::throttle`]), and the request turned into a [`Caller`]: who
//! (for the audit log) and with which [`Role`], the core's answer
//! ([`crate::control::identity`]). Without tokens every local
//! client is admin (the API then listens on loopback only).
//!
//! Whether that role may do what is not a write (a scan, a capture, a
//! reload) is the core's policy too: [`authorize`] asks it.

use std::sync::Arc;
use std::time::Instant;

use axum::extract::{ConnectInfo, FromRequestParts};
use axum::http::request::Parts;

use super::auth::presented;
use super::listener::ClientAddr;
use super::problem_response::{Kind, Problem};
use super::state::ApiState;
use super::throttle::Failure;
use crate::control::identity::{self, Credential};
use crate::control::{Caller, Face, Operation, Role, Rule};
use crate::faces_shared::writes::forbidden;

/// Identifies the caller of a request. `websocket` also accepts the token
/// as a subprotocol or as `?access_token=` (browsers cannot set headers on
/// WebSockets). Never logs the token, nor the URL that may hold it.
fn identify(parts: &Parts, state: &ApiState, websocket: bool) -> Result<Caller, Problem> {
    let peer = parts
        .extensions
        .get::<ConnectInfo<ClientAddr>>()
        .map(|c| c.0.0);
    if state.tokens.is_empty() {
        // Loopback only (see `listener::bind`): every local client is admin.
        let who: Arc<str> = peer.map_or_else(|| "local".into(), |a| a.to_string().into());
        let key = peer.map_or_else(|| "local".to_string(), |a| a.ip().to_string());
        let role = role_of(state, Credential::Loopback(&who), Role::Admin).map_err(|_| {
            Problem::new(
                Kind::Unauthorized,
                "send an API token in the header Authorization: Bearer <token>",
            )
        })?;
        return Ok(Caller::new(Face::Http, who, role, state.source_for(&key)));
    }
    let ip = peer.map(|a| a.ip());
    if let Some(ip) = ip
        && let Err(wait) = state.tokens.throttle().check(ip, None, Instant::now())
    {
        state.metrics.security().auth_throttled();
        let seconds = wait.as_secs().max(1);
        return Err(Problem::new(
            Kind::TooManyFailures,
            format!("too many invalid API tokens came from this address: retry in {seconds} s"),
        )
        .retry_after(seconds));
    }
    let Some(presented) = presented(parts, websocket) else {
        return Err(Problem::new(
            Kind::Unauthorized,
            if websocket {
                "send an API token in the header Authorization: Bearer <token>, or offer the WebSocket subprotocols \"drivegate\" and \"drivegate.bearer.<token>\""
            } else {
                "send an API token in the header Authorization: Bearer <token>"
            },
        ));
    };
    match state
        .tokens
        .check(&presented)
        .and_then(|(name, role)| Some((role_of(state, Credential::Token(&name), role).ok()?, name)))
    {
        Some((role, name)) => Ok(Caller::new(
            Face::Http,
            name.clone(),
            role,
            state.source_for(&name),
        )),
        None => {
            state.metrics.security().auth_failure();
            let client = peer.map_or_else(|| "unknown".to_string(), |a| a.to_string());
            match ip.map(|ip| state.tokens.throttle().failed(ip, None, Instant::now())) {
                Some(Failure::First) | None => tracing::warn!(
                    client,
                    "refused a request with an unknown API token (more from this address are counted, and logged if they pause it)"
                ),
                Some(Failure::Paused { failures, pause }) => tracing::warn!(
                    client,
                    failures,
                    "{failures} unknown API tokens from this address in a short time: it is refused (429) for {} s",
                    pause.as_secs()
                ),
                Some(Failure::Again) => {}
            }
            Err(Problem::new(
                Kind::Unauthorized,
                "the API token is not valid",
            ))
        }
    }
}

/// The role the core gives `credential` under the running configuration
/// ([`crate::control::identity`]); `resolved`, the role the tokens were
/// resolved with from the same file, only before the core has published a
/// configuration.
fn role_of(state: &ApiState, credential: Credential<'_>, resolved: Role) -> Result<Role, String> {
    match state.control.follow_config().borrow().as_deref() {
        Some(config) => identity::identify(config, Face::Http, credential).map(|i| i.role),
        None => Ok(resolved),
    }
}

impl FromRequestParts<ApiState> for Caller {
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, state: &ApiState) -> Result<Self, Problem> {
        identify(parts, state, false)
    }
}

/// A [`Caller`] that may also present its token as a subprotocol or as
/// `?access_token=`: only for the WebSocket routes, since browsers cannot
/// set their headers.
#[derive(Debug, Clone)]
pub struct StreamCaller(pub Caller);

impl FromRequestParts<ApiState> for StreamCaller {
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, state: &ApiState) -> Result<Self, Problem> {
        identify(parts, state, true).map(StreamCaller)
    }
}

/// Refuses `caller` (403) unless the core's policy lets its role do
/// `operation` (what is not a write: scans, scope captures, reloads).
pub fn authorize(state: &ApiState, caller: &Caller, operation: Operation) -> Result<(), Problem> {
    state
        .control
        .authorize(caller, operation)
        .map_err(|refusal| match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        })
}
