//! Browser-origin guards: the checks that keep a web page, open in a
//! browser anywhere on the plant network (or on the gateway's own desktop),
//! from driving the motors through the user's browser.
//!
//! Browsers apply no same-origin rule to WebSockets, and send a form POST
//! or a `fetch(..., {mode: "no-cors"})` without any CORS preflight: the
//! request arrives and is acted upon, only its answer is hidden from the
//! page. Two headers the page cannot forge tell such requests apart:
//!
//! - `Host`: a page that points its own DNS name at the gateway's address
//!   (DNS rebinding) becomes "same-origin" with it in the browser's eyes,
//!   but its requests still carry its own name. Only the names the daemon
//!   answers to pass: loopback names and addresses, the listen address,
//!   the address the connection arrived at, and `[http] allowed_hosts`.
//!   Anything else is answered `421` before any route runs.
//! - `Origin` (or, without it, `Sec-Fetch-Site: cross-site`): on every
//!   request that can change something (any method but GET, HEAD and
//!   OPTIONS) and on every WebSocket upgrade (the stream and the monitor's
//!   live feed), the page's origin must be the daemon's own or one of
//!   `[http] allowed_origins`; otherwise `403`. `Origin: null` (sandboxed
//!   frames, `file:` pages) is foreign.
//!
//! Clients that are not browsers send no `Origin` (curl, scripts, PLC
//! gateways, Prometheus) and are served as before; the console, served by
//! the daemon, is same-origin. See docs/security.md for the threat model.
//!
//! Under TLS every answer also carries `Strict-Transport-Security`, so a
//! browser that once reached the gateway over HTTPS never again sends it a
//! token in clear text. A WebSocket upgrade that offered the `drivegate`
//! subprotocol is answered with it (see [`super::auth`]).

use std::collections::BTreeSet;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::listener::ServedAt;
use super::problem_response::{Kind, Problem};
pub use crate::config::origins::{WebOrigin, parse_allowed_host, parse_allowed_origin, split_host};
use crate::metrics::Metrics;

/// The `Strict-Transport-Security` value under TLS: one year.
pub const HSTS: &str = "max-age=31536000";

/// Why a request was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// The `Host` is not one the daemon answers to.
    UnknownHost {
        /// The header as sent.
        host: String,
        /// Its host part, the value to add to `allowed_hosts`.
        name: String,
    },
    /// A browser page from another origin tried to change something.
    ForeignOrigin {
        /// The page's origin as sent.
        origin: String,
        /// The daemon's own origin for this request.
        own: String,
    },
    /// No `Origin`, but the browser says the request is cross-site.
    CrossSite {
        /// The daemon's own origin for this request.
        own: String,
    },
}

impl Refusal {
    /// Short label for metrics.
    pub fn reason(&self) -> &'static str {
        match self {
            Refusal::UnknownHost { .. } => "host",
            Refusal::ForeignOrigin { .. } => "origin",
            Refusal::CrossSite { .. } => "cross-site",
        }
    }

    /// The problem document.
    pub fn problem(&self) -> Problem {
        match self {
            Refusal::UnknownHost { host, name } => Problem::new(
                Kind::UnknownHost,
                format!(
                    "drivegate does not answer to the host \"{host}\": if clients reach the gateway by that name, add \"{name}\" to [http] allowed_hosts (names only pass if listed, so a web page cannot point its own name at this address)"
                ),
            ),
            Refusal::ForeignOrigin { origin, own } => Problem::new(
                Kind::ForeignOrigin,
                format!(
                    "a page from {origin} may not change anything here or open a stream: only the daemon's own origin ({own}) and [http] allowed_origins may; if that page is yours, add \"{origin}\" to [http] allowed_origins"
                ),
            ),
            Refusal::CrossSite { own } => Problem::new(
                Kind::ForeignOrigin,
                format!(
                    "the browser says this request comes from another site's page (Sec-Fetch-Site: cross-site): only the daemon's own origin ({own}) and [http] allowed_origins may change anything here"
                ),
            ),
        }
    }
}

/// The guard's configuration, fixed at start.
#[derive(Debug, Clone)]
pub struct BrowserGuard {
    hosts: BTreeSet<String>,
    origins: BTreeSet<WebOrigin>,
    listen: IpAddr,
    tls: bool,
}

impl BrowserGuard {
    /// Guards a listener on `listen` (under TLS if `tls`), also answering to
    /// `allowed_hosts` and taking changes from pages of `allowed_origins`
    /// (both as checked by [`parse_allowed_host`] and
    /// [`parse_allowed_origin`]; entries that do not parse are ignored).
    pub fn new(
        listen: IpAddr,
        tls: bool,
        allowed_hosts: &[String],
        allowed_origins: &[String],
    ) -> Self {
        BrowserGuard {
            hosts: allowed_hosts
                .iter()
                .filter_map(|h| parse_allowed_host(h).ok())
                .collect(),
            origins: allowed_origins
                .iter()
                .filter_map(|o| WebOrigin::parse(o))
                .collect(),
            listen,
            tls,
        }
    }

    /// True when the answers carry HSTS.
    pub fn tls(&self) -> bool {
        self.tls
    }

    fn host_allowed(&self, host: &str, local: Option<SocketAddr>) -> bool {
        if host == "localhost" || self.hosts.contains(host) {
            return true;
        }
        match host.parse::<IpAddr>() {
            Ok(ip) => {
                ip.is_loopback()
                    || ip == self.listen
                    || local.is_some_and(|l| l.ip() == ip)
                    || ip.to_canonical().is_loopback()
            }
            Err(_) => false,
        }
    }

    /// Checks a request's head; `local` is the address the connection
    /// arrived at.
    pub fn check(
        &self,
        method: &Method,
        headers: &HeaderMap,
        local: Option<SocketAddr>,
    ) -> Result<(), Refusal> {
        let scheme = if self.tls { "https" } else { "http" };
        // No Host at all: not a browser (every browser sends one).
        let own = match headers.get(header::HOST) {
            None => None,
            Some(value) => {
                let text = String::from_utf8_lossy(value.as_bytes()).into_owned();
                let Some((host, port)) = split_host(&text) else {
                    return Err(Refusal::UnknownHost {
                        name: text.clone(),
                        host: text,
                    });
                };
                if !self.host_allowed(&host, local) {
                    return Err(Refusal::UnknownHost {
                        host: text,
                        name: host,
                    });
                }
                // Browsers leave the port out of Host only when it is the
                // scheme's default.
                let port = port.unwrap_or(if self.tls { 443 } else { 80 });
                Some(WebOrigin::new(scheme, host, port))
            }
        };
        if !changes_something(method, headers) {
            return Ok(());
        }
        let own_text = own
            .as_ref()
            .map_or_else(|| format!("{scheme}://<this host>"), ToString::to_string);
        match headers.get(header::ORIGIN) {
            Some(value) => {
                let text = String::from_utf8_lossy(value.as_bytes()).into_owned();
                let ok = WebOrigin::parse(&text)
                    .is_some_and(|o| Some(&o) == own.as_ref() || self.origins.contains(&o));
                if ok {
                    Ok(())
                } else {
                    Err(Refusal::ForeignOrigin {
                        origin: text,
                        own: own_text,
                    })
                }
            }
            None => {
                let cross = headers
                    .get("sec-fetch-site")
                    .is_some_and(|v| v.as_bytes().eq_ignore_ascii_case(b"cross-site"));
                if cross {
                    Err(Refusal::CrossSite { own: own_text })
                } else {
                    Ok(())
                }
            }
        }
    }
}

/// Every method but the safe ones, and every WebSocket upgrade (a stream
/// takes commands).
fn changes_something(method: &Method, headers: &HeaderMap) -> bool {
    if !matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS) {
        return true;
    }
    headers.get_all(header::UPGRADE).iter().any(|v| {
        String::from_utf8_lossy(v.as_bytes())
            .to_ascii_lowercase()
            .contains("websocket")
    })
}

/// What the middleware needs: the rules and the counters.
#[derive(Clone)]
pub struct GuardState {
    /// The rules.
    pub guard: Arc<BrowserGuard>,
    /// Where refusals are counted.
    pub metrics: Arc<Metrics>,
}

/// The middleware: refuses before any route (and any body) is looked at.
pub async fn guard(State(state): State<GuardState>, request: Request, next: Next) -> Response {
    let local = request.extensions().get::<ServedAt>().map(|s| s.0);
    if let Err(refusal) = state
        .guard
        .check(request.method(), request.headers(), local)
    {
        state.metrics.security().guard_refused(refusal.reason());
        tracing::debug!(
            reason = refusal.reason(),
            "HTTP request refused: {refusal:?}"
        );
        let mut response = refusal.problem().into_response();
        add_hsts(&state.guard, &mut response);
        return response;
    }
    let offers_subprotocol = super::auth::offers_subprotocol(request.headers());
    let mut response = next.run(request).await;
    add_hsts(&state.guard, &mut response);
    // Every WebSocket route of this face speaks the one subprotocol a
    // client may offer beside its token's (see `auth`): it is answered
    // here, once for all of them, and the token's never is.
    if offers_subprotocol
        && response.status() == axum::http::StatusCode::SWITCHING_PROTOCOLS
        && !response
            .headers()
            .contains_key(header::SEC_WEBSOCKET_PROTOCOL)
    {
        response.headers_mut().insert(
            header::SEC_WEBSOCKET_PROTOCOL,
            HeaderValue::from_static(super::auth::SUBPROTOCOL),
        );
    }
    response
}

fn add_hsts(guard: &BrowserGuard, response: &mut Response) {
    if guard.tls {
        response.headers_mut().insert(
            header::STRICT_TRANSPORT_SECURITY,
            HeaderValue::from_static(HSTS),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guard(tls: bool) -> BrowserGuard {
        BrowserGuard::new(
            "0.0.0.0".parse().unwrap(),
            tls,
            &["gateway.plant.local".to_string(), "10.1.2.3".to_string()],
            &["https://hmi.plant.local:8443".to_string()],
        )
    }

    fn headers(pairs: &[(&str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.append(
                axum::http::HeaderName::from_bytes(k.as_bytes()).unwrap(),
                HeaderValue::from_str(v).unwrap(),
            );
        }
        h
    }

    const LOCAL: Option<SocketAddr> = Some(SocketAddr::new(
        IpAddr::V4(std::net::Ipv4Addr::new(192, 168, 7, 2)),
        8080,
    ));

    fn check(method: Method, pairs: &[(&str, &str)]) -> Result<(), Refusal> {
        guard(false).check(&method, &headers(pairs), LOCAL)
    }

    #[test]
    fn hosts_the_daemon_answers_to() {
        for host in [
            "localhost:8080",
            "LOCALHOST.",
            "127.0.0.1:8080",
            "127.9.9.9",
            "[::1]:8080",
            "192.168.7.2:8080",
            "gateway.plant.local",
            "Gateway.Plant.Local.:8080",
            "10.1.2.3:8080",
        ] {
            assert_eq!(check(Method::GET, &[("host", host)]), Ok(()), "{host}");
        }
        // No Host: not a browser.
        assert_eq!(check(Method::GET, &[]), Ok(()));
    }

    #[test]
    fn foreign_hosts_are_refused_naming_the_key() {
        for host in [
            "evil.example:8080",
            "10.9.9.9",
            "[::2]:80",
            "a b",
            "localhost.evil.example",
        ] {
            let e = check(Method::GET, &[("host", host)]).unwrap_err();
            assert_eq!(e.reason(), "host", "{host}");
            let p = e.problem();
            assert_eq!(p.kind(), Kind::UnknownHost);
            assert_eq!(p.status, 421);
            assert!(
                p.detail.contains(host) && p.detail.contains("allowed_hosts"),
                "{}",
                p.detail
            );
        }
    }

    #[test]
    fn changes_need_the_own_or_an_allowed_origin() {
        let own = [
            ("host", "127.0.0.1:8080"),
            ("origin", "http://127.0.0.1:8080"),
        ];
        assert_eq!(check(Method::POST, &own), Ok(()));
        let allowed = [
            ("host", "gateway.plant.local:8080"),
            ("origin", "https://HMI.plant.local:8443"),
        ];
        assert_eq!(check(Method::PUT, &allowed), Ok(()));
        for origin in [
            "http://evil.example",
            "null",
            "http://127.0.0.1:8081",
            "https://127.0.0.1:8080",
            "http://127.0.0.1:8080/path",
            "https://hmi.plant.local",
        ] {
            let e = check(
                Method::POST,
                &[("host", "127.0.0.1:8080"), ("origin", origin)],
            )
            .unwrap_err();
            assert_eq!(e.reason(), "origin", "{origin}");
            let p = e.problem();
            assert_eq!((p.kind(), p.status), (Kind::ForeignOrigin, 403));
            assert!(
                p.detail.contains(origin) && p.detail.contains("http://127.0.0.1:8080"),
                "{}",
                p.detail
            );
        }
    }

    #[test]
    fn reads_pass_whatever_their_origin() {
        let h = [
            ("host", "127.0.0.1:8080"),
            ("origin", "http://evil.example"),
        ];
        assert_eq!(check(Method::GET, &h), Ok(()));
        assert_eq!(check(Method::HEAD, &h), Ok(()));
    }

    #[test]
    fn websocket_upgrades_are_guarded_like_changes() {
        let foreign = [
            ("host", "127.0.0.1:8080"),
            ("origin", "http://evil.example"),
            ("upgrade", "WebSocket"),
        ];
        assert_eq!(check(Method::GET, &foreign).unwrap_err().reason(), "origin");
        let own = [
            ("host", "localhost:8080"),
            ("origin", "http://localhost:8080"),
            ("upgrade", "websocket"),
        ];
        assert_eq!(check(Method::GET, &own), Ok(()));
        // A script opening the stream sends no Origin.
        assert_eq!(
            check(
                Method::GET,
                &[("host", "127.0.0.1:8080"), ("upgrade", "websocket")]
            ),
            Ok(())
        );
    }

    #[test]
    fn no_origin_passes_unless_the_browser_says_cross_site() {
        assert_eq!(check(Method::POST, &[("host", "127.0.0.1:8080")]), Ok(()));
        assert_eq!(
            check(Method::POST, &[("sec-fetch-site", "same-origin")]),
            Ok(())
        );
        let e = check(
            Method::POST,
            &[("host", "127.0.0.1:8080"), ("sec-fetch-site", "cross-site")],
        )
        .unwrap_err();
        assert_eq!(e.reason(), "cross-site");
        assert_eq!(e.problem().status, 403);
    }

    #[test]
    fn the_own_origin_follows_tls() {
        let g = guard(true);
        let h = headers(&[
            ("host", "127.0.0.1:8443"),
            ("origin", "https://127.0.0.1:8443"),
        ]);
        assert_eq!(g.check(&Method::POST, &h, LOCAL), Ok(()));
        let h = headers(&[
            ("host", "127.0.0.1:8443"),
            ("origin", "http://127.0.0.1:8443"),
        ]);
        assert!(g.check(&Method::POST, &h, LOCAL).is_err());
        // Default ports are implied on both sides.
        let h = headers(&[
            ("host", "gateway.plant.local"),
            ("origin", "https://gateway.plant.local:443"),
        ]);
        assert_eq!(g.check(&Method::DELETE, &h, LOCAL), Ok(()));
    }

    #[test]
    fn configuration_entries_are_checked() {
        assert_eq!(
            parse_allowed_host("Gateway.Plant.Local").unwrap(),
            "gateway.plant.local"
        );
        assert_eq!(parse_allowed_host("[::1]").unwrap(), "::1");
        assert_eq!(parse_allowed_host("fe80::1").unwrap(), "fe80::1");
        assert!(
            parse_allowed_host("gateway:8080")
                .unwrap_err()
                .contains("has a port")
        );
        assert!(parse_allowed_host("http://x").is_err());
        assert_eq!(
            parse_allowed_origin("https://hmi.plant.local:443/").unwrap(),
            "https://hmi.plant.local"
        );
        assert!(
            parse_allowed_origin("null")
                .unwrap_err()
                .contains("not an origin")
        );
        assert!(parse_allowed_origin("hmi.plant.local").is_err());
        assert!(parse_allowed_origin("ftp://x").is_err());
    }
}
