//! The API's side of the problem documents ([`crate::faces_shared::problem`]): the
//! HTTP response (content type, `Retry-After`, `WWW-Authenticate`,
//! `Connection: close`), axum's rejections as problems, and the lists of
//! problems a kind of route answers, as the OpenAPI document gives them.

use axum::extract::rejection::{JsonRejection, PathRejection, QueryRejection};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use utoipa::IntoResponses;

pub use crate::faces_shared::problem::*;

impl From<JsonRejection> for Problem {
    fn from(rejection: JsonRejection) -> Self {
        let kind = match rejection.status() {
            StatusCode::PAYLOAD_TOO_LARGE => Kind::PayloadTooLarge,
            StatusCode::UNSUPPORTED_MEDIA_TYPE => Kind::UnsupportedMediaType,
            _ => Kind::InvalidRequest,
        };
        let detail = match kind {
            Kind::UnsupportedMediaType => {
                "send the body as JSON with the header Content-Type: application/json".to_string()
            }
            _ => rejection.body_text(),
        };
        Problem::new(kind, detail)
    }
}

impl From<QueryRejection> for Problem {
    fn from(rejection: QueryRejection) -> Self {
        Problem::invalid(rejection.body_text())
    }
}

impl From<PathRejection> for Problem {
    fn from(rejection: PathRejection) -> Self {
        Problem::invalid(rejection.body_text())
    }
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let status = self.status_code();
        let kind = self.kind();
        let retry = self.retry_after_s;
        let body = serde_json::to_vec(self.details()).unwrap_or_else(|_| b"{}".to_vec());
        let mut response = (status, body).into_response();
        let headers = response.headers_mut();
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(CONTENT_TYPE));
        if let Some(seconds) = retry {
            headers.insert(header::RETRY_AFTER, HeaderValue::from(seconds));
        }
        if kind == Kind::Unauthorized {
            headers.insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"drivegate\""),
            );
        }
        if matches!(kind, Kind::PayloadTooLarge | Kind::RequestTimeout) {
            // The rest of the body is not read, so the connection cannot
            // carry another request: say so, or a client that reuses it
            // sees its next request fail with a broken pipe.
            headers.insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        response
    }
}

/// Errors of read routes.
#[derive(IntoResponses)]
pub enum ReadProblems {
    /// `invalid-request`: a malformed parameter.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `unknown-drive` or `unknown-bus`.
    #[response(status = 404, content_type = "application/problem+json")]
    NotFound(ProblemDetails),
}

/// Errors of reads that may go to the bus.
#[derive(IntoResponses)]
pub enum FreshReadProblems {
    /// `invalid-request`: a malformed parameter.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `unknown-drive`.
    #[response(status = 404, content_type = "application/problem+json")]
    NotFound(ProblemDetails),
    /// `bus-busy`: the bus queue is full; see `Retry-After`.
    #[response(status = 429, content_type = "application/problem+json")]
    BusBusy(ProblemDetails),
    /// `drive-refused`, `drive-unconfirmed`, `drive-bad-reply`.
    #[response(status = 502, content_type = "application/problem+json")]
    BadGateway(ProblemDetails),
    /// `drive-offline` (also: no status read yet), `bus-down`,
    /// `queue-timeout`, `shutting-down`.
    #[response(status = 503, content_type = "application/problem+json")]
    Unavailable(ProblemDetails),
    /// `drive-timeout`: the drive did not answer.
    #[response(status = 504, content_type = "application/problem+json")]
    Timeout(ProblemDetails),
}

/// Errors of writes.
#[derive(IntoResponses)]
pub enum WriteProblems {
    /// `invalid-request`: malformed JSON, wrong types, unknown or
    /// contradictory fields.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`: no token, or an unknown one.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: the token's role does not allow this.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `unknown-drive`, `unknown-bus`, `unknown-command`.
    #[response(status = 404, content_type = "application/problem+json")]
    NotFound(ProblemDetails),
    /// `drive-not-active`, `drive-moving` (save while turning: send
    /// `force`), `drive-busy` (calibrating), `confirmation-required`.
    #[response(status = 409, content_type = "application/problem+json")]
    Conflict(ProblemDetails),
    /// `request-timeout`: the body did not arrive within `[http]
    /// read_timeout_s`.
    #[response(status = 408, content_type = "application/problem+json")]
    TooSlow(ProblemDetails),
    /// `payload-too-large`.
    #[response(status = 413, content_type = "application/problem+json")]
    TooLarge(ProblemDetails),
    /// `unsupported-media-type`: send `Content-Type: application/json`.
    #[response(status = 415, content_type = "application/problem+json")]
    NotJson(ProblemDetails),
    /// `out-of-range`: `valid_range` gives the accepted range.
    #[response(status = 422, content_type = "application/problem+json")]
    OutOfRange(ProblemDetails),
    /// `bus-busy`: the bus queue is full; see `Retry-After`.
    #[response(status = 429, content_type = "application/problem+json")]
    BusBusy(ProblemDetails),
    /// `drive-refused` (a Modbus exception, `exception_code`),
    /// `drive-unconfirmed`, `drive-bad-reply`.
    #[response(status = 502, content_type = "application/problem+json")]
    BadGateway(ProblemDetails),
    /// `drive-offline`, `bus-down`, `queue-timeout`, `shutting-down`.
    #[response(status = 503, content_type = "application/problem+json")]
    Unavailable(ProblemDetails),
    /// `drive-timeout`: the drive did not answer; whether it carried the
    /// request out is unknown.
    #[response(status = 504, content_type = "application/problem+json")]
    Timeout(ProblemDetails),
}

/// Errors of lease routes.
#[derive(IntoResponses)]
pub enum LeaseProblems {
    /// `invalid-request`.
    #[response(status = 400, content_type = "application/problem+json")]
    BadRequest(ProblemDetails),
    /// `unauthorized`.
    #[response(status = 401, content_type = "application/problem+json")]
    Unauthorized(ProblemDetails),
    /// `forbidden`: needs the operator role.
    #[response(status = 403, content_type = "application/problem+json")]
    Forbidden(ProblemDetails),
    /// `unknown-drive`.
    #[response(status = 404, content_type = "application/problem+json")]
    NotFound(ProblemDetails),
    /// `no-lease`: none is in place; the detail says what became of the
    /// last one (expired or its WebSocket closed, and whether its stop was
    /// confirmed or is still being tried; released; ended by the brake or
    /// deactivation), or that none was granted.
    #[response(status = 409, content_type = "application/problem+json")]
    NoLease(ProblemDetails),
    /// `request-timeout`: the body did not arrive within `[http]
    /// read_timeout_s`.
    #[response(status = 408, content_type = "application/problem+json")]
    TooSlow(ProblemDetails),
    /// `out-of-range`: a lease length outside `[safety] lease_min_ms` to `lease_max_ms`.
    #[response(status = 422, content_type = "application/problem+json")]
    OutOfRange(ProblemDetails),
}

/// Errors of admin bus operations (same classes as writes).
pub type AdminBusProblems = WriteProblems;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_body_closes_its_connection_and_says_so() {
        for kind in [Kind::PayloadTooLarge, Kind::RequestTimeout] {
            let response = Problem::new(kind, "x").into_response();
            assert_eq!(
                response
                    .headers()
                    .get(header::CONNECTION)
                    .map(|v| v.as_bytes()),
                Some(&b"close"[..]),
                "{kind:?}"
            );
        }
        let response = Problem::new(Kind::UnknownDrive, "x").into_response();
        assert_eq!(response.headers().get(header::CONNECTION), None);
    }
}
