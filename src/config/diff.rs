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
//!
//! A face is restarted on its own when its section changes ([`Face`]): a
//! listener at its new address or with its new limits, the MQTT face with
//! its new broker. Every section of the file is compared ([`diff`] takes
//! the configuration apart field by field, so a section added to
//! [`Config`] does not compile until it is compared): a change is either
//! applied or reported as applying at the next start, never ignored.

use std::collections::BTreeSet;

use super::{BusConfig, Config, DriveConfig, ModbusTcpConfig, SafetyConfig};
use crate::listed::listed_enum;

listed_enum! {
    /// A face a reload restarts by itself when what it was started with
    /// changes; the buses, the drives and the other faces keep running.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Face {
        /// The HTTP listener (REST, WebSocket, metrics, the console).
        Http,
        /// The Modbus TCP listener.
        ModbusTcp,
        /// The Modbus/TCP Security listener (`[modbus_tcp.tls]`).
        ModbusTls,
        /// The MQTT face, a client of its broker.
        Mqtt,
        /// The OPC UA listener (`[opcua]`).
        OpcUa,
    }
}

impl Face {
    /// Its name in words, as the log and a reload's answer say it.
    pub fn name(self) -> &'static str {
        match self {
            Face::Http => "HTTP API listener",
            Face::ModbusTcp => "Modbus TCP listener",
            Face::ModbusTls => "Modbus/TCP Security listener",
            Face::Mqtt => "MQTT face",
            Face::OpcUa => "OPC UA listener",
        }
    }

    /// The section it is started from.
    pub fn section(self) -> &'static str {
        match self {
            Face::Http => "[http]",
            Face::ModbusTcp => "[modbus_tcp]",
            Face::ModbusTls => "[modbus_tcp.tls]",
            Face::Mqtt => "[mqtt]",
            Face::OpcUa => "[opcua]",
        }
    }

    /// True when what this face is started with differs between `old`
    /// and `new`, so that it must be restarted to follow the file.
    pub fn changed(self, old: &Config, new: &Config) -> bool {
        match self {
            // Everything of [http] but the tokens, which the listener
            // follows request by request; but with no token at all it
            // listens on loopback only, so their coming or going counts.
            Face::Http => {
                let http = |c: &Config| {
                    let mut h = c.http.clone();
                    h.tokens.clear();
                    (h, c.http.tokens.is_empty())
                };
                http(old) != http(new)
            }
            Face::ModbusTcp => {
                let tcp = |c: &ModbusTcpConfig| {
                    (
                        c.enabled,
                        c.listen,
                        c.max_connections,
                        c.per_address_limit(),
                        c.idle_timeout_ms,
                        c.max_pipelined,
                    )
                };
                tcp(&old.modbus_tcp) != tcp(&new.modbus_tcp)
            }
            // Its limits are the plain listener's; `read_only` makes every
            // client of it a viewer when it connects.
            Face::ModbusTls if old.modbus_tcp.tls.is_none() && new.modbus_tcp.tls.is_none() => {
                false
            }
            Face::ModbusTls => {
                let tls = |c: &ModbusTcpConfig| {
                    (
                        c.tls.clone(),
                        c.max_connections,
                        c.per_address_limit(),
                        c.idle_timeout_ms,
                        c.max_pipelined,
                        c.read_only,
                    )
                };
                tls(&old.modbus_tcp) != tls(&new.modbus_tcp)
            }
            // Its store of unpublished data is in the state directory.
            Face::Mqtt => {
                old.mqtt != new.mqtt
                    || (new.mqtt.is_some() && old.safety.state_dir != new.safety.state_dir)
            }
            // Its certificates are in the state directory unless its
            // pki_dir says; its users are the [[http.token]]s, which it
            // follows session by session.
            Face::OpcUa => {
                old.opcua != new.opcua
                    || (new.opcua.is_some() && old.safety.state_dir != new.safety.state_dir)
            }
        }
    }
}

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
    /// Faces to restart: listeners to reopen, the MQTT face.
    pub faces_restarted: Vec<Face>,
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
        for face in &self.faces_restarted {
            out.push(format!("restarted: {}", face.name()));
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
    // Every section, by name: a new one must be compared here to compile.
    let Config {
        http: _,
        modbus_tcp,
        mqtt: _,
        opcua: _,
        log,
        safety,
        monitor,
        scope,
        history,
        buses: _,
    } = new;
    let mut changes = Changes::default();
    buses(old, new, &mut changes);
    drives(old, new, &mut changes);
    changes.tokens_changed = tokens_changed(old, new);
    changes.faces_restarted = Face::ALL
        .into_iter()
        .filter(|face| face.changed(old, new))
        .collect();
    self::safety(&old.safety, safety, &mut changes);
    if clients(&old.modbus_tcp) != clients(modbus_tcp) {
        changes.sections.push("[modbus_tcp] clients and units");
    }
    if old.scope != *scope {
        changes.sections.push("[scope]");
    }
    if old.monitor != *monitor {
        changes.sections.push("[monitor]");
    }
    if old.history != *history {
        // Each drive's rings are sized once, at start-up.
        changes.at_restart.push("[history]");
    }
    if old.log != *log {
        changes.at_restart.push("[log]");
    }
    changes
}

/// What of `[modbus_tcp]` the Modbus TCP faces follow request by request
/// and connection by connection; the rest is their listeners' (`Face`).
fn clients(c: &ModbusTcpConfig) -> impl PartialEq + use<> {
    let ModbusTcpConfig {
        enabled: _,
        listen: _,
        max_connections: _,
        max_connections_per_address: _,
        idle_timeout_ms: _,
        max_pipelined: _,
        tls: _,
        allowed_networks,
        clients,
        read_only,
        broadcast_reply,
        unit_map,
        polled_copy,
        raw_functions,
    } = c.clone();
    (
        allowed_networks,
        clients,
        read_only,
        broadcast_reply,
        unit_map,
        polled_copy,
        raw_functions,
    )
}

/// `[safety]`: the lease settings and the stop actions apply at once (the
/// core reads them at each lease and at the stop); where the journal is
/// kept, the size of the alarm list and what a start does with an
/// unreadable journal are read once, at start-up.
fn safety(old: &SafetyConfig, new: &SafetyConfig, changes: &mut Changes) {
    let SafetyConfig {
        on_shutdown,
        on_lease_expiry,
        jog_lease_ms,
        lease_min_ms,
        lease_max_ms,
        state_dir,
        on_unknown_state,
        alarms_kept,
    } = new.clone();
    if (
        old.on_shutdown,
        old.on_lease_expiry,
        old.jog_lease_ms,
        old.lease_min_ms,
        old.lease_max_ms,
    ) != (
        on_shutdown,
        on_lease_expiry,
        jog_lease_ms,
        lease_min_ms,
        lease_max_ms,
    ) {
        changes.sections.push("[safety]");
    }
    if (&old.state_dir, old.on_unknown_state, old.alarms_kept)
        != (&state_dir, on_unknown_state, alarms_kept)
    {
        changes
            .at_restart
            .push("[safety] state_dir, on_unknown_state and alarms_kept");
    }
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
    key("interframe", a.interframe != b.interframe);
    key(
        "reply timeout floor",
        a.reply_timeout_floor_ms != b.reply_timeout_floor_ms,
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
        assert!(c.faces_restarted.is_empty() && c.sections.is_empty());
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
    fn the_silence_before_requests_reopens_that_bus() {
        let c = changed(
            "name = \"line2\"\nport = \"sim\"",
            "name = \"line2\"\nport = \"sim\"\ninterframe = \"auto\"",
        );
        assert_eq!(
            c.buses_reopened,
            vec![("line2".to_string(), vec!["interframe".to_string()])]
        );
        let c = diff(
            &parse(&BASE.replace("port = \"sim\"", "port = \"sim\"\ninterframe = 400")),
            &parse(&BASE.replace("port = \"sim\"", "port = \"sim\"\ninterframe = 500")),
        );
        assert_eq!(c.buses_reopened.len(), 2, "{c:?}");
        // The default, written or not, is no change.
        assert!(
            changed("port = \"sim\"", "port = \"sim\"\ninterframe = \"spec\"")
                .buses_reopened
                .is_empty()
        );
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
        assert!(c.faces_restarted.is_empty(), "{c:?}");
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
        assert_eq!(c.faces_restarted, vec![Face::Http]);
    }

    #[test]
    fn listen_addresses_reopen_their_listener() {
        let c = changed("127.0.0.1:8080", "127.0.0.1:8081");
        assert_eq!(c.faces_restarted, vec![Face::Http]);
        assert_eq!(c.lines(), vec!["restarted: HTTP API listener"]);
        let c = changed("127.0.0.1:5020", "127.0.0.1:5021");
        assert_eq!(c.faces_restarted, vec![Face::ModbusTcp]);
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
        assert_eq!(
            c.faces_restarted,
            vec![],
            "no Modbus/TCP Security listener to follow it"
        );
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

    /// The reference configuration (`config/drivegate.toml`), every key at
    /// its default.
    fn reference() -> Config {
        parse(include_str!("../../config/drivegate.toml"))
    }

    /// `change` applied to the reference configuration.
    fn changed_by(change: impl FnOnce(&mut Config)) -> Changes {
        let old = reference();
        let mut new = old.clone();
        change(&mut new);
        assert_ne!(old, new, "the change changes nothing");
        diff(&old, &new)
    }

    /// The reference configuration with `text` added at its end.
    fn with(text: &str) -> Config {
        parse(&format!(
            "{}\n{text}",
            include_str!("../../config/drivegate.toml")
        ))
    }

    #[test]
    fn a_change_of_any_section_is_applied_or_said_to_wait_for_the_next_start() {
        use std::time::Duration;
        // (what, the change, what the diff must say)
        type Change = Box<dyn FnOnce(&mut Config)>;
        let cases: Vec<(&str, Change, Vec<&str>)> = vec![
            (
                "[http] listen",
                Box::new(|c| c.http.listen.set_port(18080)),
                vec!["restarted: HTTP API listener"],
            ),
            (
                "[http] a limit",
                Box::new(|c| c.http.idle_timeout += Duration::from_secs(1)),
                vec!["restarted: HTTP API listener"],
            ),
            (
                "[http] allowed_hosts",
                Box::new(|c| c.http.allowed_hosts.push("gateway.plant".into())),
                vec!["restarted: HTTP API listener"],
            ),
            (
                "[[http.token]]",
                Box::new(|c| {
                    c.http.tokens = with(
                        "[[http.token]]\nname = \"panel\"\nrole = \"viewer\"\nsha256 = \"2222222222222222222222222222222222222222222222222222222222222222\"",
                    )
                    .http
                    .tokens;
                }),
                vec!["tokens changed: 1"],
            ),
            (
                "[modbus_tcp] listen",
                Box::new(|c| c.modbus_tcp.listen.set_port(15020)),
                vec!["restarted: Modbus TCP listener"],
            ),
            (
                "[modbus_tcp] enabled",
                Box::new(|c| c.modbus_tcp.enabled = false),
                vec!["restarted: Modbus TCP listener"],
            ),
            (
                "[modbus_tcp] max_pipelined",
                Box::new(|c| c.modbus_tcp.max_pipelined += 1),
                vec!["restarted: Modbus TCP listener"],
            ),
            (
                "[modbus_tcp] max_connections_per_address",
                Box::new(|c| {
                    let three = crate::config::modbus_tcp::ConnectionCount(3);
                    c.modbus_tcp.max_connections_per_address =
                        Some(toml::Spanned::new(0..0, three));
                }),
                vec!["restarted: Modbus TCP listener"],
            ),
            (
                "[modbus_tcp] read_only",
                Box::new(|c| c.modbus_tcp.read_only = !c.modbus_tcp.read_only),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[modbus_tcp] allowed_networks",
                Box::new(|c| c.modbus_tcp.allowed_networks = Some(Vec::new())),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[modbus_tcp] raw_functions",
                Box::new(|c| {
                    let vendor = crate::config::modbus_tcp::RawFunction::try_from(0x41);
                    c.modbus_tcp.raw_functions = vendor
                        .map(|f| vec![toml::Spanned::new(0..0, f)])
                        .unwrap_or_default();
                }),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[modbus_tcp] broadcast_reply",
                Box::new(|c| c.modbus_tcp.broadcast_reply = !c.modbus_tcp.broadcast_reply),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[[modbus_tcp.clients]]",
                Box::new(|c| {
                    c.modbus_tcp.clients.pop();
                }),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[[modbus_tcp.unit_map]]",
                Box::new(|c| {
                    c.modbus_tcp.unit_map.pop();
                }),
                vec!["applied: [modbus_tcp] clients and units"],
            ),
            (
                "[mqtt] added",
                Box::new(|c| {
                    c.mqtt = with("[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"").mqtt;
                }),
                vec!["restarted: MQTT face"],
            ),
            (
                "[log]",
                Box::new(|c| c.log.level = "debug".into()),
                vec!["applies at the next start: [log]"],
            ),
            (
                "[safety] on_shutdown",
                Box::new(|c| c.safety.on_shutdown = crate::config::StopAction::Brake),
                vec!["applied: [safety]"],
            ),
            (
                "[safety] lease_max_ms",
                Box::new(|c| c.safety.lease_max_ms += 1),
                vec!["applied: [safety]"],
            ),
            (
                "[safety] alarms_kept",
                Box::new(|c| c.safety.alarms_kept += 1),
                vec![
                    "applies at the next start: [safety] state_dir, on_unknown_state and alarms_kept",
                ],
            ),
            (
                "[safety] state_dir",
                Box::new(|c| c.safety.state_dir = Some("/var/lib/elsewhere".into())),
                vec![
                    "applies at the next start: [safety] state_dir, on_unknown_state and alarms_kept",
                ],
            ),
            (
                "[monitor]",
                Box::new(|c| c.monitor.ring_frames += 1),
                vec!["applied: [monitor]"],
            ),
            (
                "[scope]",
                Box::new(|c| c.scope.max_samples += 1),
                vec!["applied: [scope]"],
            ),
            (
                "[history]",
                Box::new(|c| c.history.minutes = 30),
                vec!["applies at the next start: [history]"],
            ),
            (
                "[[bus]] baud",
                Box::new(|c| c.buses[0].baud = 57600),
                vec!["bus "],
            ),
            (
                "[[bus]] added",
                Box::new(|c| {
                    c.buses = with("[[bus]]\nname = \"another\"\nport = \"sim\"").buses;
                }),
                vec!["buses added: another"],
            ),
            (
                "[[bus.drive]]",
                Box::new(|c| {
                    c.buses[0].drives.pop();
                }),
                vec!["drives removed: "],
            ),
        ];
        for (what, change, says) in cases {
            let c = changed_by(change);
            let lines = c.lines();
            for said in says {
                assert!(
                    lines.iter().any(|l| l.starts_with(said)),
                    "a change of {what} is not reported as {said:?}: {lines:?}"
                );
            }
        }
    }

    #[test]
    fn opcua_changes_restart_only_its_listener() {
        // The reference shows [opcua]; without it, no OPC UA.
        let mut old = reference();
        old.opcua = None;
        let new = reference();
        assert_eq!(diff(&old, &new).faces_restarted, vec![Face::OpcUa]);
        assert_eq!(diff(&new, &old).faces_restarted, vec![Face::OpcUa]);
        assert_eq!(diff(&old, &new).lines(), vec!["restarted: OPC UA listener"]);
        let mut longer = new.clone();
        if let Some(o) = longer.opcua.as_mut() {
            o.session_timeout_max_ms += 1000;
        }
        assert_eq!(diff(&new, &longer).faces_restarted, vec![Face::OpcUa]);
        // Its certificates are in the state directory.
        let mut moved = new.clone();
        moved.safety.state_dir = Some("/var/lib/elsewhere".into());
        assert!(diff(&new, &moved).faces_restarted.contains(&Face::OpcUa));
        assert!(
            !diff(&old, &{
                let mut o = old.clone();
                o.safety.state_dir = Some("/var/lib/elsewhere".into());
                o
            })
            .faces_restarted
            .contains(&Face::OpcUa)
        );
    }

    #[test]
    fn tls_and_mqtt_changes_restart_only_their_face() {
        let tls = "[modbus_tcp.tls]\nlisten = \"127.0.0.1:802\"\ncert = \"/x/gw.pem\"\nkey = \"/x/gw.key\"\nclient_ca = \"/x/ca.pem\"\n";
        let (old, new) = (reference(), with(tls));
        assert_eq!(diff(&old, &new).faces_restarted, vec![Face::ModbusTls]);
        assert_eq!(diff(&new, &old).faces_restarted, vec![Face::ModbusTls]);
        // The plain listener's limits are the secure one's too.
        let mut limits = new.clone();
        limits.modbus_tcp.max_connections += 1;
        assert_eq!(
            diff(&new, &limits).faces_restarted,
            vec![Face::ModbusTcp, Face::ModbusTls]
        );
        let mqtt = "[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"\n";
        // Without the reference's [opcua], whose certificates are in the
        // state directory too.
        let plain = |mut c: Config| {
            c.opcua = None;
            c
        };
        let (a, b) = (
            plain(with(mqtt)),
            plain(with(&mqtt.replace("1883", "1884"))),
        );
        let c = diff(&a, &b);
        assert_eq!(c.faces_restarted, vec![Face::Mqtt]);
        assert_eq!(c.lines(), vec!["restarted: MQTT face"]);
        // Its store is in the state directory.
        let mut moved = a.clone();
        moved.safety.state_dir = Some("/var/lib/elsewhere".into());
        assert_eq!(diff(&a, &moved).faces_restarted, vec![Face::Mqtt]);
        assert_eq!(
            diff(&a, &plain(reference())).faces_restarted,
            vec![Face::Mqtt]
        );
    }
}
