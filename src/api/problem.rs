//! The API's side of the problem documents ([`crate::ops::problem`]): the
//! HTTP response (content type, `Retry-After`, `WWW-Authenticate`,
//! `Connection: close`) and axum's rejections as problems.

use axum::extract::rejection::{JsonRejection, PathRejection, QueryRejection};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

pub use crate::ops::problem::*;

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
