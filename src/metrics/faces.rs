//! Counters of the network faces: HTTP requests, WebSocket clients, Modbus
//! TCP connections and requests.

use std::time::Duration;

use prometheus::{
    HistogramOpts, HistogramVec, IntCounter, IntCounterVec, IntGauge, Opts, Registry,
};

/// Function codes the drives use (read holding registers, write single,
/// write multiple): their Modbus TCP series are exported from start-up.
const TCP_FUNCTIONS: [u8; 3] = [0x03, 0x06, 0x10];

/// The faces' metrics.
#[derive(Clone)]
pub struct FaceMetrics {
    http_requests: IntCounterVec,
    http_duration: HistogramVec,
    ws_clients: IntGauge,
    tcp_open: IntGauge,
    tcp_accepted: IntCounter,
    tcp_rejected: IntCounterVec,
    tcp_requests: IntCounterVec,
    tcp_malformed: IntCounter,
}

fn counter_vec(registry: &Registry, name: &str, help: &str, labels: &[&str]) -> IntCounterVec {
    let c = IntCounterVec::new(Opts::new(name, help), labels)
        .unwrap_or_else(|e| unreachable_metric(name, &e));
    let _ = registry.register(Box::new(c.clone()));
    c
}

fn gauge(registry: &Registry, name: &str, help: &str) -> IntGauge {
    let g = IntGauge::new(name, help).unwrap_or_else(|e| unreachable_metric(name, &e));
    let _ = registry.register(Box::new(g.clone()));
    g
}

fn counter(registry: &Registry, name: &str, help: &str) -> IntCounter {
    let c = IntCounter::new(name, help).unwrap_or_else(|e| unreachable_metric(name, &e));
    let _ = registry.register(Box::new(c.clone()));
    c
}

/// Metric definitions are constants of this file; a bad one is a bug caught
/// by the tests, never a runtime condition.
fn unreachable_metric(name: &str, e: &prometheus::Error) -> ! {
    panic!("invalid metric definition {name}: {e}")
}

impl FaceMetrics {
    /// Creates the metrics and registers them in `registry`.
    pub fn register(registry: &Registry) -> Self {
        let metrics = Self::new(registry);
        // The reasons a Modbus TCP connection is refused, at 0 from start-up.
        for reason in ["not_allowed", "limit"] {
            metrics.tcp_rejected.with_label_values(&[reason]);
        }
        metrics
    }

    fn new(registry: &Registry) -> Self {
        let http_duration = HistogramVec::new(
            HistogramOpts::new(
                "drivegate_http_request_duration_seconds",
                "Time to answer HTTP requests, by route.",
            )
            .buckets(vec![
                0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5,
            ]),
            &["route"],
        )
        .unwrap_or_else(|e| unreachable_metric("drivegate_http_request_duration_seconds", &e));
        let _ = registry.register(Box::new(http_duration.clone()));
        Self {
            http_requests: counter_vec(
                registry,
                "drivegate_http_requests_total",
                "HTTP requests answered, by route template, method and status code.",
                &["route", "method", "status"],
            ),
            http_duration,
            ws_clients: gauge(
                registry,
                "drivegate_websocket_clients",
                "WebSocket clients connected now.",
            ),
            tcp_open: gauge(
                registry,
                "drivegate_modbus_tcp_connections",
                "Modbus TCP connections open now.",
            ),
            tcp_accepted: counter(
                registry,
                "drivegate_modbus_tcp_connections_accepted_total",
                "Modbus TCP connections accepted.",
            ),
            tcp_rejected: counter_vec(
                registry,
                "drivegate_modbus_tcp_connections_rejected_total",
                "Modbus TCP and Modbus/TCP Security connections refused, by reason (not_allowed; per_address, heaviest, limit, files: see drivegate_connections_refused_total).",
                &["reason"],
            ),
            tcp_requests: counter_vec(
                registry,
                "drivegate_modbus_tcp_requests_total",
                "Modbus TCP requests answered, by function code and outcome.",
                &["function", "outcome"],
            ),
            tcp_malformed: counter(
                registry,
                "drivegate_modbus_tcp_malformed_frames_total",
                "Malformed Modbus TCP frames (the connection was closed).",
            ),
        }
    }

    /// Creates the Modbus TCP request series of the drives' function codes
    /// with each of `outcomes` at 0, so rate() sees the first request and
    /// a dashboard panel shows 0 rather than "No data" before any client
    /// came. The face names its outcomes (`crate::daemon::supervisor` passes them at
    /// start-up): the metrics sit below the faces and import none.
    pub fn tcp_outcomes<'a>(&self, outcomes: impl IntoIterator<Item = &'a str>) {
        for outcome in outcomes {
            for function in TCP_FUNCTIONS {
                self.tcp_requests
                    .with_label_values(&[&format!("0x{function:02x}"), outcome]);
            }
        }
    }

    /// Creates the Modbus TCP refusal series of each of `reasons` at 0
    /// (the face names them, as its outcomes).
    pub fn tcp_rejections<'a>(&self, reasons: impl IntoIterator<Item = &'a str>) {
        for reason in reasons {
            self.tcp_rejected.with_label_values(&[reason]);
        }
    }

    /// Creates the HTTP series of `routes` (template, method) answered
    /// 200, at 0: the routes a monitoring system asks (`/metrics`,
    /// `/healthz`, `/readyz`), so the families are there from the first
    /// scrape. Other routes appear with their first request (their
    /// statuses cannot be known before).
    pub fn http_routes<'a>(&self, routes: impl IntoIterator<Item = (&'a str, &'a str)>) {
        for (route, method) in routes {
            self.http_requests
                .with_label_values(&[route, method, "200"]);
            self.http_duration.with_label_values(&[route]);
        }
    }

    /// Counts one HTTP request; `route` is the route template (`/api/v1/drives/{drive}`),
    /// never the raw path, so the label set stays bounded.
    pub fn http_request(&self, route: &str, method: &str, status: u16, elapsed: Duration) {
        self.http_requests
            .with_label_values(&[route, method, &status.to_string()])
            .inc();
        self.http_duration
            .with_label_values(&[route])
            .observe(elapsed.as_secs_f64());
    }

    /// Counts a WebSocket client for as long as the guard lives.
    pub fn ws_client(&self) -> WsClientGuard {
        self.ws_clients.inc();
        WsClientGuard(self.ws_clients.clone())
    }

    /// A Modbus TCP connection was accepted; the returned guard counts it open.
    pub fn tcp_connection(&self) -> WsClientGuard {
        self.tcp_accepted.inc();
        self.tcp_open.inc();
        WsClientGuard(self.tcp_open.clone())
    }

    /// A Modbus TCP connection was refused (`not_allowed`, `per_address`,
    /// `limit`).
    pub fn tcp_rejected(&self, reason: &str) {
        self.tcp_rejected.with_label_values(&[reason]).inc();
    }

    /// A Modbus TCP request was answered with `outcome`: `ok`, `exception`
    /// (the drive's), `gateway_timeout` (0x0B), `path_unavailable` (0x0A),
    /// `busy` (0x06), `read_only`, `cached` (from the polled copy),
    /// `broadcast`, `invalid` (malformed request shape), `refused`,
    /// `not_decoded` (a function code the control core cannot decode) or
    /// `cancelled` (its client left before it reached the wire).
    pub fn tcp_request(&self, function: u8, outcome: &str) {
        self.tcp_requests
            .with_label_values(&[&format!("0x{function:02x}"), outcome])
            .inc();
    }

    /// A malformed Modbus TCP frame closed its connection.
    pub fn tcp_malformed(&self) {
        self.tcp_malformed.inc();
    }
}

/// Decrements a gauge when dropped (a client or connection went away).
pub struct WsClientGuard(IntGauge);

impl Drop for WsClientGuard {
    fn drop(&mut self) {
        self.0.dec();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_guards() {
        let registry = Registry::new();
        let m = FaceMetrics::register(&registry);
        m.http_request("/api/v1/drives", "GET", 200, Duration::from_millis(2));
        {
            let _a = m.ws_client();
            let _b = m.ws_client();
            assert_eq!(m.ws_clients.get(), 2);
        }
        assert_eq!(m.ws_clients.get(), 0);
        // Exported at 0 before the first request, once the face named its
        // outcomes.
        m.tcp_outcomes(["ok", "exception", "refused"]);
        let zero = registry
            .gather()
            .into_iter()
            .find(|f| f.name() == "drivegate_modbus_tcp_requests_total")
            .unwrap();
        assert_eq!(zero.get_metric().len(), 3 * 3);
        assert!(
            zero.get_metric()
                .iter()
                .all(|m| m.get_counter().get_value() == 0.0)
        );
        m.tcp_request(3, "ok");
        let names: Vec<String> = registry
            .gather()
            .iter()
            .map(|f| f.name().to_string())
            .collect();
        for name in [
            "drivegate_http_requests_total",
            "drivegate_http_request_duration_seconds",
            "drivegate_websocket_clients",
            "drivegate_modbus_tcp_requests_total",
            "drivegate_modbus_tcp_connections",
        ] {
            assert!(
                names.iter().any(|n| n == name),
                "{name} missing from {names:?}"
            );
        }
    }
}
