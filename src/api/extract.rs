//! Request extractors that answer malformed input with a problem document
//! (instead of axum's plain-text rejections), so every error a client sees
//! has the same shape.
//!
//! A body must arrive within `[http] read_timeout_s` of its head: a client
//! trickling one byte at a time would otherwise hold its handler and its
//! connection for ever (the idle timeout sees the bytes move).

use std::future::Future;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, FromRequestParts, Path, Query, Request};
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

use super::problem_response::{Kind, Problem};
use super::state::ApiState;

/// Runs a body read with the configured deadline.
async fn within_deadline<T>(
    state: &ApiState,
    read: impl Future<Output = Result<T, Problem>>,
) -> Result<T, Problem> {
    let limit = state.config.read_timeout;
    tokio::time::timeout(limit, read).await.unwrap_or_else(|_| {
        Err(Problem::new(
            Kind::RequestTimeout,
            format!(
                "the request body did not arrive within {} s ([http] read_timeout_s): send it whole, at once",
                limit.as_secs()
            ),
        ))
    })
}

/// A JSON body; wrong JSON, wrong types, unknown fields and anything but
/// an object are 400, a body over the limit 413, another content type 415,
/// one too slow 408.
#[derive(Debug, Clone)]
pub struct JsonBody<T>(pub T);

impl<T> FromRequest<ApiState> for JsonBody<T>
where
    T: DeserializeOwned,
{
    type Rejection = Problem;

    async fn from_request(req: Request, state: &ApiState) -> Result<Self, Problem> {
        if !says_json(req.headers()) {
            return Err(not_json());
        }
        let bytes = read_body(req, state).await?;
        object_or_null(&bytes, false)?;
        Json::<T>::from_bytes(&bytes)
            .map(|Json(v)| JsonBody(v))
            .map_err(Problem::from)
    }
}

/// A JSON body that may be left out entirely, or sent as `null` (then
/// `None`); one that is there must be an object and say it is JSON, as for
/// [`JsonBody`].
#[derive(Debug, Clone)]
pub struct OptionalJsonBody<T>(pub Option<T>);

impl<T> FromRequest<ApiState> for OptionalJsonBody<T>
where
    T: DeserializeOwned,
{
    type Rejection = Problem;

    async fn from_request(req: Request, state: &ApiState) -> Result<Self, Problem> {
        let json = says_json(req.headers());
        // Refused before it is read, as for JsonBody, when it announces
        // a length.
        let announced = req
            .headers()
            .get(axum::http::header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok())
            .is_some_and(|n| n > 0);
        if announced && !json {
            return Err(not_json());
        }
        let bytes = read_body(req, state).await?;
        if bytes.iter().all(u8::is_ascii_whitespace) {
            return Ok(OptionalJsonBody(None));
        }
        if !json {
            return Err(not_json());
        }
        object_or_null(&bytes, true)?;
        // `null` is as good as no body (the document allows either).
        Json::<Option<T>>::from_bytes(&bytes)
            .map(|Json(v)| OptionalJsonBody(v))
            .map_err(Problem::from)
    }
}

/// Reads the whole body, within the size limit and the deadline. A body
/// whose announced length is over the limit is refused at once, rather
/// than after waiting for bytes that would be thrown away.
async fn read_body(req: Request, state: &ApiState) -> Result<Bytes, Problem> {
    let limit = state.config.max_body_bytes;
    let announced = req
        .headers()
        .get(axum::http::header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if announced.is_some_and(|n| n > limit as u64) {
        return Err(Problem::new(
            Kind::PayloadTooLarge,
            format!("the body is over the limit of {limit} bytes ([http] max_body_bytes)"),
        ));
    }
    within_deadline(state, async {
        Bytes::from_request(req, state).await.map_err(|e| {
            if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
                Problem::new(Kind::PayloadTooLarge, e.body_text())
            } else {
                Problem::invalid(e.body_text())
            }
        })
    })
    .await
}

fn not_json() -> Problem {
    Problem::new(
        Kind::UnsupportedMediaType,
        "send the body as JSON with the header Content-Type: application/json",
    )
}

/// Refuses a body that is not a JSON object (or `null`, where allowed):
/// serde would otherwise read a struct from an array, field by field in
/// declaration order, so `[100]` would be a speed setpoint.
fn object_or_null(bytes: &[u8], null: bool) -> Result<(), Problem> {
    let text = bytes.trim_ascii_start();
    if text.starts_with(b"{") || (null && text.starts_with(b"null")) {
        return Ok(());
    }
    Err(Problem::invalid(if null {
        "the body must be a JSON object ({...}) or null"
    } else {
        "the body must be a JSON object ({...})"
    }))
}

/// True when the request says its body is JSON (`application/json` or
/// `application/*+json`), as axum's `Json` wants.
fn says_json(headers: &axum::http::HeaderMap) -> bool {
    let Some(value) = headers
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
    else {
        return false;
    };
    let essence = value
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    match essence.split_once('/') {
        Some(("application", subtype)) => subtype == "json" || subtype.ends_with("+json"),
        _ => false,
    }
}

/// Query parameters; bad ones are 400.
#[derive(Debug, Clone)]
pub struct Params<T>(pub T);

impl<S, T> FromRequestParts<S> for Params<T>
where
    S: Send + Sync,
    T: DeserializeOwned,
{
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Problem> {
        Query::<T>::from_request_parts(parts, state)
            .await
            .map(|Query(v)| Params(v))
            .map_err(Problem::from)
    }
}

/// Path parameters; undecodable ones are 400.
#[derive(Debug, Clone)]
pub struct PathParams<T>(pub T);

impl<S, T> FromRequestParts<S> for PathParams<T>
where
    S: Send + Sync,
    T: DeserializeOwned + Send,
{
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Problem> {
        Path::<T>::from_request_parts(parts, state)
            .await
            .map(|Path(v)| PathParams(v))
            .map_err(Problem::from)
    }
}
