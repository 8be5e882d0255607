//! Liveness, readiness and metrics, for systemd, load balancers and
//! Prometheus. They need no token: they show no secret and change nothing,
//! and the tools that read them rarely carry credentials.

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

use super::state::ApiState;
use crate::bus::handle::PortState;

/// `/healthz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Health {
    /// Always `ok` while the process serves requests.
    pub status: String,
    /// drivegate's version.
    pub version: String,
}

/// 200 while the process runs.
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "health",
    responses((status = 200, description = "The process is alive", body = Health))
)]
pub async fn healthz() -> Json<Health> {
    Json(Health {
        status: "ok".to_string(),
        version: env!("CARGO_PKG_VERSION").to_string(),
    })
}

/// One bus in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct BusReadiness {
    /// Bus name.
    pub bus: String,
    /// The serial port is open.
    pub port_open: bool,
    /// Drives whose data is live (polled within their expected period):
    /// a drive stale, offline, never heard or on a bus that is down does
    /// not count.
    pub drives_online: usize,
    /// Drives configured.
    pub drives: usize,
}

/// `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Readiness {
    /// True when every bus port is open, every bus has drives configured and
    /// at least one drive answers.
    pub ready: bool,
    /// Why not, when not.
    pub reasons: Vec<String>,
    /// Each bus.
    pub buses: Vec<BusReadiness>,
    /// What is wrong with the safety journal, in words: none, unreadable
    /// at start-up (set aside), or not writable (leases then work in
    /// memory only). It does not make drivegate unready.
    pub safety_journal: Vec<String>,
    /// The configuration file's last reload. A refused one does not make
    /// drivegate unready: the configuration it runs stays.
    pub configuration: ConfigReadiness,
    /// The MQTT face's link to its broker, when `[mqtt]` is configured.
    /// It does not make drivegate unready: the drives work without it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mqtt: Option<MqttReadiness>,
    /// The OPC UA server, when `[opcua]` is configured. It does not make
    /// drivegate unready: the drives work without it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opcua: Option<OpcUaReadiness>,
    /// The faces whose task crashed since start-up (a panic, or an end
    /// nobody asked for): down and waiting to be started again, or
    /// serving again. Empty while none did. A face down does not make
    /// drivegate unready: the drives and the other faces work on.
    pub faces: Vec<FaceReadiness>,
    /// The Modbus TCP listener, when it runs: its connections and what it
    /// refused lately. It does not make drivegate unready.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub modbus_tcp: Option<super::listeners::ListenerReadiness>,
    /// The Modbus/TCP Security listener, when it runs, likewise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub modbus_tls: Option<super::listeners::ListenerReadiness>,
}

/// A face that crashed, in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct FaceReadiness {
    /// `http`, `modbus_tcp`, `modbus_tls`, `mqtt` or `opcua`.
    pub face: String,
    /// Its name in words ("MQTT face").
    pub name: String,
    /// Serving now; false while down, waiting to be started again.
    pub serving: bool,
    /// Why it is down, in words ("it panicked: ..."); absent while it
    /// serves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub down_why: Option<String>,
    /// Since when it is down (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub down_since: Option<String>,
    /// When it is started again (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub restart_at: Option<String>,
    /// Times it was started again after a crash.
    pub restarts: u64,
    /// The last crash, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_crash: Option<String>,
    /// When that was (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_crash_at: Option<String>,
}

/// The faces that crashed, as `/readyz` and the console show them.
pub fn faces_readiness(state: &ApiState) -> Vec<FaceReadiness> {
    let rfc = crate::timestamp::rfc3339;
    state
        .metrics
        .face_health()
        .states()
        .into_iter()
        .map(|s| FaceReadiness {
            face: s.face.key().to_string(),
            name: s.face.name().to_string(),
            serving: s.down.is_none(),
            down_why: s.down.as_ref().map(|d| d.why.clone()),
            down_since: s.down.as_ref().map(|d| rfc(d.since)),
            restart_at: s.down.as_ref().map(|d| rfc(d.restart_at)),
            restarts: s.restarts,
            last_crash_at: s.last_crash.as_ref().map(|(at, _)| rfc(*at)),
            last_crash: s.last_crash.map(|(_, why)| why),
        })
        .collect()
}

/// The OPC UA server in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct OpcUaReadiness {
    /// Where it listens (`opc.tcp://` on this address).
    pub listen: String,
    /// Serving: its certificate is there and the server runs (at the
    /// first start it makes its certificate first).
    pub serving: bool,
    /// Sessions open now.
    pub sessions: i64,
    /// Why it does not serve, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    /// When that happened (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error_at: Option<String>,
}

/// The OPC UA server as `/readyz` and the console show it.
pub fn opcua_readiness(state: &ApiState) -> Option<OpcUaReadiness> {
    let face = state.metrics.opcua().state();
    Some(OpcUaReadiness {
        listen: face.listen?,
        serving: face.serving,
        sessions: state.metrics.opcua().sessions(),
        last_error_at: face
            .problem
            .as_ref()
            .map(|(at, _)| crate::timestamp::rfc3339(*at)),
        last_error: face.problem.map(|(_, why)| why),
    })
}

/// The configuration in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct ConfigReadiness {
    /// False when the last reload was refused or applied only in part (the
    /// file on disk is not the one running).
    pub last_reload_ok: bool,
    /// Why the last reload was refused, with `file:line:column`; or what
    /// of it was not done (a bus's port that did not open, a listener that
    /// could not move and where it stays).
    pub last_reload_error: Option<String>,
    /// When the running configuration was loaded (start-up or the last
    /// reload), RFC 3339.
    pub loaded_at: Option<String>,
    /// Reloads applied since start-up, whole or in part.
    pub reloads: u64,
}

/// The MQTT link in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct MqttReadiness {
    /// The broker, as configured.
    pub broker: String,
    /// Connected to it.
    pub connected: bool,
    /// The Sparkplug primary host's `STATE` says online; absent without
    /// a primary host (or before its `STATE` was heard).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub primary_host_online: Option<bool>,
    /// The births are out: data flows to the hosts.
    pub publishing: bool,
    /// The last connection error, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    /// When it happened (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error_at: Option<String>,
}

/// The MQTT link as `/readyz` and the console show it.
pub fn mqtt_readiness(state: &ApiState) -> Option<MqttReadiness> {
    let link = state.metrics.mqtt().link();
    let broker = link.broker?;
    Some(MqttReadiness {
        broker,
        connected: link.connected,
        primary_host_online: link.host_online,
        publishing: link.born,
        last_error_at: link
            .last_error
            .as_ref()
            .map(|(at, _)| crate::timestamp::rfc3339(*at)),
        last_error: link.last_error.map(|(_, why)| why),
    })
}

/// The routes of this module a monitoring system asks, as the router
/// names them: their request series exist from start-up.
pub const MONITORED_ROUTES: [&str; 3] = ["/metrics", "/healthz", "/readyz"];

/// The reason `/readyz` gives when the configuration has no `[[bus]]` (the
/// package's configuration as shipped); the console says the same.
pub const NO_BUS: &str = "no bus configured: run `drivegate probe --port /dev/serial/by-id/...` \
     (your adapter's stable name: `ls -l /dev/serial/by-id/`) to find the drives and their \
     baud rate, then add a [[bus]] \
     with its [[bus.drive]] sections to the configuration and reload it \
     (`systemctl reload drivegate`)";

/// The readiness of the plant.
pub fn readiness(state: &ApiState) -> Readiness {
    let mut reasons = Vec::new();
    let mut buses = Vec::new();
    let mut online_total = 0;
    let mut configured_total = 0;
    let plant = state.plant.now();
    if plant.bus_count() == 0 {
        reasons.push(NO_BUS.to_string());
    }
    for bus in plant.buses() {
        let name = bus.handle.name().to_string();
        let port_open = matches!(bus.handle.port_state(), PortState::Up { .. });
        match bus.handle.port_state() {
            PortState::Up { .. } => {}
            PortState::Opening => reasons.push(format!("bus {name}: the port is not open yet")),
            PortState::Down { reason, .. } => {
                reasons.push(format!("bus {name}: the port is down ({reason})"));
            }
        }
        let units: Vec<u8> = bus.config.drives.iter().map(|d| d.unit()).collect();
        if units.is_empty() {
            reasons.push(format!(
                "bus {name} has no drives configured: scan it (the console's commissioning \
                 page, or POST /api/v1/buses/{name}/scan) and add its [[bus.drive]] sections"
            ));
        }
        configured_total += units.len();
        let online = bus
            .handle
            .freshness_all(std::time::Instant::now())
            .iter()
            .filter(|(unit, v)| units.contains(unit) && v.freshness.is_live())
            .count();
        online_total += online;
        buses.push(BusReadiness {
            bus: name,
            port_open,
            drives_online: online,
            drives: units.len(),
        });
    }
    if online_total == 0 && configured_total > 0 {
        reasons.push("no drive answers its status polls (no drive's data is live)".to_string());
    }
    Readiness {
        ready: reasons.is_empty(),
        reasons,
        buses,
        safety_journal: state.control.journal_warnings(),
        configuration: {
            let status = state.control.reload_status();
            ConfigReadiness {
                last_reload_ok: status.last_ok,
                last_reload_error: status.last_error,
                loaded_at: status.last_good_at.map(crate::timestamp::rfc3339),
                reloads: status.applied + status.partial,
            }
        },
        mqtt: mqtt_readiness(state),
        opcua: opcua_readiness(state),
        faces: faces_readiness(state),
        modbus_tcp: super::listeners::readiness(
            &state.metrics,
            crate::connections::words::MODBUS_TCP,
        ),
        modbus_tls: super::listeners::readiness(
            &state.metrics,
            crate::connections::words::MODBUS_TLS,
        ),
    }
}

/// 200 when every bus port is open and at least one drive answers, else 503
/// with the reasons.
#[utoipa::path(
    get,
    path = "/readyz",
    tag = "health",
    responses(
        (status = 200, description = "Ready", body = Readiness),
        (status = 503, description = "Not ready; `reasons` says why", body = Readiness),
    )
)]
pub async fn readyz(State(state): State<ApiState>) -> (StatusCode, Json<Readiness>) {
    let r = readiness(&state);
    let status = if r.ready {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    (status, Json(r))
}

/// Prometheus text exposition (version 0.0.4): drive values from the poll
/// cache, bus counters, and the faces' counters. A scrape never touches the bus.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "health",
    responses((status = 200, description = "Metrics", content_type = "text/plain; version=0.0.4", body = String))
)]
pub async fn metrics(State(state): State<ApiState>) -> Response {
    let mut response = state.metrics.render().into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(crate::metrics::CONTENT_TYPE),
    );
    response
}
