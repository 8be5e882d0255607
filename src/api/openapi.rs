//! The OpenAPI 3.1 document, built from the same route table the server
//! runs (so they cannot drift), and the interactive page at `/docs`
//! (Swagger UI, its assets built into the binary: it works with no
//! internet). `openapi/openapi.json` is a checked-in copy that a test
//! compares with [`document`].

use utoipa::Number;
use utoipa::openapi::schema::Schema;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{LicenseBuilder, OpenApi as Document, RefOr};
use utoipa::{Modify, OpenApi};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::monitor_live::MonitorClientMessage;
use super::problem_response::{ProblemDetails, ValidRange};
use super::state::ApiState;
use super::stream_messages::{ClientMessage, DriveSelection};
use super::{
    alarms, buses, certificates, config, config_commands, config_file, document, drives, health,
    history, monitor, monitor_live, readback, replacement, scope, setpoints, settings, stream,
    tokens, whoami,
};
use crate::control::LeaseBounds;
use crate::control::Role;

/// Where the document is served.
pub const DOCUMENT_PATH: &str = "/openapi.json";
/// Where the interactive page is served.
pub const DOCS_PATH: &str = "/docs";

#[derive(OpenApi)]
#[openapi(
    info(
        title = "drivegate",
        description = "REST and WebSocket API of drivegate, the gateway to a bus of RS-485 (Modbus RTU) servo drives.\n\nEvery command returns only after the drive confirmed it. Errors are `application/problem+json` (RFC 9457); the `type` says what went wrong. Send the API token as `Authorization: Bearer <token>`; its role (viewer, operator, admin) decides what it may do. `/healthz`, `/readyz` and `/metrics` need no token."
    ),
    modifiers(&BearerScheme),
    components(schemas(
        ProblemDetails,
        ValidRange,
        Role,
        ClientMessage,
        DriveSelection,
        MonitorClientMessage
    )),
    tags(
        (name = "drives", description = "Drives and their decoded status"),
        (name = "commands", description = "Config commands and modes (manual 1.3)"),
        (name = "setpoints", description = "Speed, position and torque setpoints and their motor-safety leases (manual 1.4 to 1.6)"),
        (name = "settings", description = "Protection, ramps, inertia and RS-485 control (manual 1.8 to 1.12)"),
        (name = "buses", description = "Bus health and counters, scans, address setting (manual 1.2)"),
        (name = "stream", description = "The WebSocket stream of statuses and events, with commands"),
        (name = "monitor", description = "Every frame on the wire of a bus: decoded, with its outcome and who caused it; live, and as CSV or PCAP"),
        (name = "scope", description = "Triggered captures of status fields at the bus's full rate"),
        (name = "alarms", description = "Faults, stalls, drives offline, buses down, communication-loss stops, stops not confirmed and refused safety writes: kept across restarts until acknowledged"),
        (name = "config", description = "The configuration file: read, check and change it (admin), its API tokens, and reloads without a restart"),
        (name = "certificates", description = "The certificates the daemon serves and trusts (OPC UA, HTTPS, Modbus/TCP Security): trust a refused OPC UA client, remove a trusted one, renew the OPC UA server's own (admin)"),
        (name = "health", description = "Liveness, readiness and Prometheus metrics (no token needed)"),
    )
)]
struct ApiDoc;

/// Declares the bearer token scheme.
struct BearerScheme;

impl Modify for BearerScheme {
    fn modify(&self, openapi: &mut Document) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some(
                        "An API token from [[http.token]] in the configuration. Not needed when no tokens are configured (the API then listens on loopback only). The role an operation needs (viewer, operator or admin; each includes the ones before it) is the scope of its bearer requirement.",
                    ))
                    .build(),
            ),
        );
    }
}

/// Every documented route, ready for its state.
pub fn router() -> OpenApiRouter<ApiState> {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(health::healthz))
        .routes(routes!(health::readyz))
        .routes(routes!(health::metrics))
        .routes(routes!(drives::list_drives))
        .routes(routes!(drives::get_drive))
        .routes(routes!(drives::get_status))
        .routes(routes!(readback::get_settings, document::put_settings))
        .routes(routes!(document::get_declared))
        .routes(routes!(replacement::post_replacement))
        .routes(routes!(whoami::whoami))
        .routes(routes!(config_commands::post_command))
        .routes(routes!(config_commands::put_mode))
        .routes(routes!(setpoints::put_setpoint))
        .routes(routes!(setpoints::post_renew))
        .routes(routes!(setpoints::delete_lease))
        .routes(routes!(settings::put_protection))
        .routes(routes!(settings::put_speed_ramp))
        .routes(routes!(settings::put_position_ramp))
        .routes(routes!(settings::put_inertia))
        .routes(routes!(settings::put_rs485_control))
        .routes(routes!(buses::list_buses))
        .routes(routes!(buses::get_bus))
        .routes(routes!(buses::post_scan))
        .routes(routes!(buses::post_address))
        .routes(routes!(config::post_reload))
        .routes(routes!(config::post_drives))
        .routes(routes!(config_file::get_file, config_file::put_file))
        .routes(routes!(config_file::post_check))
        .routes(routes!(tokens::list_tokens, tokens::post_token))
        .routes(routes!(tokens::delete_token))
        .routes(routes!(certificates::list_certificates))
        .routes(routes!(certificates::post_trust))
        .routes(routes!(certificates::delete_trusted))
        .routes(routes!(certificates::post_renew))
        .routes(routes!(stream::stream))
        .routes(routes!(monitor::get_monitor))
        .routes(routes!(monitor::get_frames))
        .routes(routes!(monitor::get_frames_csv))
        .routes(routes!(monitor::get_frames_pcap))
        .routes(routes!(monitor_live::live))
        .routes(routes!(
            scope::get_scope,
            scope::post_scope,
            scope::delete_scope
        ))
        .routes(routes!(scope::post_trigger))
        .routes(routes!(scope::get_result))
        .routes(routes!(scope::get_result_csv))
        .routes(routes!(alarms::list_alarms))
        .routes(routes!(alarms::post_ack))
        .routes(routes!(history::get_history))
}

/// Sets what the derive cannot: the version and the licence.
pub fn finish(mut document: Document) -> Document {
    document.info.version = env!("CARGO_PKG_VERSION").to_string();
    document.info.license = Some(
        LicenseBuilder::new()
            .name("MIT OR Apache-2.0")
            .identifier(Some("MIT OR Apache-2.0"))
            .build(),
    );
    document
}

/// The OpenAPI document of the API, with the default configuration's
/// limits (the checked-in `openapi/openapi.json`).
pub fn document() -> Document {
    let (_, document) = router().split_for_parts();
    let safety = crate::config::SafetyConfig::default();
    let bounds = LeaseBounds {
        min: std::time::Duration::from_millis(safety.lease_min_ms),
        max: std::time::Duration::from_millis(safety.lease_max_ms),
    };
    document_for(document, bounds)
}

/// The document as a daemon whose core has `lease_bounds` serves it: the
/// lease lengths it accepts are its own (`[safety] lease_min_ms`,
/// `lease_max_ms`).
pub fn document_for(document: Document, lease_bounds: LeaseBounds) -> Document {
    let mut document = finish(document);
    let ms = |d: std::time::Duration| usize::try_from(d.as_millis()).unwrap_or(usize::MAX);
    let bounds = (ms(lease_bounds.min), ms(lease_bounds.max));
    if let Some(components) = document.components.as_mut() {
        for schema in components.schemas.values_mut() {
            set_lease_bounds(schema, bounds);
        }
    }
    document
}

/// Sets `minimum` and `maximum` of every `lease_ms` property in `schema`.
fn set_lease_bounds(schema: &mut RefOr<Schema>, (min, max): (usize, usize)) {
    let RefOr::T(schema) = schema else {
        return;
    };
    let items = match schema {
        Schema::Object(object) => {
            for (name, property) in object.properties.iter_mut() {
                if name == "lease_ms"
                    && let RefOr::T(Schema::Object(lease)) = property
                {
                    lease.minimum = Some(Number::UInt(min));
                    lease.maximum = Some(Number::UInt(max));
                }
                set_lease_bounds(property, (min, max));
            }
            return;
        }
        Schema::OneOf(one_of) => &mut one_of.items,
        Schema::AllOf(all_of) => &mut all_of.items,
        Schema::AnyOf(any_of) => &mut any_of.items,
        _ => return,
    };
    for item in items {
        set_lease_bounds(item, (min, max));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lease_lengths_are_the_configurations() {
        let lease_bounds = |bounds: LeaseBounds| {
            let (_, doc) = router().split_for_parts();
            let value = serde_json::to_value(document_for(doc, bounds)).unwrap();
            let schemas = &value["components"]["schemas"];
            [
                &schemas["SetpointBody"]["oneOf"][0]["properties"]["lease_ms"],
                &schemas["SetpointBody"]["oneOf"][3]["properties"]["lease_ms"],
                &schemas["RenewBody"]["properties"]["lease_ms"],
            ]
            .map(|p| (p["minimum"].as_u64(), p["maximum"].as_u64()))
        };
        let ms = std::time::Duration::from_millis;
        let defaults = LeaseBounds {
            min: ms(100),
            max: ms(60_000),
        };
        assert_eq!(lease_bounds(defaults), [(Some(100), Some(60_000)); 3]);
        let config = LeaseBounds {
            min: ms(20),
            max: ms(5_000),
        };
        assert_eq!(lease_bounds(config), [(Some(20), Some(5_000)); 3]);
        // The document the daemon is built with has the defaults.
        let value = serde_json::to_value(document()).unwrap();
        assert_eq!(
            value["components"]["schemas"]["RenewBody"]["properties"]["lease_ms"]["maximum"],
            60_000
        );
    }
}
