//! Every configuration `check-config` accepts starts, and every one it
//! refuses is refused naming the valid range, at the key's line.
//!
//! The keys and their ranges come from the code, not from a list here: a
//! configuration with every section ([mqtt] in both formats, [opcua],
//! [modbus_tcp.tls], a simulated bus with every table of its own) is
//! probed key by key, the way an operator's mistake would: a huge number
//! gets the range back ("valid 2 to 3600"), a word that is no value gets
//! the values of an enum ("expected one of ..."). Then:
//!
//! - each number just below and just above its range is refused, with the
//!   range named, at the key's line (or, for a rule across keys, naming
//!   the key);
//! - configurations are made with every key at once at one point of its
//!   range (its least, its most, the middle, a tenth in; the JSON format
//!   at the least and the most), the enums at each of their values,
//!   booleans both ways; a key that a rule across
//!   keys refuses there (a lease bound against the jog's lease) is left
//!   at its default and must have been refused naming a range;
//! - each configuration accepted is started in-process, against a real
//!   mosquitto, and must serve: `/readyz` answered, Modbus TCP, Modbus/TCP
//!   Security and OPC UA accepting connections, MQTT connected, no face
//!   crashed.
//!
//! Every key of those tables must be probed: a key added to the code
//! fails here until the base configuration shows it (or the test says why
//! not).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use drivegate::config::Config;
use toml::{Table, Value};

use crate::support::certs::Pki;
use crate::support::mosquitto::Mosquitto;
use crate::support::{TestDaemon, bounded, eventually};

const UNKNOWN: &str = "zz_not_a_key";
const NOT_A_VALUE: &str = "zz_not_a_value";
const HUGE: i64 = 1_000_000_000_000_000;

/// Keys the base does not show, and why.
const NOT_PROBED: &[(&str, &str)] = &[
    (
        "http.tls",
        "certificate files: no number (HTTPS is tested in security/https.rs)",
    ),
    ("mqtt.username", "a name"),
    ("mqtt.password_file", "a file"),
    ("mqtt.ca", "a file"),
    ("mqtt.client_cert", "a file"),
    ("mqtt.client_key", "a file"),
    (
        "mqtt.primary_host_id",
        "a name; births then wait for a host",
    ),
    ("safety.state_dir", "a directory"),
    (
        "http.token.file",
        "a token's source: one of sha256, file, env",
    ),
    (
        "http.token.env",
        "a token's source: one of sha256, file, env",
    ),
    (
        "http.lease_min_ms",
        "moved to [safety]: refused here, naming where it went",
    ),
    (
        "http.lease_max_ms",
        "moved to [safety]: refused here, naming where it went",
    ),
    ("http.allowed_hosts", "a list of names: no range"),
    ("http.allowed_origins", "a list of origins: no range"),
    (
        "modbus_tcp.allowed_networks",
        "a list of networks: no range",
    ),
    (
        "modbus_tcp.raw_functions",
        "a list of function codes, each checked",
    ),
    (
        "bus.drive.settings.protection.limit_counts",
        "limit_a in counts: one of the two",
    ),
    ("bus.sim.devices", "a list of units"),
    ("bus.sim.strict_units", "a list of units"),
    ("bus.sim.faults.silent_units", "a list of units"),
    ("opcua.security", "a list of endpoints, each an enum"),
    (
        "opcua.user_certificate.thumbprint",
        "a user certificate is named one way: by subject here, or by thumbprint",
    ),
];

/// Every section, each key at a valid value.
fn base(broker: &str, format: &str, pki: &Pki, opcua_pki: &std::path::Path) -> String {
    format!(
        r#"
[http]
listen = "127.0.0.1:0"
max_body_bytes = 65536
max_connections = 128
max_connections_per_address = 32
idle_timeout_s = 120
header_timeout_ms = 5000
read_timeout_s = 30
send_buffer_bytes = 65536
stream_buffer = 256
lease_default_ms = 0
token_guesses = 10
[[http.token]]
name = "ranges"
role = "admin"
sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"

[modbus_tcp]
enabled = true
listen = "127.0.0.1:0"
max_connections = 64
max_connections_per_address = 16
idle_timeout_ms = 60000
max_pipelined = 16
read_only = false
broadcast_reply = false
[[modbus_tcp.clients]]
network = "10.20.0.0/16"
role = "operator"
allow_saves_while_moving = false
comm_loss_ms = 500
comm_loss_action = "zero-speed"
[[modbus_tcp.unit_map]]
units = "1-2"
bus = "sim"
bus_units = "1-2"
[[modbus_tcp.polled_copy]]
bus = "sim"
max_age_ms = 250
[modbus_tcp.tls]
listen = "127.0.0.1:0"
cert = "{server}"
key = "{server_key}"
client_ca = "{ca}"
default_role = "viewer"
allow_saves_while_moving = false
comm_loss_ms = 1000
comm_loss_action = "brake"

[mqtt]
broker = "{broker}"
format = "{format}"
topic_prefix = "ranges/gw"
group_id = "plant"
node_id = "ranges"
commands = "none"
unauthenticated_commands = false
keepalive_s = 10
max_message_bytes = 65536
comm_loss_ms = 5000
comm_loss_action = "zero-speed"
store_max_mb = 64
full_publish_s = 0
[mqtt.deadbands]
speed_rpm = 1.0
angle_deg = 0.5
current_a = 0.05
voltage_v = 0.5
temperature_c = 1.0

[opcua]
listen = "127.0.0.1:0"
pki_dir = "{opcua_pki}"
allow_none_on_network = false
anonymous = "viewer"
session_timeout_max_ms = 30000
comm_loss_action = "zero-speed"
max_sessions = 20
max_sessions_per_address = 10
max_connections = 64
max_connections_per_address = 16
user_ca = "{ca}"
max_subscriptions_per_session = 10
max_monitored_items_per_session = 1000
max_monitored_items = 10000
max_queue_size = 10
max_event_queue_size = 1000
max_queued_values = 100000
[[opcua.user_certificate]]
subject = "CN=olivia, O=plant"
role = "operator"

[log]
format = "auto"
level = "info"

[safety]
on_shutdown = "zero-speed"
on_lease_expiry = "zero-speed"
jog_lease_ms = 300
lease_min_ms = 100
lease_max_ms = 60000
on_unknown_state = "zero-speed"
alarms_kept = 500

[monitor]
enabled = true
ring_frames = 10000

[scope]
max_samples = 200000
floor_rate_hz = 10.0
max_wait_s = 3600

[history]
minutes = 60
full_rate_s = 60

[[bus]]
name = "sim"
port = "sim"
baud = 115200
response_timeout_ms = 250
reply_timeout_floor_ms = 3
retries = 1
poll_interval_ms = 0
guard_ms = 50
broadcast_delay_ms = 20
interframe = "spec"
offline_after = 3
offline_backoff_ms = 2000
offline_backoff_max_ms = 30000
queue_capacity = 256
queue_per_client = 64
queue_timeout_ms = 5000
poll_share = 4
[bus.rs485]
direction = "auto"
rts_active_high = true
delay_before_send_us = 0
delay_after_send_us = 0
[bus.sim]
turnaround_ms = 0.5
seed = 1
reboot_ms = 300.0
calibrated = true
frame_gap_us = 350
[bus.sim.delivery]
chunk_bytes = 1
jitter_us = 0
[bus.sim.faults]
drop_rate = 0.0
crc_error_rate = 0.0
late_rate = 0.0
late_ms = 0.0
noise_rate = 0.0
[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
poll_interval_ms = 100
[bus.drive.settings]
apply_settings = "never"
save = false
inertia_ratio = 5
rs485_control = true
[bus.drive.settings.protection]
limit_a = 12.0
stall_ms = 3000
[bus.drive.settings.speed_ramp]
alpha = 5000
[bus.drive.settings.position_ramp]
alpha = 200
"#,
        server = pki.path("server.pem").display(),
        server_key = pki.path("server.key").display(),
        ca = pki.path("clients.pem").display(),
        opcua_pki = opcua_pki.display(),
    )
}

/// What a key takes.
#[derive(Debug, Clone)]
enum Kind {
    /// A number in a range (`int`: written as an integer).
    Number { min: f64, max: f64, int: bool },
    /// A number with no bound the code names.
    Any,
    /// One of these words.
    Word(Vec<String>),
    /// true or false.
    Bool,
}

/// A key of a table, and what it takes.
#[derive(Debug, Clone)]
struct Key {
    /// The table's path (an array of tables by its first entry).
    table: Vec<String>,
    name: String,
    kind: Kind,
}

impl Key {
    fn dotted(&self) -> String {
        [self.table.join("."), self.name.clone()].join(".")
    }
}

/// The table at `path` of `doc`.
fn table<'a>(doc: &'a mut Table, path: &[String]) -> &'a mut Table {
    let mut t = doc;
    for key in path {
        t = match t.get_mut(key).unwrap() {
            Value::Table(t) => t,
            Value::Array(a) => a[0].as_table_mut().unwrap(),
            other => panic!("{path:?}: {other:?} is no table"),
        };
    }
    t
}

/// `doc` with `key` set to `value`.
fn with(doc: &Table, key: &Key, value: Value) -> Table {
    let mut doc = doc.clone();
    table(&mut doc, &key.table).insert(key.name.clone(), value);
    doc
}

fn text(doc: &Table) -> String {
    toml::to_string(doc).unwrap()
}

/// What check-config says of `doc`'s values: nothing, or its error.
fn parsed(doc: &Table) -> Result<Config, String> {
    Config::parse(&text(doc), "drivegate.toml").map_err(|e| e.to_string())
}

/// What check-config says of `doc`, its TLS files loaded too.
fn check(doc: &Table) -> Result<Config, String> {
    let config = parsed(doc)?;
    drivegate::api::config_check::check_tls(&config)?;
    Ok(config)
}

/// The range an error names ("valid 2 to 3600").
fn range_named(error: &str) -> Option<(f64, f64)> {
    let rest = error.split_once("valid ")?.1;
    let (min, rest) = rest.split_once(" to ")?;
    let max: String = rest
        .chars()
        .take_while(|c| c.is_ascii_digit() || matches!(c, '.' | '-'))
        .collect();
    Some((min.parse().ok()?, max.trim_end_matches('.').parse().ok()?))
}

/// The words an enum's error lists ("expected one of `a`, `b`").
fn words_named(error: &str) -> Option<Vec<String>> {
    let list = error.split_once("expected ")?.1;
    let words: Vec<String> = list
        .split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect();
    (!words.is_empty()).then_some(words)
}

/// The keys the code accepts in the table at `path`.
fn accepted_keys(doc: &Table, path: &[String]) -> Vec<String> {
    let mut doc = doc.clone();
    table(&mut doc, path).insert(UNKNOWN.into(), Value::Integer(0));
    let error = parsed(&doc)
        .err()
        .unwrap_or_else(|| panic!("[{}] takes any key", path.join(".")));
    let list = error
        .split_once("expected one of ")
        .or_else(|| error.split_once("expected "))
        .unwrap_or_else(|| panic!("[{}]: {error}", path.join(".")))
        .1;
    list.split(", ")
        .flat_map(|k| k.split(" or "))
        .map(|k| k.trim().trim_matches('`').to_string())
        .collect()
}

/// Every key of every table of `doc`, probed; what is wrong goes to
/// `problems`.
fn probe(doc: &Table, problems: &mut Vec<String>) -> Vec<Key> {
    let mut keys = Vec::new();
    let mut tables: Vec<Vec<String>> = vec![Vec::new()];
    while let Some(path) = tables.pop() {
        let mut copy = doc.clone();
        let t = table(&mut copy, &path).clone();
        if !path.is_empty() {
            for name in accepted_keys(doc, &path) {
                let dotted = [path.join("."), name.clone()].join(".");
                let shown = t.contains_key(&name);
                let skipped = NOT_PROBED.iter().any(|(k, _)| *k == dotted);
                if !(shown || skipped || is_table_name(&name, &t)) {
                    problems.push(format!(
                        "{dotted}: a key the code takes that this test does not probe; show it in the base configuration"
                    ));
                }
            }
        }
        for (name, value) in &t {
            let mut sub = path.clone();
            sub.push(name.clone());
            match value {
                Value::Table(_) => tables.push(sub),
                Value::Array(a) if a.first().is_some_and(Value::is_table) => tables.push(sub),
                Value::Integer(_) | Value::Float(_) => {
                    let key = Key {
                        table: path.clone(),
                        name: name.clone(),
                        kind: Kind::Any,
                    };
                    let int = value.is_integer();
                    let kind = match parsed(&with(doc, &key, Value::Integer(HUGE))) {
                        Ok(_) => Kind::Any,
                        Err(e) => match range_named(&e) {
                            Some((min, max)) => Kind::Number { min, max, int },
                            None => {
                                problems.push(format!(
                                    "{}: a huge number refused without a range: {e}",
                                    key.dotted()
                                ));
                                Kind::Any
                            }
                        },
                    };
                    keys.push(Key { kind, ..key });
                }
                Value::Boolean(_) => keys.push(Key {
                    table: path.clone(),
                    name: name.clone(),
                    kind: Kind::Bool,
                }),
                Value::String(_) => {
                    let key = Key {
                        table: path.clone(),
                        name: name.clone(),
                        kind: Kind::Any,
                    };
                    if let Err(e) = parsed(&with(doc, &key, Value::String(NOT_A_VALUE.into())))
                        && e.contains("unknown variant")
                        && let Some(words) = words_named(&e)
                    {
                        keys.push(Key {
                            kind: Kind::Word(words),
                            ..key
                        });
                    }
                }
                _ => {}
            }
        }
    }
    keys
}

fn is_table_name(name: &str, t: &Table) -> bool {
    matches!(t.get(name), Some(Value::Table(_) | Value::Array(_)))
}

/// `v` as the key writes it.
fn number(v: f64, int: bool) -> Value {
    if int {
        Value::Integer(v.round() as i64)
    } else {
        Value::Float(v)
    }
}

/// The points of a range a configuration is made at.
const POINTS: [&str; 4] = ["least", "most", "middle", "a tenth in"];

fn point(min: f64, max: f64, i: usize) -> f64 {
    match i % POINTS.len() {
        0 => min,
        1 => max,
        2 => min + (max - min) / 2.0,
        _ => min + (max - min) / 10.0,
    }
}

/// The line of `doc`'s text where `key` is set.
fn line_of(doc: &Table, key: &Key) -> usize {
    let text = text(doc);
    let mut in_table = key.table.is_empty();
    let header = key.table.join(".");
    for (i, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.starts_with('[') {
            in_table = l.trim_matches(['[', ']']) == header;
        } else if in_table && l.starts_with(&format!("{} =", key.name)) {
            return i + 1;
        }
    }
    panic!("{} not in the text", key.dotted())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_configuration_check_config_accepts_starts_and_every_refusal_names_the_range() {
    bounded(Duration::from_secs(120), async {
        let broker = Mosquitto::start();
        let pki = Pki::new();
        pki.ca("clients");
        let dir = tempfile::tempdir().unwrap();
        let opcua_pki = crate::support::opcua::server_pki(dir.path());
        let bases: Vec<Table> = ["sparkplug", "json"]
            .iter()
            .map(|format| base(&broker.url(), format, &pki, &opcua_pki).parse().unwrap())
            .collect();
        let started = Instant::now();
        let mut problems = Vec::new();
        let keys = probe(&bases[0], &mut problems);
        let numbers = keys
            .iter()
            .filter(|k| matches!(k.kind, Kind::Number { .. }))
            .count();
        assert!(numbers > 60, "only {numbers} numeric keys found: {keys:#?}");

        // Just outside each range: refused, naming it, at the key's line.
        for key in &keys {
            let Kind::Number { min, max, int } = key.kind else {
                continue;
            };
            let step = if int { 1.0 } else { (max - min) / 1000.0 };
            for v in [min - step, max + step] {
                let doc = with(&bases[0], key, number(v, int));
                let Err(e) = parsed(&doc) else {
                    problems.push(format!(
                        "{} = {v} accepted; the refusal of {HUGE} named {min} to {max}",
                        key.dotted()
                    ));
                    continue;
                };
                if range_named(&e) != Some((min, max)) {
                    problems.push(format!("{} = {v}: {e} (not the range {min} to {max})", key.dotted()));
                }
                // At the key's line; a rule across keys (or over a whole
                // table) may point elsewhere, but then names the key.
                let line = format!("drivegate.toml:{}:", line_of(&doc, key));
                let names = e.contains(&format!("{} =", key.name))
                    || e.contains(&format!("{}:", key.name));
                if !e.starts_with(&line) && !names {
                    problems.push(format!("{} = {v}: {e} (not at {line})", key.dotted()));
                }
            }
        }
        let refusals = started.elapsed();
        assert!(problems.is_empty(), "{}", problems.join("\n"));

        // Every key at one point of its range at once, in both formats.
        let mut seen: BTreeMap<String, Vec<String>> = BTreeMap::new();
        let mut runs: Vec<(String, String)> = Vec::new();
        for (f, base) in bases.iter().enumerate() {
            // The JSON format at the bounds only: the rest is the same.
            for i in 0..if f == 0 { POINTS.len() } else { 2 } {
                let mut set: Vec<(&Key, Value)> = keys
                    .iter()
                    .filter(|k| !(k.name == "format" && k.table == ["mqtt"]))
                    .filter_map(|key| {
                        let value = match &key.kind {
                            Kind::Number { min, max, int } => number(point(*min, *max, i), *int),
                            Kind::Word(words) => Value::String(words[(i + f) % words.len()].clone()),
                            Kind::Bool => Value::Boolean((i + f) % 2 == 1),
                            Kind::Any => return None,
                        };
                        Some((key, value))
                    })
                    .collect();
                // Each key set in turn, kept where the file stays valid;
                // what a rule across keys refuses there stays at its
                // default (the files differ only in their values: the
                // TLS files are loaded once, at the end).
                let mut doc = base.clone();
                set.retain(|(key, value)| {
                    let tried = with(&doc, key, value.clone());
                    match parsed(&tried) {
                        Ok(_) => {
                            doc = tried;
                            true
                        }
                        Err(e) => {
                            // A number out of what another key allows is
                            // refused naming its range; a word or a
                            // boolean, naming the key and why.
                            let said = match key.kind {
                                Kind::Number { .. } => range_named(&e).is_some(),
                                _ => e.contains(&format!("{} =", key.name)),
                            };
                            if !said {
                                problems.push(format!(
                                    "{} = {value} (at {}) refused without naming a range: {e}",
                                    key.dotted(),
                                    POINTS[i]
                                ));
                            }
                            false
                        }
                    }
                });
                check(&doc).unwrap_or_else(|e| panic!("the TLS files: {e}"));
                for (key, value) in &set {
                    seen.entry(key.dotted()).or_default().push(value.to_string());
                }
                assert!(problems.is_empty(), "{}", problems.join("\n"));
                // A node id of its own: two run at once on the broker.
                let n = runs.len();
                table(&mut doc, &["mqtt".to_string()])
                    .insert("node_id".into(), Value::String(format!("ranges-{n}")));
                runs.push((
                    text(&doc),
                    format!("{} format, keys at {}", ["sparkplug", "json"][f], POINTS[i]),
                ));
            }
        }
        // Two at a time (they mostly wait on their stops), never the two
        // with the largest bus monitor rings together.
        let t0 = Instant::now();
        for (a, b) in [(0, 5), (1, 4), (2, 3)] {
            tokio::join!(serves(&runs[a].0, &runs[a].1), serves(&runs[b].0, &runs[b].1));
        }
        let starts = t0.elapsed();
        // Each bound of each range was started, or refused by a rule
        // across keys that named its range.
        for key in &keys {
            if let Kind::Number { min, max, int } = key.kind {
                let values = seen.get(&key.dotted()).cloned().unwrap_or_default();
                for bound in [min, max] {
                    let shown = number(bound, int).to_string();
                    if !values.contains(&shown) {
                        eprintln!("{} = {shown} never started: a rule across keys refuses it with the defaults", key.dotted());
                    }
                }
            }
        }
        eprintln!(
            "{} keys ({numbers} numbers), refusals checked in {refusals:?}; {} configurations started in {starts:?}",
            keys.len(),
            runs.len(),
        );
    })
    .await;
}

/// `GET /readyz` on a connection of its own, closed after the answer.
async fn readyz(http: std::net::SocketAddr) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(http).await.unwrap();
    s.write_all(b"GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut answer = String::new();
    let _ = s.read_to_string(&mut answer).await;
    answer
}

/// Starts `toml` in-process and checks that every face serves.
async fn serves(toml: &str, what: &str) {
    let d = TestDaemon::start_no_wait(toml).await;
    // With header_timeout_ms at its least (100 ms) a loaded machine may
    // close a connection before it read the request: asked again then.
    let mut ready = String::new();
    for _ in 0..50 {
        ready = readyz(d.http).await;
        if !ready.is_empty() {
            break;
        }
    }
    assert!(
        ready.starts_with("HTTP/1.1 200") || ready.starts_with("HTTP/1.1 503"),
        "{what}: /readyz answered {ready}"
    );
    assert!(ready.contains("\"faces\":[]"), "{what}: {ready}");
    let addresses = d.faces_addresses().await;
    if !d.config.modbus_tcp.enabled {
        assert!(addresses.modbus_tcp.is_none(), "{what}: Modbus TCP is off");
    }
    for (face, addr) in [
        ("Modbus TCP", addresses.modbus_tcp.or(addresses.modbus_tls)),
        ("Modbus/TCP Security", addresses.modbus_tls),
        ("OPC UA", addresses.opcua),
    ] {
        let addr = addr.unwrap_or_else(|| panic!("{what}: {face} did not start"));
        tokio::net::TcpStream::connect(addr)
            .await
            .unwrap_or_else(|e| panic!("{what}: {face} on {addr}: {e}"));
    }
    eventually(
        Duration::from_secs(10),
        &format!("{what}: MQTT connected"),
        || d.metrics.mqtt().link().connected.then_some(()),
    )
    .await;
    let crashed = d.metrics.face_health().states();
    assert!(crashed.is_empty(), "{what}: faces crashed: {crashed:?}");
    d.stop().await;
}
