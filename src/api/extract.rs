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

use super::problem::{Kind, Problem};
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

/// A JSON body; wrong JSON, wrong types and unknown fields are 400, a body
/// over the limit 413, another content type 415, one too slow 408.
#[derive(Debug, Clone)]
pub struct JsonBody<T>(pub T);

impl<T> FromRequest<ApiState> for JsonBody<T>
where
    T: DeserializeOwned,
{
    type Rejection = Problem;

    async fn from_request(req: Request, state: &ApiState) -> Result<Self, Problem> {
        within_deadline(state, async {
            Json::<T>::from_request(req, state)
                .await
                .map(|Json(v)| JsonBody(v))
                .map_err(Problem::from)
        })
        .await
    }
}

/// A JSON body that may be left out entirely, or sent as `null` (then `None`).
#[derive(Debug, Clone)]
pub struct OptionalJsonBody<T>(pub Option<T>);

impl<T> FromRequest<ApiState> for OptionalJsonBody<T>
where
    T: DeserializeOwned,
{
    type Rejection = Problem;

    async fn from_request(req: Request, state: &ApiState) -> Result<Self, Problem> {
        let bytes = within_deadline(state, async {
            Bytes::from_request(req, state).await.map_err(|e| {
                if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
                    Problem::new(Kind::PayloadTooLarge, e.body_text())
                } else {
                    Problem::invalid(e.body_text())
                }
            })
        })
        .await?;
        if bytes.iter().all(u8::is_ascii_whitespace) {
            return Ok(OptionalJsonBody(None));
        }
        // `null` is as good as no body (the document allows either).
        serde_json::from_slice::<Option<T>>(&bytes)
            .map(OptionalJsonBody)
            .map_err(|e| Problem::invalid(format!("the JSON body is not valid: {e}")))
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
