//! The API tokens, for an admin (the core's `Operation::Configure`: a
//! token is lines of the configuration file):
//!
//! - `GET /api/v1/tokens`: each token in force with its role, where it is
//!   defined (its line, and where its secret is) and when it was last
//!   used; what the first token changes, said before it is made;
//! - `POST /api/v1/tokens`: a new token, made as `drivegate token new`
//!   makes one (256 random bits, only its SHA-256 in the file), written
//!   into the file as `config_file::apply` writes any change (whole or
//!   not at all, previous versions kept, audited, reloaded); the token is
//!   in this answer only;
//! - `DELETE /api/v1/tokens/{name}`: its `[[http.token]]` removed the
//!   same way; refused from the next request on.

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::caller::authorize;
use super::config::ReloadReply;
use super::config_file::{FileProblems, apply, path_of, read};
use super::extract::{JsonBody, PathParams};
use super::new_token::{FIRST_TOKEN_NOTE, MAKE_AN_ADMIN, NewTokenError, generate};
use super::problem_response::{Kind, Problem};
use super::state::ApiState;
use crate::config::edit::{add_token, remove_token, sha256_hex, token_lines};
use crate::config::http::TokenSource;
use crate::config::{Config, file};
use crate::control::{Caller, Operation, Role};
use crate::timestamp::rfc3339;

/// One API token, as the configuration has it (never its secret).
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct TokenView {
    /// Its name: the `who` of the audit log.
    pub name: String,
    /// Its role.
    pub role: Role,
    /// Where its secret is: `sha256` (only its digest, in the file),
    /// `file` or `env`.
    pub source: String,
    /// Where it is defined, in words: `drivegate.toml:42`, and the file
    /// or variable that holds its secret.
    pub defined: String,
    /// When it was last presented to the API (RFC 3339), since the HTTP
    /// listener started; null: not since.
    pub last_used: Option<String>,
}

/// The tokens in force.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct TokensReply {
    /// Each token of the running configuration.
    pub tokens: Vec<TokenView>,
    /// The configuration file they are written in.
    pub file: Option<String>,
    /// Whether drivegate may write the file; a new token is otherwise
    /// answered with the file to put in place by hand.
    pub writable: bool,
    /// What making the first token changes (none is configured now: every
    /// client on this machine is admin without one), to say before it is
    /// made.
    pub first_token: Option<String>,
    /// What to know when no token has the admin role after the change.
    pub no_admin: Option<String>,
}

/// A token to make.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewTokenBody {
    /// Its name: 1 to 64 letters, digits, `-`, `_` or `.`, not the name
    /// of another token.
    pub name: String,
    /// Its role.
    pub role: Role,
}

/// A token made.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct NewTokenReply {
    /// Its name.
    pub name: String,
    /// Its role.
    pub role: Role,
    /// The token: shown this once, kept nowhere (the file has its
    /// SHA-256). Send it as `Authorization: Bearer <token>`.
    pub token: String,
    /// The `[[http.token]]` lines written.
    pub lines: String,
    /// True when it is the configuration's first token: from now on every
    /// client needs one, this machine's too.
    pub first: bool,
    /// The reload that followed; null when the file was not written.
    pub reload: Option<ReloadReply>,
    /// Why the file was not written (drivegate may not write it): put
    /// `file_text` in place by hand and reload; the token works from then.
    pub not_written: Option<String>,
    /// The new file, when drivegate could not write it.
    pub file_text: Option<String>,
}

/// A token revoked.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct RevokedReply {
    /// Its name.
    pub name: String,
    /// What else to know: a secret file or variable left in place, the
    /// API back on loopback when it was the last token.
    pub notes: Vec<String>,
    /// The reload that followed.
    pub reload: ReloadReply,
}

/// The running configuration.
fn running(state: &ApiState) -> Option<std::sync::Arc<Config>> {
    state.control.follow_config().borrow().clone()
}

/// Lists the API tokens in force (admin): name, role, where each is
/// defined and where its secret is, when it was last used; and what the
/// first token changes.
#[utoipa::path(
    get,
    path = "/api/v1/tokens",
    tag = "config",
    security(("bearer" = ["admin"])),
    responses(
        (status = 200, description = "The tokens", body = TokensReply),
        FileProblems,
    )
)]
pub async fn list_tokens(
    State(state): State<ApiState>,
    caller: Caller,
) -> Result<Json<TokensReply>, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    let path = state.control.config_file();
    let text = match &path {
        Some(p) => tokio::fs::read_to_string(p).await.unwrap_or_default(),
        None => String::new(),
    };
    let lines = token_lines(&text);
    let file_name = path.as_ref().map_or_else(
        || "the configuration".to_string(),
        |p| {
            p.file_name().map_or_else(
                || p.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            )
        },
    );
    let used = state.tokens.last_used();
    let configured = running(&state)
        .map(|c| c.http.tokens.clone())
        .unwrap_or_default();
    let tokens: Vec<TokenView> = configured
        .iter()
        .map(|t| {
            let at = lines
                .iter()
                .find(|(n, _)| *n == t.name)
                .map_or(file_name.clone(), |(_, l)| format!("{file_name}:{l}"));
            let (source, defined) = match &t.source {
                TokenSource::Sha256(_) => ("sha256", format!("{at} (its SHA-256)")),
                TokenSource::File(f) => ("file", format!("{at}, secret in {}", f.display())),
                TokenSource::Env(v) => ("env", format!("{at}, secret in ${v}")),
            };
            TokenView {
                name: t.name.clone(),
                role: t.role,
                source: source.to_string(),
                defined,
                last_used: used.get(&t.name).copied().map(rfc3339),
            }
        })
        .collect();
    let none = tokens.is_empty();
    let no_admin = !tokens.iter().any(|t| t.role == Role::Admin);
    Ok(Json(TokensReply {
        tokens,
        writable: path.as_deref().is_some_and(|p| file::may_write(p).is_ok()),
        file: path.map(|p| p.display().to_string()),
        first_token: none.then(|| FIRST_TOKEN_NOTE.replace('\n', " ")),
        no_admin: no_admin.then(|| MAKE_AN_ADMIN.replace('\n', " ").replace("  ", " ")),
    }))
}

/// Makes an API token (admin), as `drivegate token new` does, writes its
/// `[[http.token]]` (its SHA-256 only) into the configuration file and
/// reloads: the token works from the answer on. The token is in this
/// answer only. When drivegate may not write its file, nothing is
/// written and the answer holds the new file to put in place by hand.
#[utoipa::path(
    post,
    path = "/api/v1/tokens",
    tag = "config",
    security(("bearer" = ["admin"])),
    request_body = NewTokenBody,
    responses(
        (status = 200, description = "The token, shown once, and the reload", body = NewTokenReply),
        FileProblems,
    )
)]
pub async fn post_token(
    State(state): State<ApiState>,
    caller: Caller,
    JsonBody(body): JsonBody<NewTokenBody>,
) -> Result<Json<NewTokenReply>, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    let path = path_of(&state)?;
    let made = generate(&body.name, body.role.name()).map_err(|e| match e {
        NewTokenError::Invalid(why) => Problem::invalid(format!("token name: {why}")),
        NewTokenError::Random(why) => Problem::new(Kind::Internal, why),
    })?;
    let on_disk = read(&path).await?;
    let digest = sha256_hex(&made.token);
    let text =
        add_token(&on_disk, &body.name, body.role.name(), &digest).map_err(Problem::invalid)?;
    let first = running(&state).is_some_and(|c| c.http.tokens.is_empty());
    let mut reply = NewTokenReply {
        name: body.name.clone(),
        role: body.role,
        token: made.token,
        lines: made.config,
        first,
        reload: None,
        not_written: None,
        file_text: None,
    };
    if let Err(e) = file::may_write(&path) {
        reply.not_written = Some(format!(
            "drivegate may not write {} ({e}): nothing was written. Put the new file in place by hand (sudoedit {}; or add the lines) and reload (systemctl reload drivegate): the token works from then",
            path.display(),
            path.display()
        ));
        reply.file_text = Some(text);
        return Ok(Json(reply));
    }
    let what = format!("API token \"{}\" made ({})", body.name, body.role.name());
    let applied = apply(&state, &caller, &path, &on_disk, text, &what).await?;
    reply.reload = Some(applied.reload);
    Ok(Json(reply))
}

/// Revokes an API token (admin): its `[[http.token]]` is removed from the
/// configuration file, which is reloaded; the token is refused from then
/// on. A token whose secret is in a file or a variable leaves them in
/// place (the answer says so).
#[utoipa::path(
    delete,
    path = "/api/v1/tokens/{name}",
    tag = "config",
    security(("bearer" = ["admin"])),
    params(("name" = String, Path, description = "The token's name")),
    responses(
        (status = 200, description = "Revoked, and the reload", body = RevokedReply),
        (status = 404, description = "`unknown-token`: no token of that name in the file", body = super::problem_response::ProblemDetails, content_type = "application/problem+json"),
        FileProblems,
    )
)]
pub async fn delete_token(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<RevokedReply>, Problem> {
    authorize(&state, &caller, Operation::Configure)?;
    let path = path_of(&state)?;
    let on_disk = read(&path).await?;
    let text =
        remove_token(&on_disk, &name).map_err(|why| Problem::new(Kind::UnknownToken, why))?;
    let mut notes = Vec::new();
    let configured = running(&state)
        .map(|c| c.http.tokens.clone())
        .unwrap_or_default();
    match configured.iter().find(|t| t.name == name).map(|t| &t.source) {
        Some(TokenSource::File(f)) => notes.push(format!(
            "its secret stays in {}: delete the file if nothing else reads it",
            f.display()
        )),
        Some(TokenSource::Env(v)) => notes.push(format!(
            "its secret stays in the environment variable {v} of the service until it is removed from the unit"
        )),
        _ => {}
    }
    if configured.len() == 1 && configured[0].name == name {
        notes.push(
            "it was the last token: the API now listens on loopback only, and every client on this machine is admin without a token".to_string(),
        );
    }
    if *caller.who == *name {
        notes.push("it was the token of this request: the next one needs another".to_string());
    }
    let what = format!("API token \"{name}\" revoked");
    let applied = apply(&state, &caller, &path, &on_disk, text, &what).await?;
    Ok(Json(RevokedReply {
        name,
        notes,
        reload: applied.reload,
    }))
}
