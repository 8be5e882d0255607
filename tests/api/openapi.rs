//! The OpenAPI document: the checked-in `openapi/openapi.json` must match
//! what the code generates (run with `UPDATE_OPENAPI=1` to rewrite it after
//! an intended change), the daemon serves the same document, and `/docs`
//! works without internet.

use std::time::Duration;

use crate::support::{FOUR_DRIVES, TestDaemon};

const CHECKED_IN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/openapi/openapi.json");

#[test]
fn checked_in_document_matches_the_code() {
    let generated = drivegate::api::openapi::document()
        .to_pretty_json()
        .expect("the document serialises");
    if std::env::var_os("UPDATE_OPENAPI").is_some() {
        std::fs::create_dir_all(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi")).unwrap();
        std::fs::write(CHECKED_IN, format!("{generated}\n")).unwrap();
    }
    let checked_in = std::fs::read_to_string(CHECKED_IN).unwrap_or_default();
    assert!(
        checked_in.trim_end() == generated,
        "openapi/openapi.json differs from the API the code serves: review the change and rerun with UPDATE_OPENAPI=1 to rewrite it"
    );
}

#[test]
fn document_covers_every_route_and_declares_version_and_licence() {
    let doc: serde_json::Value =
        serde_json::from_str(&drivegate::api::openapi::document().to_json().unwrap()).unwrap();
    assert_eq!(doc["openapi"], "3.1.0");
    assert_eq!(doc["info"]["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(doc["info"]["license"]["name"], "MIT OR Apache-2.0");
    let paths = doc["paths"].as_object().unwrap();
    for (path, method) in [
        ("/api/v1/drives", "get"),
        ("/api/v1/drives/{drive}", "get"),
        ("/api/v1/drives/{drive}/status", "get"),
        ("/api/v1/drives/{drive}/commands/{command}", "post"),
        ("/api/v1/drives/{drive}/mode", "put"),
        ("/api/v1/drives/{drive}/setpoint", "put"),
        ("/api/v1/drives/{drive}/lease/renew", "post"),
        ("/api/v1/drives/{drive}/lease", "delete"),
        ("/api/v1/drives/{drive}/protection", "put"),
        ("/api/v1/drives/{drive}/ramps/speed", "put"),
        ("/api/v1/drives/{drive}/ramps/position", "put"),
        ("/api/v1/drives/{drive}/inertia", "put"),
        ("/api/v1/drives/{drive}/rs485-control", "put"),
        ("/api/v1/buses", "get"),
        ("/api/v1/buses/{bus}", "get"),
        ("/api/v1/buses/{bus}/scan", "post"),
        ("/api/v1/buses/{bus}/address", "post"),
        ("/api/v1/stream", "get"),
        ("/healthz", "get"),
        ("/readyz", "get"),
        ("/metrics", "get"),
    ] {
        assert!(
            paths.get(path).and_then(|p| p.get(method)).is_some(),
            "{method} {path} is not documented"
        );
    }
    let schemas = doc["components"]["schemas"].as_object().unwrap();
    for schema in [
        "ProblemDetails",
        "StatusReply",
        "StatusView",
        "DriveView",
        "SetpointBody",
        "ServerMessage",
        "ClientMessage",
        "LeaseInfo",
    ] {
        assert!(schemas.contains_key(schema), "schema {schema} missing");
    }
    // Every operation has an id of its own (clients generated from the
    // document name their methods by it).
    let mut ids = std::collections::BTreeMap::new();
    for (path, item) in paths {
        for (method, op) in item.as_object().unwrap() {
            if let Some(id) = op.get("operationId").and_then(|i| i.as_str())
                && let Some(other) = ids.insert(id.to_string(), format!("{method} {path}"))
            {
                panic!("operationId {id} names both {other} and {method} {path}");
            }
        }
    }
    // Errors are documented as problem+json.
    let setpoint = &paths["/api/v1/drives/{drive}/setpoint"]["put"]["responses"];
    assert!(setpoint["422"]["content"]["application/problem+json"].is_object());
    assert!(doc["components"]["securitySchemes"]["bearer"].is_object());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_serves_the_document_and_an_offline_docs_page() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let http = reqwest::Client::new();
        let served: serde_json::Value = http
            .get(d.url("/openapi.json"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let generated: serde_json::Value =
            serde_json::from_str(&drivegate::api::openapi::document().to_json().unwrap()).unwrap();
        assert_eq!(served, generated);

        let page = http.get(d.url("/docs/")).send().await.unwrap();
        assert_eq!(page.status(), 200);
        let html = page.text().await.unwrap();
        assert!(html.contains("swagger"), "{html}");
        // Every script and stylesheet comes from the daemon itself.
        for attr in ["src=\"", "href=\""] {
            for link in html.split(attr).skip(1) {
                let url = link.split('"').next().unwrap_or("");
                assert!(
                    !url.starts_with("http://")
                        && !url.starts_with("https://")
                        && !url.starts_with("//"),
                    "/docs loads {url} from elsewhere"
                );
            }
        }
        let init = http
            .get(d.url("/docs/swagger-initializer.js"))
            .send()
            .await
            .unwrap();
        assert_eq!(init.status(), 200);
        assert!(init.text().await.unwrap().contains("/openapi.json"));
        let bundle = http
            .get(d.url("/docs/swagger-ui-bundle.js"))
            .send()
            .await
            .unwrap();
        assert_eq!(bundle.status(), 200);
        assert!(bundle.bytes().await.unwrap().len() > 100_000);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
