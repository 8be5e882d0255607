//! What changed between the running configuration and a new one: a pure
//! comparison of two checked [`Config`]s, which the daemon then applies
//! (`crate::reload`). Nothing here opens a port or touches a drive.
//!
//! The bus is the unit a change is applied to: a bus whose settings or
//! drive list changed is reopened (its thread and port, its simulator
//! with `port = "sim"`), the others keep running untouched. A drive keeps
//! its identity (and with it its lease and its stream subscriptions) as
//! long as its name, its bus and its unit stay the same; a drive renamed,
//! moved to another bus or given another unit is one drive removed and
//! one added, so a lease never follows a name to another motor.

use std::collections::BTreeSet;

use super::{BusConfig, Config, DriveConfig};

/// The changes from one configuration to the next, in the plant's terms.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Changes {
    /// Buses new in the file, by name.
    pub buses_added: Vec<String>,
    /// Buses gone from the file.
    pub buses_removed: Vec<String>,
    /// Buses kept whose port is reopened, each with why ("port",
    /// "baud", "drives", ...).
    pub buses_reopened: Vec<(String, Vec<String>)>,
    /// Drives new in the file, by name.
    pub drives_added: Vec<String>,
    /// Drives gone from the file (or moved to another bus or unit: those
    /// are added again under the same name).
    pub drives_removed: Vec<String>,
    /// Drives kept whose settings (poll interval, gear ratio) changed.
    pub drives_changed: Vec<String>,
    /// Tokens added, removed or changed (role or secret).
    pub tokens_changed: usize,
    /// Listeners to reopen: `http`, `modbus_tcp`, `modbus_tls`.
    pub listeners_reopened: Vec<&'static str>,
    /// Other sections whose new values apply at once, e.g. `[safety]`,
    /// `[modbus_tcp] clients`.
    pub sections: Vec<&'static str>,
    /// What changed but only applies at the next start.
    pub at_restart: Vec<&'static str>,
}

impl Changes {
    /// True when nothing changed.
    pub fn is_empty(&self) -> bool {
        *self == Changes::default()
    }

    /// The changes in words, one line each ("drives added: press").
    pub fn lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut list = |what: &str, names: &[String]| {
            if !names.is_empty() {
                out.push(format!("{what}: {}", names.join(", ")));
            }
        };
        list("drives added", &self.drives_added);
        list("drives removed", &self.drives_removed);
        list("drives changed", &self.drives_changed);
        list("buses added", &self.buses_added);
        list("buses removed", &self.buses_removed);
        for (bus, why) in &self.buses_reopened {
            out.push(format!("bus {bus} reopened ({} changed)", why.join(", ")));
        }
        if self.tokens_changed > 0 {
            out.push(format!("tokens changed: {}", self.tokens_changed));
        }
        for listener in &self.listeners_reopened {
            out.push(format!("listener reopened: {listener}"));
        }
        for section in &self.sections {
            out.push(format!("applied: {section}"));
        }
        for section in &self.at_restart {
            out.push(format!("applies at the next start: {section}"));
        }
        if out.is_empty() {
            out.push("no change".to_string());
        }
        out
    }
}

/// What changed from `old` to `new` (both already checked).
pub fn diff(old: &Config, new: &Config) -> Changes {
    let mut changes = Changes::default();
    buses(old, new, &mut changes);
    drives(old, new, &mut changes);
    changes.tokens_changed = tokens_changed(old, new);
    listeners(old, new, &mut changes);
    if old.safety != new.safety {
        changes.sections.push("[safety]");
    }
    let clients = |c: &Config| {
        (
            c.modbus_tcp.allowed_networks.clone(),
            c.modbus_tcp.clients.clone(),
            c.modbus_tcp.read_only,
            c.modbus_tcp.broadcast_reply,
            c.modbus_tcp.unit_map.clone(),
            c.modbus_tcp.polled_copy.clone(),
        )
    };
    if clients(old) != clients(new) {
        changes.sections.push("[modbus_tcp] clients and units");
    }
    if old.scope != new.scope {
        changes.sections.push("[scope]");
    }
    if old.monitor != new.monitor {
        changes.sections.push("[monitor]");
    }
    if old.log != new.log {
        changes.at_restart.push("[log]");
    }
    changes
}

/// Buses added, removed, and reopened with why. A change of `[scope]` or
/// `[monitor]` reopens every bus: their settings size what each bus keeps.
fn buses(old: &Config, new: &Config, changes: &mut Changes) {
    let observers_changed = old.scope != new.scope || old.monitor != new.monitor;
    for bus in &new.buses {
        match old.buses.iter().find(|b| b.name() == bus.name()) {
            None => changes.buses_added.push(bus.name().to_string()),
            Some(before) => {
                let mut why = bus_differences(before, bus);
                if observers_changed {
                    why.push("[scope] or [monitor]".to_string());
                }
                if !why.is_empty() {
                    changes.buses_reopened.push((bus.name().to_string(), why));
                }
            }
        }
    }
    for bus in &old.buses {
        if !new.buses.iter().any(|b| b.name() == bus.name()) {
            changes.buses_removed.push(bus.name().to_string());
        }
    }
}

/// The keys of a bus that differ, by name.
fn bus_differences(a: &BusConfig, b: &BusConfig) -> Vec<String> {
    let mut why = Vec::new();
    let mut key = |name: &str, differ: bool| {
        if differ {
            why.push(name.to_string());
        }
    };
    key("port", a.port != b.port);
    key("baud", a.baud != b.baud);
    key(
        "timing",
        (
            a.response_timeout_ms,
            a.retries,
            a.guard_ms,
            a.broadcast_delay_ms,
        ) != (
            b.response_timeout_ms,
            b.retries,
            b.guard_ms,
            b.broadcast_delay_ms,
        ),
    );
    key("poll rates", a.poll_interval_ms != b.poll_interval_ms);
    key(
        "offline detection",
        (
            a.offline_after,
            a.offline_backoff_ms,
            a.offline_backoff_max_ms,
        ) != (
            b.offline_after,
            b.offline_backoff_ms,
            b.offline_backoff_max_ms,
        ),
    );
    key(
        "queue",
        (
            a.queue_capacity,
            a.queue_per_client,
            a.queue_timeout_ms,
            a.poll_share,
        ) != (
            b.queue_capacity,
            b.queue_per_client,
            b.queue_timeout_ms,
            b.poll_share,
        ),
    );
    key("rs485", a.rs485 != b.rs485);
    key("sim", a.sim != b.sim);
    key("drives", a.drives != b.drives);
    why
}

/// A drive's identity: the same name on the same bus at the same unit.
fn identity<'a>(bus: &'a BusConfig, d: &'a DriveConfig) -> (&'a str, &'a str, u8) {
    (d.name(), bus.name(), d.unit())
}

fn all_drives(config: &Config) -> Vec<(&BusConfig, &DriveConfig)> {
    config
        .buses
        .iter()
        .flat_map(|b| b.drives.iter().map(move |d| (b, d)))
        .collect()
}

fn drives(old: &Config, new: &Config, changes: &mut Changes) {
    let before = all_drives(old);
    let after = all_drives(new);
    for &(bus, d) in &after {
        match before
            .iter()
            .find(|(b, o)| identity(b, o) == identity(bus, d))
        {
            None => changes.drives_added.push(d.name().to_string()),
            Some((_, o)) if *o != d => changes.drives_changed.push(d.name().to_string()),
            Some(_) => {}
        }
    }
    for &(bus, d) in &before {
        if !after
            .iter()
            .any(|(b, n)| identity(b, n) == identity(bus, d))
        {
            changes.drives_removed.push(d.name().to_string());
        }
    }
}

/// Tokens whose name is new or gone, or whose role or secret changed.
fn tokens_changed(old: &Config, new: &Config) -> usize {
    let names: BTreeSet<&str> = old
        .http
        .tokens
        .iter()
        .chain(&new.http.tokens)
        .map(|t| t.name.as_str())
        .collect();
    names
        .into_iter()
        .filter(|name| {
            let a = old.http.tokens.iter().find(|t| t.name == *name);
            let b = new.http.tokens.iter().find(|t| t.name == *name);
            a != b
        })
        .count()
}

/// Listeners whose address or certificates changed. The HTTP listener is
/// also reopened when tokens appear or all go (without tokens it listens on
/// loopback only), and for its connection limits.
fn listeners(old: &Config, new: &Config, changes: &mut Changes) {
    let http = |c: &Config| {
        let mut h = c.http.clone();
        h.tokens.clear();
        (h, c.http.tokens.is_empty())
    };
    if http(old) != http(new) {
        changes.listeners_reopened.push("http");
    }
    let tcp = |c: &Config| {
        (
            c.modbus_tcp.enabled,
            c.modbus_tcp.listen,
            c.modbus_tcp.max_connections,
            c.modbus_tcp.idle_timeout_ms,
            c.modbus_tcp.max_pipelined,
        )
    };
    if tcp(old) != tcp(new) {
        changes.listeners_reopened.push("modbus_tcp");
    }
    if old.modbus_tcp.tls != new.modbus_tcp.tls {
        changes.listeners_reopened.push("modbus_tls");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Config {
        match Config::parse(text, "test.toml") {
            Ok(c) => c,
            Err(e) => panic!("{e}"),
        }
    }

    const BASE: &str = r#"
[http]
listen = "127.0.0.1:8080"
[[http.token]]
name = "panel"
role = "operator"
sha256 = "0000000000000000000000000000000000000000000000000000000000000000"
[modbus_tcp]
listen = "127.0.0.1:5020"
[[bus]]
name = "line1"
port = "sim"
[[bus.drive]]
unit = 1
name = "conveyor"
[[bus.drive]]
unit = 2
name = "mixer"
[[bus]]
name = "line2"
port = "sim"
[[bus.drive]]
unit = 1
name = "press"
"#;

    fn changed(from: &str, to: &str) -> Changes {
        diff(&parse(BASE), &parse(&BASE.replace(from, to)))
    }

    #[test]
    fn the_same_file_changes_nothing() {
        let c = diff(&parse(BASE), &parse(BASE));
        assert!(c.is_empty(), "{c:?}");
        assert_eq!(c.lines(), vec!["no change"]);
    }

    #[test]
    fn comments_and_moved_lines_change_nothing() {
        let moved = format!(
            "# a comment\n\n{}",
            BASE.replace("unit = 1\nname = \"press\"", "name = \"press\"\nunit = 1")
        );
        assert!(diff(&parse(BASE), &parse(&moved)).is_empty());
    }

    #[test]
    fn a_drive_added_reopens_only_its_bus() {
        let c = changed(
            "name = \"press\"\n",
            "name = \"press\"\n[[bus.drive]]\nunit = 2\nname = \"saw\"\n",
        );
        assert_eq!(c.drives_added, vec!["saw"]);
        assert!(c.drives_removed.is_empty() && c.drives_changed.is_empty());
        assert_eq!(
            c.buses_reopened,
            vec![("line2".to_string(), vec!["drives".to_string()])]
        );
        assert!(c.buses_added.is_empty() && c.buses_removed.is_empty());
        assert!(c.listeners_reopened.is_empty() && c.sections.is_empty());
        assert_eq!(
            c.lines(),
            vec!["drives added: saw", "bus line2 reopened (drives changed)"]
        );
    }

    #[test]
    fn a_drive_removed() {
        let c = changed("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "");
        assert_eq!(c.drives_removed, vec!["mixer"]);
        assert_eq!(c.buses_reopened[0].0, "line1");
    }

    #[test]
    fn a_drive_given_another_unit_is_removed_and_added() {
        let c = changed("unit = 2\nname = \"mixer\"", "unit = 3\nname = \"mixer\"");
        assert_eq!(c.drives_removed, vec!["mixer"]);
        assert_eq!(c.drives_added, vec!["mixer"]);
        assert!(c.drives_changed.is_empty());
    }

    #[test]
    fn a_drive_moved_to_another_bus_is_removed_and_added() {
        let c = changed("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "");
        let c2 = diff(
            &parse(BASE),
            &parse(
                &BASE
                    .replace("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "")
                    .replace(
                        "name = \"press\"\n",
                        "name = \"press\"\n[[bus.drive]]\nunit = 2\nname = \"mixer\"\n",
                    ),
            ),
        );
        assert_eq!(c.drives_removed, vec!["mixer"]);
        assert_eq!(c2.drives_removed, vec!["mixer"]);
        assert_eq!(c2.drives_added, vec!["mixer"]);
        let reopened: Vec<&str> = c2.buses_reopened.iter().map(|(b, _)| b.as_str()).collect();
        assert_eq!(reopened, vec!["line1", "line2"]);
    }

    #[test]
    fn a_drive_poll_rate_is_a_change_of_the_drive() {
        let c = changed(
            "unit = 1\nname = \"press\"",
            "unit = 1\nname = \"press\"\npoll_interval_ms = 100",
        );
        assert_eq!(c.drives_changed, vec!["press"]);
        assert!(c.drives_added.is_empty() && c.drives_removed.is_empty());
    }

    #[test]
    fn a_bus_port_or_baud_reopens_that_bus_only() {
        let c = changed(
            "name = \"line2\"\nport = \"sim\"",
            "name = \"line2\"\nport = \"sim\"\nbaud = 57600\npoll_interval_ms = 20",
        );
        assert_eq!(
            c.buses_reopened,
            vec![(
                "line2".to_string(),
                vec!["baud".to_string(), "poll rates".to_string()]
            )]
        );
        assert!(c.drives_added.is_empty() && c.drives_changed.is_empty());
    }

    #[test]
    fn buses_added_and_removed_with_their_drives() {
        let c = changed("name = \"line2\"", "name = \"line3\"");
        assert_eq!(c.buses_added, vec!["line3"]);
        assert_eq!(c.buses_removed, vec!["line2"]);
        assert_eq!(c.drives_removed, vec!["press"]);
        assert_eq!(c.drives_added, vec!["press"]);
        assert!(c.buses_reopened.is_empty());
    }

    #[test]
    fn tokens_are_counted_and_need_no_listener() {
        let c = changed(
            "[modbus_tcp]",
            "[[http.token]]\nname = \"scada\"\nrole = \"viewer\"\nsha256 = \"1111111111111111111111111111111111111111111111111111111111111111\"\n[modbus_tcp]",
        );
        assert_eq!(c.tokens_changed, 1);
        assert!(c.listeners_reopened.is_empty(), "{c:?}");
        let c = changed("role = \"operator\"", "role = \"admin\"");
        assert_eq!(c.tokens_changed, 1);
        assert_eq!(c.lines(), vec!["tokens changed: 1"]);
    }

    #[test]
    fn the_last_token_gone_reopens_http_on_loopback() {
        let c = diff(
            &parse(BASE),
            &parse(&BASE.replace(
                "[[http.token]]\nname = \"panel\"\nrole = \"operator\"\nsha256 = \"0000000000000000000000000000000000000000000000000000000000000000\"\n",
                "",
            )),
        );
        assert_eq!(c.tokens_changed, 1);
        assert_eq!(c.listeners_reopened, vec!["http"]);
    }

    #[test]
    fn listen_addresses_reopen_their_listener() {
        let c = changed("127.0.0.1:8080", "127.0.0.1:8081");
        assert_eq!(c.listeners_reopened, vec!["http"]);
        let c = changed("127.0.0.1:5020", "127.0.0.1:5021");
        assert_eq!(c.listeners_reopened, vec!["modbus_tcp"]);
        assert!(c.buses_reopened.is_empty());
    }

    #[test]
    fn safety_clients_scope_and_log() {
        let c = changed("[http]", "[safety]\nlease_max_ms = 20000\n[http]");
        assert_eq!(c.sections, vec!["[safety]"]);
        assert!(c.buses_reopened.is_empty());
        let c = changed(
            "listen = \"127.0.0.1:5020\"",
            "listen = \"127.0.0.1:5020\"\nread_only = true",
        );
        assert_eq!(c.sections, vec!["[modbus_tcp] clients and units"]);
        assert!(c.listeners_reopened.is_empty());
        let c = changed("[http]", "[scope]\nmax_samples = 1000\n[http]");
        assert_eq!(c.sections, vec!["[scope]"]);
        assert_eq!(
            c.buses_reopened.len(),
            2,
            "the scope's limits size every bus's slot"
        );
        let c = changed("[http]", "[log]\nformat = \"json\"\n[http]");
        assert_eq!(c.at_restart, vec!["[log]"]);
    }
}
