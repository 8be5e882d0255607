//! The docs against the code, for the kinds of contradiction a newcomer
//! trips over: a metric the docs name that a fresh `/metrics` does not
//! have (until some first event), a metric listed in a table whose labels
//! or subject it does not share, a field table of the API holding what is
//! no field; a path the docs give that the package does not install or
//! that the unit makes read-only for what the daemon writes there; and an
//! adapter named by its plugging order where the README says to use
//! `/dev/serial/by-id/`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use crate::support::{FOUR_DRIVES, TestDaemon, bounded};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const UNIT: &str = include_str!("../../deploy/systemd/drivegate.service");
/// Where `cargo deb` installs the units of `systemd-units`: its
/// `dh_installsystemd` writes every `.service` under `lib/systemd/system/`
/// (`LIB_SYSTEMD_SYSTEM_DIR` in cargo-deb's `dh/dh_installsystemd.rs`).
const CARGO_DEB_UNIT_DIR: &str = "/lib/systemd/system/";

fn read(path: &str) -> String {
    std::fs::read_to_string(Path::new(ROOT).join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// Every user-facing text: the README, docs/*.md, the configurations, the
/// package's files, the Prometheus rules and the dashboard.
fn user_texts() -> Vec<(String, String)> {
    let mut files = vec![
        "README.md".to_string(),
        "config/drivegate.toml".to_string(),
        "config/default.toml".to_string(),
        "deploy/debian/drivegate.toml".to_string(),
        "deploy/debian/postinst".to_string(),
        "deploy/systemd/drivegate.service".to_string(),
        "deploy/prometheus/alerts.yml".to_string(),
        "deploy/grafana/drivegate.json".to_string(),
    ];
    let mut docs: Vec<String> = std::fs::read_dir(Path::new(ROOT).join("docs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".md"))
        .map(|n| format!("docs/{n}"))
        .collect();
    docs.sort();
    files.extend(docs);
    files
        .into_iter()
        .map(|f| (read(&f), f))
        .map(|(t, f)| (f, t))
        .collect()
}

/// The metric names `text` mentions (`drivegate_` and a letter, then
/// lowercase letters, digits and `_`), a histogram's `_bucket`, `_sum`
/// and `_count` put down to their family.
fn metric_names(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for (i, _) in text.match_indices("drivegate_") {
        if text[..i]
            .chars()
            .next_back()
            // Part of a longer name (a test's, `a_file_drivegate_may_...`).
            .is_some_and(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/' || c == '.')
        {
            continue;
        }
        let name: String = text[i..]
            .chars()
            .take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_')
            .collect();
        let after = text[i + name.len()..].chars().next();
        if !name["drivegate_".len()..].starts_with(|c: char| c.is_ascii_lowercase())
            || name.ends_with('_')
            || after == Some('*')
        {
            continue;
        }
        let family = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|s| name.strip_suffix(s))
            .unwrap_or(&name);
        out.insert(family.to_string());
    }
    out
}

/// The families of a `/metrics` text, each with the label names of each
/// of its samples.
fn families(text: &str) -> BTreeMap<String, Vec<BTreeSet<String>>> {
    let mut out: BTreeMap<String, Vec<BTreeSet<String>>> = BTreeMap::new();
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("# TYPE ") {
            let name = rest.split(' ').next().unwrap().to_string();
            out.entry(name).or_default();
            continue;
        }
        if line.starts_with('#') || line.is_empty() {
            continue;
        }
        let (name, labels) = match line.split_once('{') {
            Some((name, rest)) => (name, rest.split_once('}').unwrap().0),
            None => (line.split(' ').next().unwrap(), ""),
        };
        let labels: BTreeSet<String> = labels
            .split(',')
            .filter_map(|pair| Some(pair.split_once('=')?.0.to_string()))
            .filter(|l| l != "le")
            .collect();
        let family = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|s| name.strip_suffix(s))
            .filter(|f| out.contains_key(*f))
            .unwrap_or(name);
        out.entry(family.to_string()).or_default().push(labels);
    }
    out
}

/// The metric tables of `docs/operations.md`'s "Metrics": each table's
/// title (its `###` heading, or the bold words that introduce it) with
/// every metric of its rows and the row's text.
fn metric_tables(guide: &str) -> Vec<(String, String, String)> {
    let start = guide.find("\n## Metrics").expect("a Metrics chapter");
    let end = guide[start + 1..]
        .find("\n## ")
        .map_or(guide.len(), |e| start + 1 + e);
    let mut title = String::new();
    let mut rows = Vec::new();
    for line in guide[start..end].lines() {
        if let Some(heading) = line.strip_prefix("### ") {
            title = heading.trim().to_string();
        } else if let Some(bold) = line.strip_prefix("**") {
            title = bold
                .split("**")
                .next()
                .unwrap()
                .trim_end_matches('.')
                .to_string();
        } else if line.starts_with("| `drivegate_") {
            let cell = line.split(" | ").next().unwrap();
            for name in metric_names(cell) {
                rows.push((title.clone(), name, line.to_string()));
            }
        }
    }
    rows
}

/// What the metrics of a table share: the labels every series carries
/// (as its introduction says) and the prefixes of their names.
fn table_rule(title: &str) -> Option<(&'static [&'static str], &'static [&'static str])> {
    Some(match title {
        "Drives" => (&["bus", "unit", "name"], &["drivegate_drive_"]),
        "Buses" => (&["bus"], &["drivegate_bus_", "drivegate_sim_"]),
        "Per-attempt wire counters" => (&["bus", "unit"], &["drivegate_bus_wire_"]),
        "The bus monitor and the scope" => (&["bus"], &["drivegate_monitor_", "drivegate_scope_"]),
        "Network faces and process" => (
            &[],
            &[
                "drivegate_http_",
                "drivegate_websocket_",
                "drivegate_modbus_tcp_",
                "drivegate_tls_",
                "drivegate_face_",
                "drivegate_build_",
                "drivegate_process_",
            ],
        ),
        "Safety, configuration, alarms and trends" => (
            &[],
            &[
                "drivegate_restart_",
                "drivegate_safety_",
                "drivegate_config_",
                "drivegate_alarm",
                "drivegate_history_",
            ],
        ),
        "Connections" => (&[], &["drivegate_connections"]),
        "MQTT" => (&[], &["drivegate_mqtt_"]),
        "OPC UA" => (&[], &["drivegate_opcua_"]),
        _ => return None,
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_documented_metric_is_in_a_fresh_scrape_in_the_table_of_its_kind() {
    bounded(std::time::Duration::from_secs(60), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        // The daemon's first scrape: nothing has happened but the polls.
        let text = reqwest::get(d.url("/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        d.stop().await;
        let exported = families(&text);
        let guide = read("docs/operations.md");
        let tables = metric_tables(&guide);

        // Documented anywhere, present from the first scrape; a metric
        // that cannot honestly be 0 before its first event says so in its
        // row ("no series before ...").
        let mut absent = Vec::new();
        for (file, text) in user_texts() {
            for name in metric_names(&text) {
                if exported.contains_key(&name) {
                    continue;
                }
                let said = tables
                    .iter()
                    .any(|(_, n, row)| *n == name && row.contains("no series before"));
                if !said {
                    absent.push(format!("{name} ({file})"));
                }
            }
        }
        absent.dedup();
        assert!(
            absent.is_empty(),
            "documented but absent from a fresh /metrics: {absent:?}"
        );

        // Each in the table whose labels and subject it shares.
        let mut misplaced = Vec::new();
        for (title, name, _) in &tables {
            let Some((labels, prefixes)) = table_rule(title) else {
                panic!("a metrics table this test has no rule for: {title:?}");
            };
            if !prefixes.iter().any(|p| name.starts_with(p)) {
                misplaced.push(format!("{name} in \"{title}\""));
                continue;
            }
            for series in exported.get(name).into_iter().flatten() {
                if let Some(missing) = labels.iter().find(|l| !series.contains(**l)) {
                    misplaced.push(format!(
                        "{name} in \"{title}\": a series without `{missing}` ({series:?})"
                    ));
                    break;
                }
            }
        }
        assert!(misplaced.is_empty(), "{misplaced:#?}");
        // And every family exported is in one table.
        let listed: BTreeSet<&String> = tables.iter().map(|(_, n, _)| n).collect();
        let unlisted: Vec<&String> = exported.keys().filter(|n| !listed.contains(n)).collect();
        assert!(
            unlisted.is_empty(),
            "exported, in no table of docs/operations.md: {unlisted:?}"
        );
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_apis_status_field_table_holds_the_status_fields_and_nothing_else() {
    bounded(std::time::Duration::from_secs(60), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let status: serde_json::Value = reqwest::get(d.url("/api/v1/drives/conveyor/status"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        d.stop().await;
        let keys: BTreeSet<String> = status
            .as_object()
            .unwrap_or_else(|| panic!("{status}"))
            .keys()
            .cloned()
            .collect();
        let api = read("docs/api.md");
        let section = &api[api.find("\n### Status\n").expect("### Status")..];
        // The paragraph before the table names what the answer holds
        // beside the status block; the table holds the block's fields.
        let prose: BTreeSet<&str> = section[..section.find("| field |").unwrap()]
            .split(|c: char| !(c.is_ascii_lowercase() || c == '_'))
            .collect();
        let fields: BTreeSet<String> = keys
            .iter()
            .filter(|k| !prose.contains(k.as_str()))
            .cloned()
            .collect();
        let table: Vec<&str> = section
            .lines()
            .skip_while(|l| !l.starts_with("| field |"))
            .skip(2)
            .take_while(|l| l.starts_with('|'))
            .collect();
        let mut documented = BTreeSet::new();
        for row in &table {
            let cell = row.trim_start_matches("| ").split(" | ").next().unwrap();
            for name in cell.split(", ") {
                documented.insert(name.trim_matches('`').to_string());
            }
        }
        assert_eq!(
            documented, fields,
            "docs/api.md's status table against GET .../status"
        );
    })
    .await;
}

/// The absolute paths the package installs: its assets, its
/// configuration files and its unit, as `cargo deb` takes them from
/// Cargo.toml.
fn installed() -> Vec<String> {
    let manifest: toml::Table = read("Cargo.toml").parse().unwrap();
    let deb = manifest["package"]["metadata"]["deb"].as_table().unwrap();
    let mut paths = Vec::new();
    for asset in deb["assets"].as_array().unwrap() {
        let a = asset.as_array().unwrap();
        let (source, dest) = (a[0].as_str().unwrap(), a[1].as_str().unwrap());
        let file = Path::new(source).file_name().unwrap().to_string_lossy();
        paths.push(if dest.ends_with('/') {
            format!("/{dest}{file}")
        } else {
            format!("/{dest}")
        });
    }
    for conf in deb["conf-files"].as_array().unwrap() {
        paths.push(conf.as_str().unwrap().to_string());
    }
    let unit = deb["systemd-units"]["unit-name"].as_str().unwrap();
    paths.push(format!("{CARGO_DEB_UNIT_DIR}{unit}.service"));
    paths
}

/// A directive's values in the unit (every line of it).
fn directive<'a>(name: &str) -> Vec<&'a str> {
    UNIT.lines()
        .filter_map(|l| l.strip_prefix(&format!("{name}=")))
        .flat_map(str::split_whitespace)
        .collect()
}

#[test]
fn the_paths_the_docs_give_are_those_the_package_installs_and_the_unit_allows() {
    let installed = installed();
    let is_installed = |path: &str| {
        installed
            .iter()
            .any(|p| p == path || (path.ends_with('/') && p.starts_with(path)))
    };
    // The guide's table of what the package installs.
    let guide = read("docs/operations.md");
    let table = &guide[guide.find("The package installs:").unwrap()..];
    let rows: Vec<&str> = table
        .lines()
        .skip(4)
        .take_while(|l| l.starts_with('|'))
        .collect();
    assert!(rows.len() >= 5, "{rows:?}");
    for row in rows {
        let path = row.split('`').nth(1).unwrap();
        assert!(
            is_installed(path),
            "docs/operations.md says the package installs {path}; it installs {installed:?}"
        );
    }
    // Wherever a text names the unit's file, it is where the package puts
    // it (or a copy an administrator makes in /etc).
    for (file, text) in user_texts() {
        for (i, _) in text.match_indices("systemd/system/drivegate.service") {
            let start = text[..i]
                .rfind(|c: char| c == '`' || c.is_whitespace())
                .map_or(0, |s| s + 1);
            let path = &text[start..i + "systemd/system/drivegate.service".len()];
            assert!(
                is_installed(path) || path.starts_with("/etc/systemd/system/"),
                "{file} names {path}"
            );
        }
    }
    // What the unit starts, reads and points at is installed.
    let exec = directive("ExecStart");
    assert!(is_installed(exec[0]), "ExecStart={}", exec[0]);
    let config = exec[exec.iter().position(|a| *a == "--config").unwrap() + 1];
    assert!(is_installed(config), "--config {config}");
    for doc in directive("Documentation") {
        let path = doc.strip_prefix("file:").unwrap_or(doc);
        assert!(
            !path.starts_with('/') || is_installed(path),
            "Documentation={doc}"
        );
    }
    // What the daemon writes is writable under ProtectSystem=strict: the
    // configuration's directory (the console's "add to configuration"
    // writes a new file there and renames it over the old one) and the
    // state directory (its journals).
    assert!(directive("ProtectSystem").contains(&"strict"));
    let config_dir = Path::new(config).parent().unwrap().to_str().unwrap();
    assert!(
        directive("ReadWritePaths").contains(&config_dir),
        "the unit keeps {config_dir} read-only, where the console writes the configuration"
    );
    assert_eq!(directive("StateDirectory"), ["drivegate"]);
    // postinst lets the service's group write there.
    let postinst = read("deploy/debian/postinst");
    assert!(
        postinst.contains(&format!("chown root:drivegate {config_dir}\n"))
            && postinst.contains(&format!("chown root:drivegate {config}\n")),
        "{postinst}"
    );
}

#[test]
fn no_text_tells_to_name_an_adapter_by_its_plugging_order() {
    // The README: "Use the adapter's stable name, not /dev/ttyUSB0".
    let mut texts = user_texts();
    let mut sources = Vec::new();
    collect(&Path::new(ROOT).join("src"), "rs", &mut sources);
    collect(&Path::new(ROOT).join("web/console"), "js", &mut sources);
    for path in sources {
        let mut text = std::fs::read_to_string(&path).unwrap();
        // A module's unit tests may use any name.
        if let Some(tests) = text.find("#[cfg(test)]") {
            text.truncate(tests);
        }
        if path.file_name().is_some_and(|n| n == "tests.rs") {
            continue;
        }
        texts.push((path.display().to_string(), text));
    }
    let mut found = Vec::new();
    for (file, text) in &texts {
        for line in text.lines() {
            let told = ["--port /dev/tty", "port = \"/dev/tty", "port = '/dev/tty"]
                .iter()
                .any(|p| line.contains(p));
            if told {
                found.push(format!("{file}: {}", line.trim()));
            }
        }
    }
    assert!(found.is_empty(), "{found:#?}");
}

fn collect(dir: &Path, ext: &str, out: &mut Vec<std::path::PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            collect(&path, ext, out);
        } else if path.extension().is_some_and(|e| e == ext) {
            out.push(path);
        }
    }
}

#[test]
fn the_readme_shows_both_quick_start_commands_in_command_blocks() {
    let readme = read("README.md");
    let start = readme.find("## Try it").expect("a quick start");
    let end = readme[start + 3..]
        .find("\n## ")
        .map_or(readme.len(), |e| start + 3 + e);
    let mut commands = Vec::new();
    let mut block = false;
    for line in readme[start..end].lines() {
        if line.starts_with("```") {
            block = !block && line == "```sh";
        } else if block {
            commands.push(line.split('#').next().unwrap().trim().to_string());
        }
    }
    for wanted in ["cargo run --release -- serve", "scripts/test"] {
        assert!(
            commands.iter().any(|c| c == wanted),
            "the README's quick start has no command block with `{wanted}`: {commands:?}"
        );
    }
}

/// A heading's anchor as GitHub makes it: lower case, punctuation dropped
/// (but `-` and `_`), spaces as `-`.
fn anchor_of(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, ' ' | '-' | '_'))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks).
fn anchors(text: &str) -> BTreeSet<String> {
    let mut block = false;
    let mut out = BTreeSet::new();
    for line in text.lines() {
        if line.starts_with("```") {
            block = !block;
        } else if !block && line.starts_with('#') {
            out.insert(anchor_of(line.trim_start_matches('#')));
        }
    }
    out
}

/// Every link from one document to another (README, docs/, tests/,
/// vendor/) leads to a file that exists and, when it names a heading, to
/// a heading that exists: a reader sent to "the benchmark" finds it.
#[test]
fn every_link_between_the_docs_leads_to_a_file_and_a_heading_that_exist() {
    let mut files: Vec<String> = vec![
        "README.md".into(),
        "tests/README.md".into(),
        "vendor/README.md".into(),
    ];
    files.extend(
        user_texts()
            .into_iter()
            .map(|(f, _)| f)
            .filter(|f| f.starts_with("docs/")),
    );
    let mut checked = 0;
    let mut broken = Vec::new();
    for file in &files {
        let text = read(file);
        let dir = Path::new(file).parent().unwrap_or(Path::new(""));
        let mut block = false;
        for line in text.lines() {
            if line.starts_with("```") {
                block = !block;
                continue;
            }
            if block {
                continue;
            }
            let mut rest = line;
            while let Some(at) = rest.find("](") {
                let after = &rest[at + 2..];
                let Some(end) = after.find(')') else { break };
                let target = &after[..end];
                rest = &after[end..];
                if target.contains("://") || target.starts_with("mailto:") {
                    continue;
                }
                let (path, anchor) = target.split_once('#').unwrap_or((target, ""));
                let linked = if path.is_empty() {
                    file.clone()
                } else {
                    dir.join(path).to_string_lossy().into_owned()
                };
                checked += 1;
                let full = Path::new(ROOT).join(&linked);
                if !full.exists() {
                    broken.push(format!("{file}: {target} (no file {linked})"));
                    continue;
                }
                if !anchor.is_empty()
                    && linked.ends_with(".md")
                    && !anchors(&read(&linked)).contains(anchor)
                {
                    broken.push(format!(
                        "{file}: {target} (no heading #{anchor} in {linked})"
                    ));
                }
            }
        }
    }
    assert!(
        checked > 20,
        "only {checked} links found: the reader is wrong"
    );
    assert!(
        broken.is_empty(),
        "links that lead nowhere:\n{}",
        broken.join("\n")
    );
}
