//! Counters of the transport's defences: requests the browser-origin
//! guards refused, failed and throttled token checks, TLS handshakes that
//! failed, certificate reloads, and the HTTP listener's connections (open,
//! refused by its limits, closed for a request head that did not come).

use prometheus::{IntCounter, IntCounterVec, IntGauge, Opts, Registry};

/// The faces that speak TLS, each with its series from start-up.
const TLS_FACES: [&str; 2] = ["http", "modbus_tcp"];

/// The security counters.
#[derive(Clone)]
pub struct SecurityMetrics {
    guard_refused: IntCounterVec,
    auth_failures: IntCounter,
    auth_throttled: IntCounter,
    tls_handshake_failures: IntCounterVec,
    tls_reloads: IntCounterVec,
    tls_refused_clients: IntCounterVec,
    http_open: IntGauge,
    http_refused: IntCounterVec,
    http_header_timeouts: IntCounter,
}

/// Why the HTTP listener refused a connection (the label of
/// `drivegate_http_connections_refused_total`).
const HTTP_REFUSALS: [&str; 4] = ["limit", "per_address", "heaviest", "files"];

fn counter_vec(registry: &Registry, name: &str, help: &str, labels: &[&str]) -> IntCounterVec {
    let c = IntCounterVec::new(Opts::new(name, help), labels)
        .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
    let _ = registry.register(Box::new(c.clone()));
    c
}

fn counter(registry: &Registry, name: &str, help: &str) -> IntCounter {
    let c = IntCounter::new(name, help)
        .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
    let _ = registry.register(Box::new(c.clone()));
    c
}

impl SecurityMetrics {
    /// Creates the counters and registers them in `registry`.
    pub fn register(registry: &Registry) -> Self {
        let metrics = Self {
            guard_refused: counter_vec(
                registry,
                "drivegate_http_guard_refused_total",
                "HTTP requests refused by the browser-origin guards, by reason (host, origin, cross-site).",
                &["reason"],
            ),
            auth_failures: counter(
                registry,
                "drivegate_http_auth_failures_total",
                "HTTP requests and stream upgrades with an unknown API token.",
            ),
            auth_throttled: counter(
                registry,
                "drivegate_http_auth_throttled_total",
                "HTTP requests answered 429 because their address sent too many unknown tokens.",
            ),
            tls_handshake_failures: counter_vec(
                registry,
                "drivegate_tls_handshake_failures_total",
                "TLS handshakes that failed, by face (http, modbus_tcp).",
                &["face"],
            ),
            tls_reloads: counter_vec(
                registry,
                "drivegate_tls_reloads_total",
                "Certificate reloads (SIGHUP), by face and result (ok, failed: the previous certificate stays).",
                &["face", "result"],
            ),
            tls_refused_clients: counter_vec(
                registry,
                "drivegate_modbus_tcp_tls_refused_total",
                "Modbus/TCP Security clients refused after the handshake, by reason (role).",
                &["reason"],
            ),
            http_open: {
                let g = IntGauge::new(
                    "drivegate_http_connections",
                    "HTTP connections open now (WebSocket and keep-alive included).",
                )
                .unwrap_or_else(|e| panic!("invalid metric definition: {e}"));
                let _ = registry.register(Box::new(g.clone()));
                g
            },
            http_refused: counter_vec(
                registry,
                "drivegate_http_connections_refused_total",
                "HTTP connections answered 503 and closed, by reason: limit ([http] max_connections \
                 reached), heaviest (near it, from the address holding the most), files (near the \
                 process's file limit, from the heaviest address) or per_address (the client's \
                 address held [http] max_connections_per_address).",
                &["reason"],
            ),
            http_header_timeouts: counter(
                registry,
                "drivegate_http_header_timeouts_total",
                "HTTP connections closed because a request head did not arrive whole within \
                 [http] header_timeout_ms (nothing sent, or sent too slowly); kept-alive \
                 connections closed unused are not counted.",
            ),
        };
        // Every known series at 0 from start-up, so rate() sees the first
        // event and a dashboard shows 0 rather than "No data".
        for reason in ["host", "origin", "cross-site"] {
            metrics.guard_refused.with_label_values(&[reason]);
        }
        for reason in HTTP_REFUSALS {
            metrics.http_refused.with_label_values(&[reason]);
        }
        for face in TLS_FACES {
            metrics.tls_handshake_failures.with_label_values(&[face]);
            for result in ["ok", "failed"] {
                metrics.tls_reloads.with_label_values(&[face, result]);
            }
        }
        metrics.tls_refused_clients.with_label_values(&["role"]);
        metrics
    }

    /// A request refused by a browser-origin guard.
    pub fn guard_refused(&self, reason: &str) {
        self.guard_refused.with_label_values(&[reason]).inc();
    }

    /// An unknown token.
    pub fn auth_failure(&self) {
        self.auth_failures.inc();
    }

    /// A request answered 429 for its address's failures.
    pub fn auth_throttled(&self) {
        self.auth_throttled.inc();
    }

    /// A failed TLS handshake on `face`.
    pub fn tls_handshake_failed(&self, face: &str) {
        self.tls_handshake_failures.with_label_values(&[face]).inc();
    }

    /// A certificate reload on `face`, `ok` or not.
    pub fn tls_reload(&self, face: &str, ok: bool) {
        let result = if ok { "ok" } else { "failed" };
        self.tls_reloads.with_label_values(&[face, result]).inc();
    }

    /// An HTTP connection opened: counted open until the guard drops.
    pub fn http_connection(&self) -> OpenConnection {
        self.http_open.inc();
        OpenConnection(self.http_open.clone())
    }

    /// An HTTP connection refused, for `reason` (`limit` or
    /// `per_address`).
    pub fn http_refused(&self, reason: &str) {
        self.http_refused.with_label_values(&[reason]).inc();
    }

    /// An HTTP connection closed for a request head not whole in time.
    pub fn http_header_timeout(&self) {
        self.http_header_timeouts.inc();
    }

    /// A Modbus/TCP Security client refused after its handshake.
    pub fn tls_client_refused(&self, reason: &str) {
        self.tls_refused_clients.with_label_values(&[reason]).inc();
    }
}

/// An open HTTP connection in `drivegate_http_connections`, until dropped.
pub struct OpenConnection(IntGauge);

impl Drop for OpenConnection {
    fn drop(&mut self) {
        self.0.dec();
    }
}
