//! `config/drivegate.toml`, the reference of every key, against the code:
//! it parses with the daemon's own loader, every value it shows as a
//! default is the code's default, and every key the code accepts is in it.
//!
//! The accepted keys come from the configuration types themselves: every
//! table is read with `deny_unknown_fields`, so a key the code does not
//! know is refused with the list of those it does ("expected one of ...").
//! The test puts such a key into each table of the reference and reads the
//! list back: a key added to the code and forgotten in the file fails here.

use std::path::Path;

use drivegate::config::Config;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const UNKNOWN: &str = "zz_not_a_key";

fn reference() -> (String, toml::Table) {
    let text = std::fs::read_to_string(Path::new(ROOT).join("config/drivegate.toml")).unwrap();
    let table = text.parse().unwrap();
    (text, table)
}

/// The keys the code accepts in the table at `path` of `doc`: the list
/// in the refusal of an unknown key put there.
fn accepted_keys(doc: &toml::Table, path: &[&str]) -> Vec<String> {
    let mut doc = doc.clone();
    let mut table = &mut doc;
    for key in path {
        table = match table.get_mut(*key).unwrap() {
            toml::Value::Table(t) => t,
            toml::Value::Array(a) => a[0].as_table_mut().unwrap(),
            other => panic!("{path:?}: {other:?} is no table"),
        };
    }
    table.insert(UNKNOWN.to_string(), toml::Value::Integer(0));
    let text = toml::to_string(&doc).unwrap();
    let error = Config::parse(&text, "reference")
        .err()
        .unwrap_or_else(|| panic!("[{}] takes any key", path.join(".")))
        .to_string();
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

/// True when the reference shows `key`: set, commented out as an example,
/// or as a table of its own.
fn shown(text: &str, path: &[&str], key: &str) -> bool {
    let full = [path, &[key]].concat().join(".");
    text.lines().map(str::trim).any(|line| {
        let line = line.trim_start_matches('#').trim();
        line.starts_with(&format!("{key} ="))
            || line == format!("[{full}]")
            || line == format!("[[{full}]]")
    })
}

#[test]
fn every_key_the_code_accepts_is_in_the_reference() {
    let (text, doc) = reference();
    // Every table the code reads, the ones only shown commented out given
    // a valid entry first.
    let mut doc_full = doc.clone();
    let extra: toml::Table = r#"
[[http.token]]
name = "x"
role = "viewer"
sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
[[modbus_tcp.polled_copy]]
bus = "line1"
max_age_ms = 250
"#
    .parse()
    .unwrap();
    for (section, value) in extra {
        let toml::Value::Table(items) = value else {
            unreachable!()
        };
        let into = doc_full[&section].as_table_mut().unwrap();
        for (key, v) in items {
            into.insert(key, v);
        }
    }
    let tables: &[&[&str]] = &[
        &[],
        &["http"],
        &["http", "token"],
        &["modbus_tcp"],
        &["modbus_tcp", "clients"],
        &["modbus_tcp", "unit_map"],
        &["modbus_tcp", "polled_copy"],
        &["log"],
        &["safety"],
        &["monitor"],
        &["scope"],
        &["history"],
        &["opcua"],
        &["bus"],
        &["bus", "rs485"],
        &["bus", "drive"],
    ];
    let mut missing = Vec::new();
    for path in tables {
        for key in accepted_keys(&doc_full, path) {
            if !shown(&text, path, &key) {
                missing.push([*path, &[key.as_str()]].concat().join("."));
            }
        }
    }
    // The simulator's tables are on the second bus.
    let mut sim_doc = doc_full.clone();
    let buses = sim_doc["bus"].as_array_mut().unwrap();
    let bench = buses.remove(1);
    buses.insert(0, bench);
    for path in [
        &["bus", "sim"][..],
        &["bus", "sim", "delivery"],
        &["bus", "sim", "faults"],
    ] {
        for key in accepted_keys(&sim_doc, path) {
            if !shown(&text, path, &key) {
                missing.push([path, &[key.as_str()]].concat().join("."));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "config/drivegate.toml does not show: {missing:?}"
    );
}

/// The configuration of a bus `line1` on the simulator, with `extra`
/// after it (appended, so the spans of what comes before do not move).
fn with(extra: &str) -> String {
    let base = "[[bus]]\nname = \"line1\"\nport = \"sim\"\n";
    let config =
        Config::parse(&format!("{base}{extra}"), "test").unwrap_or_else(|e| panic!("{extra}: {e}"));
    format!("{config:?}")
}

#[test]
fn every_value_the_reference_shows_is_the_default() {
    let (_, doc) = reference();
    let plain = with("");
    // A [bus.sim] section, even empty, is there: compare with it.
    let plain_sim = with("[bus.sim]\n");
    let mut differ = Vec::new();
    let mut check = |table: &str, key: &str, value: &toml::Value| {
        if value.is_table()
            || value
                .as_array()
                .is_some_and(|a| a.iter().any(|v| v.is_table()))
        {
            return;
        }
        let set = with(&format!("[{table}]\n{key} = {value}\n"));
        let base = if table.starts_with("bus.sim") {
            &plain_sim
        } else {
            &plain
        };
        if &set != base {
            differ.push(format!("[{table}] {key} = {value}"));
        }
    };
    for section in [
        "http",
        "modbus_tcp",
        "log",
        "safety",
        "monitor",
        "scope",
        "history",
    ] {
        for (key, value) in doc[section].as_table().unwrap() {
            check(section, key, value);
        }
    }
    // Examples, not defaults: which bus and drives, and on the simulated
    // bench its seed.
    let buses = doc["bus"].as_array().unwrap();
    let mut bus_differ = Vec::new();
    for (key, value) in buses[0].as_table().unwrap() {
        if !["name", "port"].contains(&key.as_str()) {
            // Keys of the bus itself go right after its port.
            if !value.is_table()
                && !value.is_array()
                && with(&format!("{key} = {value}\n")) != plain
            {
                bus_differ.push(format!("[[bus]] {key} = {value}"));
            }
        }
    }
    for (key, value) in buses[0]["rs485"].as_table().unwrap() {
        check("bus.rs485", key, value);
    }
    let sim = buses[1]["sim"].as_table().unwrap();
    for (key, value) in sim {
        if key != "seed" {
            check("bus.sim", key, value);
        }
    }
    for sub in ["delivery", "faults"] {
        for (key, value) in sim[sub].as_table().unwrap() {
            check(&format!("bus.sim.{sub}"), key, value);
        }
    }
    differ.extend(bus_differ);
    // [opcua] is off unless there: its values against an empty [opcua].
    let plain_opcua = with("[opcua]\n");
    for (key, value) in doc["opcua"].as_table().unwrap() {
        if with(&format!("[opcua]\n{key} = {value}\n")) != plain_opcua {
            differ.push(format!("[opcua] {key} = {value}"));
        }
    }
    assert!(
        differ.is_empty(),
        "config/drivegate.toml shows values that are not the defaults: {differ:?}"
    );
}

#[test]
fn the_reference_parses_with_the_daemons_loader() {
    let config = Config::load(&Path::new(ROOT).join("config/drivegate.toml")).unwrap();
    assert_eq!(config.buses.len(), 2);
}

/// The `[mqtt]` section, shown commented out (MQTT is off unless
/// configured), uncommented.
fn mqtt_section(text: &str) -> String {
    let start = text.find("# [mqtt]\n").expect("the reference shows [mqtt]");
    text[start..]
        .lines()
        .take_while(|l| l.starts_with('#'))
        .map(|l| l.trim_start_matches('#').trim())
        // Tables and keys; the lines that only explain are left out.
        .filter(|l| {
            l.starts_with('[')
                || l.split_once(" =")
                    .is_some_and(|(k, _)| k.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_mqtt_section_shows_every_key_and_its_defaults() {
    let (text, doc) = reference();
    let section = mqtt_section(&text);
    let mut full = doc.clone();
    let mqtt: toml::Table = section.parse().unwrap_or_else(|e| panic!("{e}\n{section}"));
    full.insert("mqtt".to_string(), mqtt["mqtt"].clone());
    let mut missing = Vec::new();
    for path in [&["mqtt"][..], &["mqtt", "deadbands"]] {
        for key in accepted_keys(&full, path) {
            if !shown(&text, path, &key) {
                missing.push([path, &[key.as_str()]].concat().join("."));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "config/drivegate.toml does not show: {missing:?}"
    );
    // Examples, not defaults: where the broker is, who the node and its
    // host are (and the JSON topics' prefix, which follows the node), the
    // credentials and certificates.
    let examples = [
        "broker",
        "node_id",
        "topic_prefix",
        "primary_host_id",
        "username",
        "password_file",
        "ca",
        "client_cert",
        "client_key",
    ];
    let broker = "[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"\n";
    let plain = with(broker);
    let mut differ = Vec::new();
    for (key, value) in mqtt["mqtt"].as_table().unwrap() {
        if examples.contains(&key.as_str()) {
            continue;
        }
        if let Some(table) = value.as_table() {
            for (k, v) in table {
                if with(&format!("{broker}[mqtt.{key}]\n{k} = {v}\n")) != plain {
                    differ.push(format!("[mqtt.{key}] {k} = {v}"));
                }
            }
        } else if with(&format!("{broker}{key} = {value}\n")) != plain {
            differ.push(format!("[mqtt] {key} = {value}"));
        }
    }
    assert!(
        differ.is_empty(),
        "config/drivegate.toml shows [mqtt] values that are not the defaults: {differ:?}"
    );
}
