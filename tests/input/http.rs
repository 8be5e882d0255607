//! Bad input to the HTTP API, generated (proptest) and sent over real
//! sockets to the daemon on the simulator: JSON of every shape and wrong
//! types, missing and extra fields, out-of-range values, bodies that are not
//! JSON or too large, odd content types, path parameters with odd
//! characters, unknown routes and methods, huge and odd headers, bad bearer
//! formats. Every answer is a success or a well-formed problem document
//! (never a 5xx), a refused request writes nothing to a drive, a
//! well-behaved client is served throughout, and no socket or task is left
//! behind.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::input::{
    ADMIN, Baseline, Bystander, OPERATOR, VIEWER, check_answer, config, raw_http, request,
    writes_on_wire,
};
use drivegate::plant::Plant;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use serde_json::Value;

const LIMIT: Duration = Duration::from_secs(60);
/// `[http] max_body_bytes` of these tests: small, so large bodies are cheap.
const MAX_BODY: usize = 2048;

/// Generated cases per property; `DRIVEGATE_PROPTEST_CASES` runs more.
fn cases(default: u32) -> u32 {
    std::env::var("DRIVEGATE_PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The daemon with the role tokens and a small body limit.
/// Generated requests carry many wrong tokens: more than the pause after
/// token guesses lets through (tests/security/tokens.rs tests that).
async fn daemon() -> TestDaemon {
    TestDaemon::start(&config(
        &format!("max_body_bytes = {MAX_BODY}\ntoken_guesses = 1000000"),
        "",
        true,
        "",
    ))
    .await
}

/// [`daemon`] with drives at every unit of a scan's default range (1-32),
/// so the scans that generated bodies start spend no bus time on silent
/// units.
async fn daemon_with_every_scanned_unit() -> TestDaemon {
    let text = crate::support::input::drives_up_to_32(&config(
        &format!("max_body_bytes = {MAX_BODY}\ntoken_guesses = 1000000"),
        "",
        true,
        "",
    ));
    TestDaemon::start(&text).await
}

/// Runs a property with the generated cases on a blocking thread (the
/// strategy is made there: proptest's are not `Send`), each case sending its
/// requests from this test's runtime.
async fn check<S>(
    strategy: impl FnOnce() -> S + Send + 'static,
    cases: u32,
    test: impl Fn(S::Value) -> std::pin::Pin<Box<dyn Future<Output = Result<(), String>> + Send>>
    + Send
    + Sync
    + 'static,
) where
    S: Strategy,
    S::Value: std::fmt::Debug,
{
    let handle = tokio::runtime::Handle::current();
    let result = tokio::task::spawn_blocking(move || {
        let mut runner = TestRunner::new(Config {
            cases,
            failure_persistence: None,
            ..Config::default()
        });
        runner
            .run(&strategy(), |case| {
                handle.block_on(test(case)).map_err(TestCaseError::fail)
            })
            .map_err(|e| e.to_string())
    })
    .await
    .expect("the property runner did not panic");
    if let Err(e) = result {
        panic!("{e}");
    }
}

/// A write operation of the document that takes a JSON body.
#[derive(Debug, Clone)]
struct BodyRoute {
    method: String,
    path: String,
    /// Every field the body may have.
    fields: BTreeSet<String>,
    /// The body may be left out.
    optional: bool,
}

/// The operations with a request body, from the OpenAPI document; the
/// address broadcast is left out (a valid one readdresses every drive).
fn body_routes() -> Vec<BodyRoute> {
    let doc: Value =
        serde_json::from_str(&drivegate::api::openapi::document().to_json().unwrap()).unwrap();
    let schemas = &doc["components"]["schemas"];
    let mut routes = Vec::new();
    for (path, operations) in doc["paths"].as_object().unwrap() {
        for (method, op) in operations.as_object().unwrap() {
            let Some(body) = op.get("requestBody") else {
                continue;
            };
            if path.ends_with("/address") {
                continue;
            }
            let schema = &body["content"]["application/json"]["schema"];
            let mut fields = BTreeSet::new();
            collect_fields(schema, schemas, &mut fields);
            assert!(!fields.is_empty(), "{method} {path}: no fields found");
            routes.push(BodyRoute {
                method: method.to_uppercase(),
                path: path.replace("{drive}", "lift").replace("{bus}", "sim"),
                fields,
                optional: body["required"] != true,
            });
        }
    }
    assert!(routes.len() >= 9, "only {} body routes", routes.len());
    routes
}

fn collect_fields(schema: &Value, schemas: &Value, out: &mut BTreeSet<String>) {
    if let Some(r) = schema["$ref"].as_str() {
        let name = r.rsplit('/').next().unwrap();
        return collect_fields(&schemas[name], schemas, out);
    }
    if let Some(props) = schema["properties"].as_object() {
        out.extend(props.keys().cloned());
    }
    for key in ["oneOf", "anyOf", "allOf"] {
        for s in schema[key].as_array().into_iter().flatten() {
            collect_fields(s, schemas, out);
        }
    }
}

/// Every field name any body takes, so generated objects often have the
/// right keys with the wrong values.
const FIELDS: &[&str] = &[
    "speed_rpm",
    "position_deg",
    "torque_a",
    "torque_counts",
    "lease_ms",
    "limit_a",
    "limit_counts",
    "stall_ms",
    "save",
    "force",
    "alpha",
    "time_s",
    "step_rpm",
    "step_deg",
    "ratio",
    "enabled",
    "mode",
    "from",
    "to",
];

fn json_leaf() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        any::<f64>().prop_filter_map("finite", |f| serde_json::Number::from_f64(f)
            .map(Value::Number)),
        // Values around the bounds of the drive's ranges.
        prop::sample::select(vec![
            -2049.0,
            -2048.6,
            -2048.0,
            -180.01,
            -16.1,
            -1.0,
            -0.001,
            0.0,
            0.004,
            0.5,
            1.0,
            2.0,
            15.99,
            16.0,
            180.0,
            180.01,
            255.0,
            256.0,
            360.01,
            2047.0,
            2047.5,
            2048.0,
            60000.0,
            60001.0,
            65535.0,
            65536.0,
            4294967295.0,
            4294967296.0,
            1e300,
        ])
        .prop_map(Value::from),
        prop::sample::select(vec![
            "speed",
            "position",
            "torque",
            "open_loop",
            "",
            "SPEED"
        ])
        .prop_map(Value::from),
        ".{0,24}".prop_map(Value::String),
    ]
}

fn json_value() -> impl Strategy<Value = Value> {
    json_leaf().prop_recursive(2, 12, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(Value::Array),
            prop::collection::btree_map(key(), inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

fn key() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::sample::select(FIELDS).prop_map(str::to_string),
        1 => "[a-zA-Z_]{1,10}",
    ]
}

/// An object of known keys (mostly) with values of any kind.
fn body_object() -> impl Strategy<Value = Value> {
    prop::collection::btree_map(key(), json_value(), 0..5)
        .prop_map(|m| Value::Object(m.into_iter().collect()))
}

#[derive(Debug, Clone)]
enum Body {
    Json(Value),
    Bytes(Vec<u8>),
    /// A valid-looking JSON object padded to this many bytes.
    Padded(usize),
}

impl Body {
    fn bytes(&self) -> Vec<u8> {
        match self {
            Body::Json(v) => v.to_string().into_bytes(),
            Body::Bytes(b) => b.clone(),
            Body::Padded(n) => {
                let mut text = String::from("{\"speed_rpm\": 1, \"pad\": \"");
                while text.len() + 2 < *n {
                    text.push('x');
                }
                text.push_str("\"}");
                text.into_bytes()
            }
        }
    }
}

/// A value of the right type for `field`, often at or past its bounds.
fn typed_value(field: &str) -> BoxedStrategy<Value> {
    match field {
        "save" | "force" | "enabled" | "only_drive_on_bus" => prop_oneof![
            4 => any::<bool>().prop_map(Value::Bool),
            1 => json_leaf(),
        ]
        .boxed(),
        "mode" => prop::sample::select(vec!["speed", "position", "torque", "open_loop", "fast"])
            .prop_map(Value::from)
            .boxed(),
        // Scan ranges: each silent unit costs bus time, so the valid ones
        // stay among the first few units.
        "from" | "to" => prop_oneof![
            3 => prop::sample::select(vec![-1.0, 0.0, 1.0, 2.0, 4.0, 6.0, 256.0, 1e300, 2.5])
                .prop_map(Value::from),
            1 => json_leaf().prop_filter("no long scans", |v| {
                v.as_f64().is_none_or(|n| !(7.0..=255.0).contains(&n))
            }),
        ]
        .boxed(),
        _ => prop_oneof![
            3 => prop::sample::select(vec![
                -2049.0, -2048.6, -2048.0, -360.5, -180.01, -16.1, -1.0, 0.0, 0.004, 0.5, 1.0,
                15.99, 16.0, 99.0, 100.0, 180.0, 180.01, 255.0, 256.0, 360.01, 2047.0, 2047.5,
                2048.0, 60000.0, 60001.0, 65535.0, 65536.0, 4294967296.0, 1e300, -1e300,
            ])
            .prop_map(Value::from),
            1 => (-100_000i64..100_000).prop_map(Value::from),
            1 => (-1e4..1e4f64).prop_map(Value::from),
            1 => json_leaf(),
        ]
        .boxed(),
    }
}

/// An object of some of the route's own fields, values of about the right
/// type: what reaches the range checks.
fn shaped(fields: Vec<String>) -> impl Strategy<Value = Value> {
    prop::sample::subsequence(fields.clone(), 1..=fields.len().min(3)).prop_flat_map(|chosen| {
        let values: Vec<BoxedStrategy<Value>> = chosen.iter().map(|f| typed_value(f)).collect();
        (Just(chosen), values)
            .prop_map(|(keys, values)| Value::Object(keys.into_iter().zip(values).collect()))
    })
}

fn body(fields: Vec<String>) -> impl Strategy<Value = Body> {
    prop_oneof![
        6 => shaped(fields).prop_map(Body::Json),
        3 => body_object().prop_map(Body::Json),
        2 => json_value().prop_map(Body::Json),
        2 => prop::collection::vec(any::<u8>(), 0..48).prop_map(Body::Bytes),
        1 => (body_object(), any::<prop::sample::Index>()).prop_map(|(v, cut)| {
            let text = v.to_string().into_bytes();
            let n = cut.index(text.len().max(1));
            Body::Bytes(text[..n].to_vec())
        }),
        1 => (MAX_BODY - 64..MAX_BODY * 3).prop_map(Body::Padded),
    ]
}

fn content_type() -> impl Strategy<Value = Option<String>> {
    prop_oneof![
        6 => Just(Some("application/json".to_string())),
        1 => prop::sample::select(vec![
            "application/json; charset=utf-8",
            "APPLICATION/JSON",
            "application/merge-patch+json",
            "text/plain",
            "text/json",
            "application/x-www-form-urlencoded",
            "multipart/form-data; boundary=x",
            "application/octet-stream",
            "application/jsonx",
            ";;;",
        ])
        .prop_map(|s| Some(s.to_string())),
        1 => "[ -~]{0,30}".prop_map(Some),
        1 => Just(None),
    ]
}

/// Whether axum takes `ct` as JSON: application/json or application/*+json.
fn is_json(ct: Option<&str>) -> bool {
    let Some(ct) = ct else { return false };
    let Ok(mime) = ct.parse::<mime_probe::Mime>() else {
        return false;
    };
    mime.is_json()
}

/// Just enough of a media type parser to say what axum will do with it.
mod mime_probe {
    pub struct Mime {
        ty: String,
        subtype: String,
    }

    impl std::str::FromStr for Mime {
        type Err = ();

        fn from_str(s: &str) -> Result<Self, ()> {
            let essence = s.split(';').next().unwrap_or("").trim();
            let (ty, subtype) = essence.split_once('/').ok_or(())?;
            let token = |t: &str| {
                !t.is_empty()
                    && t.bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b"!#$&-^_.+".contains(&b))
            };
            if !token(ty) || !token(subtype) {
                return Err(());
            }
            Ok(Mime {
                ty: ty.to_ascii_lowercase(),
                subtype: subtype.to_ascii_lowercase(),
            })
        }
    }

    impl Mime {
        pub fn is_json(&self) -> bool {
            self.ty == "application" && (self.subtype == "json" || self.subtype.ends_with("+json"))
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bodies_of_every_shape_are_answered_cleanly_and_refusals_write_nothing() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon_with_every_scanned_unit().await;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(d.http, Some(VIEWER));
        bystander.wait_for(3).await;
        let routes = Arc::new(body_routes());
        let (addr, plant) = (d.http, d.plant.clone());
        // Scans are the slow route (one response timeout per silent unit):
        // a third of the weight of the others.
        let weights: Vec<(u32, usize)> = routes
            .iter()
            .enumerate()
            .map(|(i, r)| (if r.path.ends_with("/scan") { 1 } else { 3 }, i))
            .collect();
        let fields: Vec<Vec<String>> = routes
            .iter()
            .map(|r| r.fields.iter().cloned().collect())
            .collect();
        let strategy = move || {
            prop::strategy::Union::new_weighted(
                weights.iter().map(|&(w, i)| (w, Just(i))).collect(),
            )
            .prop_flat_map(move |i| (Just(i), body(fields[i].clone()), content_type()))
        };
        let seen = Arc::new(std::sync::Mutex::new(
            std::collections::BTreeMap::<u16, u32>::new(),
        ));
        let tally = seen.clone();
        check(strategy, cases(256), move |(route, body, ct)| {
            let (routes, plant, tally) = (routes.clone(), plant.clone(), tally.clone());
            Box::pin(async move {
                let status = body_case(addr, &plant, &routes[route], &body, ct.as_deref()).await?;
                *tally.lock().unwrap().entry(status).or_default() += 1;
                Ok(())
            })
        })
        .await;
        // The generator reaches every check, not only the JSON parser.
        let seen = seen.lock().unwrap().clone();
        println!("answers to generated bodies, by status: {seen:?}");
        for status in [200, 400, 413, 415, 422] {
            assert!(seen.contains_key(&status), "no {status} among {seen:?}");
        }
        bystander.finish(3, "the body property").await;
        baseline
            .assert_back(Duration::from_secs(5), "bodies of every shape")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

async fn body_case(
    addr: SocketAddr,
    plant: &Plant,
    route: &BodyRoute,
    body: &Body,
    ct: Option<&str>,
) -> Result<u16, String> {
    let bytes = body.bytes();
    let header = ct.map(|c| format!("Content-Type: {c}"));
    let extra: Vec<&str> = header.iter().map(String::as_str).collect();
    let before = writes_on_wire(plant);
    let answer = raw_http(
        addr,
        &request(&route.method, &route.path, Some(ADMIN), &extra, &bytes),
    )
    .await?;
    let context = || {
        format!(
            "{} {} with {ct:?} {:?}: {} {}",
            route.method,
            route.path,
            String::from_utf8_lossy(&bytes),
            answer.status,
            answer.text()
        )
    };
    check_answer(&answer).map_err(|e| format!("{e} ({})", context()))?;
    let empty = bytes.iter().all(u8::is_ascii_whitespace);
    let expected = if !is_json(ct) && (!route.optional || !empty) {
        // A body that does not say it is JSON (where one is needed, or
        // where one was sent).
        Some(415)
    } else if bytes.len() > MAX_BODY {
        Some(413)
    } else if empty && !route.optional {
        Some(400)
    } else {
        None
    };
    if let Some(status) = expected
        && answer.status != status
    {
        return Err(format!("expected {status}: {}", context()));
    }
    if answer.status < 300 {
        // Accepted: a JSON object (or nothing, where the body is optional)
        // with no field the route does not take.
        match serde_json::from_slice::<Value>(&bytes) {
            Ok(Value::Object(map)) => {
                if let Some(extra) = map.keys().find(|k| !route.fields.contains(*k)) {
                    return Err(format!("accepted an unknown field {extra}: {}", context()));
                }
            }
            Ok(Value::Null) | Err(_) if route.optional && (empty || bytes == b"null") => {}
            _ => {
                return Err(format!(
                    "accepted a body that is not an object: {}",
                    context()
                ));
            }
        }
    } else if writes_on_wire(plant) != before {
        return Err(format!("a refused request wrote to a drive: {}", context()));
    }
    Ok(answer.status)
}

/// Percent-encodes every byte outside the URL's unreserved set.
fn encode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

/// A path segment: anything at all, percent-encoded, or raw characters that
/// mean something in a path.
fn segment() -> impl Strategy<Value = String> {
    prop_oneof![
        3 => any::<String>().prop_map(|s| encode(&s)),
        2 => "[a-z0-9]{1,12}",
        1 => prop::sample::select(vec![
            "..", ".", "%2e%2e", "%2E", "%00", "%zz", "%", "%2F", "a%2Fb", ";", ";x=1", "~",
            "conveyor%00", "conveyor.", "CONVEYOR", "0", "-1", "01", "256", "4294967297",
            "1e2", "%20lift", "lift%20", "%E2%80%AE", "%C0%AF", "%FF%FE",
        ])
        .prop_map(str::to_string),
        1 => (1usize..4000).prop_map(|n| "z".repeat(n)),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn odd_path_parameters_are_unknown_things_not_errors() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(d.http, Some(VIEWER));
        bystander.wait_for(3).await;
        let (addr, plant) = (d.http, d.plant.clone());
        let templates = [
            ("GET", "/api/v1/drives/{}", ""),
            ("GET", "/api/v1/drives/{}/status?fresh=true", ""),
            ("POST", "/api/v1/drives/{}/commands/activate", ""),
            ("POST", "/api/v1/drives/lift/commands/{}", ""),
            ("PUT", "/api/v1/drives/{}/setpoint", r#"{"speed_rpm": 1}"#),
            ("DELETE", "/api/v1/drives/{}/lease", ""),
            ("GET", "/api/v1/buses/{}", ""),
            ("POST", "/api/v1/buses/{}/scan", r#"{"from": 1, "to": 1}"#),
        ];
        let known = [
            "conveyor",
            "lift",
            "turntable",
            "feeder",
            "1",
            "2",
            "3",
            "4",
            "sim",
        ];
        let strategy = move || (0..templates.len(), segment());
        check(strategy, cases(300), move |(t, seg)| {
            let plant = plant.clone();
            Box::pin(async move {
                let (method, template, body) = templates[t];
                // Names that exist, written in a way that decodes to them,
                // are not odd: skip them.
                let decoded = percent_decode(&seg);
                if known.iter().any(|k| decoded.eq_ignore_ascii_case(k))
                    || decoded.parse::<u8>().is_ok_and(|u| (1..=4).contains(&u))
                    || drivegate::drive::ConfigCommand::from_name(&decoded).is_some()
                {
                    return Ok(());
                }
                let target = template.replace("{}", &seg);
                let ct = ["Content-Type: application/json"];
                let extra: &[&str] = if body.is_empty() { &[] } else { &ct };
                let before = writes_on_wire(&plant);
                let a = raw_http(
                    addr,
                    &request(method, &target, Some(ADMIN), extra, body.as_bytes()),
                )
                .await?;
                check_answer(&a).map_err(|e| format!("{e} ({method} {target})"))?;
                if !matches!(a.status, 400 | 404) {
                    return Err(format!("{method} {target}: {} {}", a.status, a.text()));
                }
                if writes_on_wire(&plant) != before {
                    return Err(format!("{method} {target} wrote to a drive"));
                }
                Ok(())
            })
        })
        .await;
        bystander.finish(3, "the path property").await;
        baseline
            .assert_back(Duration::from_secs(5), "odd paths")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%'
            && let Some(v) = s
                .get(i + 1..i + 3)
                .and_then(|h| u8::from_str_radix(h, 16).ok())
        {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_routes_are_404_and_wrong_methods_405_with_allow() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(d.http, Some(VIEWER));
        bystander.wait_for(3).await;
        let addr = d.http;

        // Every documented path with every method it does not take.
        let doc: Value =
            serde_json::from_str(&drivegate::api::openapi::document().to_json().unwrap()).unwrap();
        let methods = ["GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE"];
        let mut checked = 0;
        for (path, ops) in doc["paths"].as_object().unwrap() {
            let target = path
                .replace("{drive}", "lift")
                .replace("{bus}", "sim")
                .replace("{command}", "activate")
                .replace("{id}", "1");
            let allowed: Vec<String> = ops
                .as_object()
                .unwrap()
                .keys()
                .map(|m| m.to_uppercase())
                .collect();
            for method in methods.iter().filter(|m| !allowed.iter().any(|a| a == *m)) {
                let a = raw_http(addr, &request(method, &target, Some(ADMIN), &[], b""))
                    .await
                    .unwrap();
                check_answer(&a).unwrap_or_else(|e| panic!("{method} {target}: {e}"));
                assert_eq!(a.status, 405, "{method} {target}: {}", a.text());
                let allow = a.header("allow").unwrap().to_uppercase();
                for m in &allowed {
                    assert!(
                        allow.contains(m.as_str()),
                        "{method} {target}: Allow {allow}"
                    );
                }
                checked += 1;
            }
        }
        assert!(checked > 80, "only {checked} wrong methods tried");

        // Made-up paths, with made-up methods too.
        let prefixes = [
            "",
            "/api",
            "/api/v1",
            "/api/v2",
            "/api/v1/drives/lift",
            "/api/v1/buses/sim",
            "/healthz",
            "/metrics",
        ];
        let strategy = move || {
            (
                prop::sample::select(prefixes.to_vec()),
                prop::collection::vec("[a-zA-Z0-9_.~-]{1,10}", 1..4),
                prop::sample::select(vec![
                    "GET", "POST", "PUT", "DELETE", "PATCH", "PROPFIND", "FOO",
                ]),
            )
        };
        check(strategy, cases(200), move |(prefix, segments, method)| {
            Box::pin(async move {
                let target = format!("{prefix}/{}", segments.join("/"));
                let a = raw_http(addr, &request(method, &target, Some(ADMIN), &[], b"")).await?;
                check_answer(&a).map_err(|e| format!("{e} ({method} {target})"))?;
                // Some made-up paths exist (/api/v1/drives/lift/status ...):
                // those may answer anything but an error of the server.
                let documented = doc_has(&target);
                if !documented && a.status != 404 {
                    return Err(format!("{method} {target}: {} {}", a.status, a.text()));
                }
                Ok(())
            })
        })
        .await;
        bystander.finish(3, "the route property").await;
        baseline
            .assert_back(Duration::from_secs(5), "unknown routes")
            .await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// True when `target` matches a documented path template (or is the
/// interactive page, with its files).
fn doc_has(target: &str) -> bool {
    if target.starts_with("/docs") || target.starts_with("/openapi.json") {
        return true;
    }
    let doc = drivegate::api::openapi::document();
    let segments: Vec<&str> = target.trim_end_matches('/').split('/').collect();
    doc.paths.paths.keys().any(|template| {
        let parts: Vec<&str> = template.split('/').collect();
        parts.len() == segments.len()
            && parts
                .iter()
                .zip(&segments)
                .all(|(p, s)| p.starts_with('{') || p == s)
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn odd_headers_and_bearer_formats() {
    tokio::time::timeout(LIMIT, async {
        let d = daemon().await;
        let baseline = Baseline::take(&d).await;
        let bystander = Bystander::http(d.http, Some(VIEWER));
        bystander.wait_for(3).await;
        let addr = d.http;
        let status = "/api/v1/drives/conveyor/status";

        // Huge and many headers: hyper's limits answer 431 (or the request
        // passes); never a server error, and the daemon carries on.
        for size in [8 * 1024, 64 * 1024, 512 * 1024, 2 * 1024 * 1024] {
            let big = format!("X-Padding: {}", "p".repeat(size));
            let a = raw_http(addr, &request("GET", status, Some(ADMIN), &[&big], b""))
                .await
                .unwrap_or_else(|e| panic!("a {size}-byte header: {e}"));
            check_answer(&a).unwrap_or_else(|e| panic!("a {size}-byte header: {e}"));
            assert!(matches!(a.status, 200 | 431), "{size}: {}", a.status);
        }
        let many: Vec<String> = (0..500).map(|i| format!("X-H{i}: {i}")).collect();
        let many: Vec<&str> = many.iter().map(String::as_str).collect();
        let a = raw_http(addr, &request("GET", status, Some(ADMIN), &many, b""))
            .await
            .unwrap();
        check_answer(&a).unwrap();
        assert!(matches!(a.status, 200 | 431), "500 headers: {}", a.status);
        let big_body_header = "Content-Length: 99999999999999999999";
        let a = raw_http(
            addr,
            &format!("PUT /api/v1/drives/lift/inertia HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n{big_body_header}\r\nContent-Type: application/json\r\nAuthorization: Bearer {ADMIN}\r\n\r\n{{}}").into_bytes(),
        )
        .await
        .unwrap();
        check_answer(&a).unwrap();
        // A request line and headers that are not HTTP.
        for garbage in [
            &b"\x00\x01\x02\x03\r\n\r\n"[..],
            b"GET\r\n\r\n",
            b"GET / HTTP/9.9\r\n\r\n",
            b"GET /healthz HTTP/1.1\r\nHost x\r\n\r\n",
            b"GET /healthz HTTP/1.1\r\nContent-Length: -1\r\n\r\n",
            b"POST /api/v1/buses/sim/scan HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: chunked\r\nContent-Length: 3\r\n\r\nzz\r\n",
        ] {
            if let Ok(a) = raw_http(addr, garbage).await {
                check_answer(&a)
                    .unwrap_or_else(|e| panic!("{:?}: {e}", String::from_utf8_lossy(garbage)));
            }
        }

        // Authorization values of every shape: 401 with a problem unless it
        // is a valid token in the one accepted form.
        let strategy = || prop_oneof![
            "[ -~]{0,80}",
            prop::sample::select(vec![
                String::new(),
                "Bearer".into(),
                "Bearer ".into(),
                "Bearer  ".into(),
                format!("Basic {ADMIN}"),
                format!("Token {ADMIN}"),
                format!("Bearer{ADMIN}"),
                format!("Bearer {ADMIN}x"),
                format!("Bearer x{ADMIN}"),
                format!("Bearer {}", &ADMIN[..ADMIN.len() - 1]),
                format!("Bearer {}", ADMIN.to_uppercase()),
                format!("Bearer \"{ADMIN}\""),
                format!("Bearer {ADMIN},{ADMIN}"),
                format!("Bearer {}", "t".repeat(20_000)),
                format!("Bearer\t{ADMIN}"),
            ]),
        ];
        check(strategy, cases(200), move |value| {
            Box::pin(async move {
                let header = format!("Authorization: {value}");
                let a = raw_http(addr, &request("POST", "/api/v1/drives/lift/commands/fault-reset", None, &[&header], b"")).await?;
                check_answer(&a).map_err(|e| format!("{e} ({value:?})"))?;
                // The server's rule: a scheme of "bearer" in any case, one
                // space, the token with blanks around it ignored.
                let valid = value.trim().split_once(' ').is_some_and(|(scheme, token)| {
                    scheme.eq_ignore_ascii_case("bearer") && token.trim() == ADMIN
                });
                match (valid, a.status) {
                    (true, 200) | (false, 401 | 431) => Ok(()),
                    _ => Err(format!("Authorization {value:?}: {} {}", a.status, a.text())),
                }
            })
        })
        .await;
        // Bytes that are not text in the header, two headers, a token in
        // the query string of a REST route: all refused.
        let mut odd = format!("POST /api/v1/drives/lift/commands/fault-reset HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nContent-Length: 0\r\nAuthorization: Bearer {OPERATOR}").into_bytes();
        odd.extend_from_slice(b"\xff\xfe\r\n\r\n");
        let a = raw_http(addr, &odd).await.unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 401, "{}", a.text());
        let a = raw_http(
            addr,
            &request("POST", "/api/v1/drives/lift/commands/fault-reset", None, &[&format!("Authorization: Bearer {VIEWER}"), &format!("Authorization: Bearer {OPERATOR}")], b""),
        )
        .await
        .unwrap();
        check_answer(&a).unwrap();
        assert_ne!(a.status, 200, "two Authorization headers let a viewer write");
        let a = raw_http(
            addr,
            &request("POST", &format!("/api/v1/drives/lift/commands/fault-reset?access_token={OPERATOR}"), None, &[], b""),
        )
        .await
        .unwrap();
        check_answer(&a).unwrap();
        assert_eq!(a.status, 401, "a REST route took the token from the query");

        bystander.finish(3, "odd headers").await;
        baseline.assert_back(Duration::from_secs(5), "odd headers").await;
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}
