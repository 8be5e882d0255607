//! The web console: a page served at `/` to watch, jog and commission the
//! drives from a browser, with no internet and no build step.
//!
//! Its files (`web/console/`, plain ES modules, and the vendored uPlot in
//! `web/vendor/`) are compiled into the binary with `include_bytes!`, so the
//! daemon needs nothing beside it and a plant network without internet
//! shows the same page. The page is a client of the public API like any
//! other (`/api/v1/...` and the stream, with the user's token): this module
//! only serves files, and decides nothing about the drives.
//!
//! Every answer carries a strict Content-Security-Policy (scripts and
//! styles from this daemon only, no inline script, connections only to it
//! and its WebSocket), an `ETag` (the file's SHA-256) with `Cache-Control:
//! no-cache` so a browser revalidates cheaply (304) and never runs a stale
//! page after an upgrade, and `X-Content-Type-Options: nosniff`.

use std::sync::OnceLock;

use axum::Router;
use axum::extract::Path;
use axum::http::header::{
    CACHE_CONTROL, CONTENT_SECURITY_POLICY, CONTENT_TYPE, ETAG, HOST, IF_NONE_MATCH,
    REFERRER_POLICY, X_CONTENT_TYPE_OPTIONS, X_FRAME_OPTIONS,
};
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use sha2::{Digest, Sha256};

/// Where the console's files are served (the page itself is at `/`).
pub const PREFIX: &str = "/console/";

/// One embedded file: its path under [`PREFIX`], content type and bytes.
pub struct Asset {
    /// Path under `/console/` (and under `web/` in the repository, less
    /// its first directory for the console's own files).
    pub path: &'static str,
    /// The `Content-Type` it is served with.
    pub content_type: &'static str,
    /// Its bytes.
    pub bytes: &'static [u8],
}

const HTML: &str = "text/html; charset=utf-8";
const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const TEXT: &str = "text/plain; charset=utf-8";
const SVG: &str = "image/svg+xml";

macro_rules! asset {
    ($path:literal, $file:literal, $type:expr) => {
        Asset {
            path: $path,
            content_type: $type,
            bytes: include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/web/", $file)),
        }
    };
}

/// Every file of the console. A test checks that every file under `web/`
/// is listed here, so none is forgotten.
pub const ASSETS: &[Asset] = &[
    asset!("index.html", "console/index.html", HTML),
    asset!("style.css", "console/style.css", CSS),
    asset!("icon.svg", "console/icon.svg", SVG),
    asset!("app.js", "console/app.js", JS),
    asset!("api.js", "console/api.js", JS),
    asset!("stream.js", "console/stream.js", JS),
    asset!("store.js", "console/store.js", JS),
    asset!("ui.js", "console/ui.js", JS),
    asset!("jog.js", "console/jog.js", JS),
    asset!("ramps.js", "console/ramps.js", JS),
    asset!("setpoint.js", "console/setpoint.js", JS),
    asset!("alarms.js", "console/alarms.js", JS),
    asset!("trends.js", "console/trends.js", JS),
    asset!("scan.js", "console/scan.js", JS),
    asset!("gateway.js", "console/gateway.js", JS),
    asset!("pages/overview.js", "console/pages/overview.js", JS),
    asset!("pages/drive.js", "console/pages/drive.js", JS),
    asset!("pages/settings.js", "console/pages/settings.js", JS),
    asset!(
        "pages/commissioning.js",
        "console/pages/commissioning.js",
        JS
    ),
    asset!("pages/replace.js", "console/pages/replace.js", JS),
    asset!("pages/events.js", "console/pages/events.js", JS),
    asset!("pages/alarms.js", "console/pages/alarms.js", JS),
    asset!("pages/scope.js", "console/pages/scope.js", JS),
    asset!("pages/monitor.js", "console/pages/monitor.js", JS),
    asset!("pages/config.js", "console/pages/config.js", JS),
    asset!("pages/tokens.js", "console/pages/tokens.js", JS),
    asset!("pages/certificates.js", "console/pages/certificates.js", JS),
    asset!(
        "vendor/uplot/uPlot.iife.min.js",
        "vendor/uplot/uPlot.iife.min.js",
        JS
    ),
    asset!(
        "vendor/uplot/uPlot.min.css",
        "vendor/uplot/uPlot.min.css",
        CSS
    ),
    asset!("vendor/uplot/LICENSE", "vendor/uplot/LICENSE", TEXT),
    asset!("vendor/uplot/MANIFEST", "vendor/uplot/MANIFEST", TEXT),
];

/// The ETag of each asset, in the order of [`ASSETS`], computed once.
fn etags() -> &'static [String] {
    static ETAGS: OnceLock<Vec<String>> = OnceLock::new();
    ETAGS.get_or_init(|| {
        ASSETS
            .iter()
            .map(|a| {
                let digest = Sha256::digest(a.bytes);
                let hex: String = digest[..12].iter().map(|b| format!("{b:02x}")).collect();
                format!("\"{hex}\"")
            })
            .collect()
    })
}

/// The page's Content-Security-Policy. `connect-src` names the WebSocket
/// of the host the page was loaded from as well as `'self'`, for browsers
/// whose `'self'` does not cover `ws:`.
pub fn content_security_policy(host: Option<&str>) -> String {
    let ws = host
        .filter(|h| valid_host(h))
        .map(|h| format!(" ws://{h} wss://{h}"))
        .unwrap_or_default();
    format!(
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
         connect-src 'self'{ws}; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )
}

/// A Host header that can go into a header value unchanged: a name or an
/// address, and a port.
fn valid_host(host: &str) -> bool {
    !host.is_empty()
        && host.len() <= 255
        && host
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-.:[]".contains(&b))
}

/// The routes: `/` (the page) and `/console/{*path}` (its files).
pub fn router<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/", get(|headers: HeaderMap| async move { serve("index.html", &headers) }))
        .route(
            "/console/{*path}",
            get(|Path(path): Path<String>, headers: HeaderMap| async move {
                serve(&path, &headers)
            }),
        )
}

/// The answer for the asset at `path`: the file, 304 when the browser's
/// copy is current, or `None` when there is no such file.
pub fn answer(path: &str, headers: &HeaderMap) -> Option<Response> {
    let index = ASSETS.iter().position(|a| a.path == path)?;
    let asset = &ASSETS[index];
    let etag = etags().get(index)?.as_str();
    let host = headers.get(HOST).and_then(|h| h.to_str().ok());
    let mut response = if matches_etag(headers, etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(CONTENT_TYPE, asset.content_type)], asset.bytes).into_response()
    };
    let h = response.headers_mut();
    h.insert(ETAG, HeaderValue::from_str(etag).ok()?);
    h.insert(CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    h.insert(
        CONTENT_SECURITY_POLICY,
        HeaderValue::from_str(&content_security_policy(host)).ok()?,
    );
    Some(response)
}

fn serve(path: &str, headers: &HeaderMap) -> Response {
    answer(path, headers).unwrap_or_else(|| {
        crate::api::problem_response::Problem::new(
            crate::api::problem_response::Kind::NotFound,
            format!("the console has no file {PREFIX}{path}; open the console at /"),
        )
        .into_response()
    })
}

fn matches_etag(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get(IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_are_unique_and_the_page_is_html() {
        let mut paths: Vec<&str> = ASSETS.iter().map(|a| a.path).collect();
        paths.sort_unstable();
        paths.dedup();
        assert_eq!(paths.len(), ASSETS.len());
        let headers = HeaderMap::new();
        let page = answer("index.html", &headers).unwrap();
        assert_eq!(page.headers()[CONTENT_TYPE], HTML);
        assert!(answer("nope.js", &headers).is_none());
        assert!(answer("../Cargo.toml", &headers).is_none());
    }

    #[test]
    fn a_current_copy_is_answered_304() {
        let first = answer("app.js", &HeaderMap::new()).unwrap();
        let etag = first.headers()[ETAG].clone();
        let mut headers = HeaderMap::new();
        headers.insert(IF_NONE_MATCH, etag);
        let again = answer("app.js", &headers).unwrap();
        assert_eq!(again.status(), StatusCode::NOT_MODIFIED);
        headers.insert(IF_NONE_MATCH, HeaderValue::from_static("\"stale\""));
        assert_eq!(answer("app.js", &headers).unwrap().status(), StatusCode::OK);
    }

    #[test]
    fn the_policy_names_only_this_host() {
        let csp = content_security_policy(Some("127.0.0.1:8080"));
        assert!(csp.contains("connect-src 'self' ws://127.0.0.1:8080 wss://127.0.0.1:8080;"));
        assert!(csp.contains("script-src 'self';") && !csp.contains("unsafe"));
        // A Host that could smuggle another directive is left out.
        let csp = content_security_policy(Some("evil; script-src *"));
        assert!(csp.contains("connect-src 'self';"), "{csp}");
    }
}
