//! What changed between the running configuration and a new one: a pure
//! comparison of two checked [`Config`]s, which the daemon then applies
//! (`crate::daemon::reloader`). Nothing here opens a port or touches a drive.
//!
//! The bus is the unit a change is applied to, and a change touches only
//! what it changes ([`bus_change`]): the keys of a bus's open port (its
//! `port`, its `baud`, `[bus.rs485]`, and `[bus.sim]`, the simulated
//! adapter) reopen it; everything else (timing, retries, `interframe`,
//! poll rates, offline detection, the queue, the drives: added, removed,
//! renamed, given other settings) is applied to the running bus between
//! two transactions, its port kept open. The other buses are untouched.
//! A drive is the motor at a unit of a bus: it keeps its identity (its
//! lease, its stream subscriptions, its cache, its trends and its alarms)
//! as long as its bus and its unit stay the same, whatever its name (a
//! rename, [`Changes::drives_renamed`]); a drive moved to another bus or
//! given another unit is one drive removed and one added, so a lease
//! never follows a name to another motor.
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

    /// Its key in metrics' labels and `/readyz`.
    pub fn key(self) -> &'static str {
        match self {
            Face::Http => "http",
            Face::ModbusTcp => "modbus_tcp",
            Face::ModbusTls => "modbus_tls",
            Face::Mqtt => "mqtt",
            Face::OpcUa => "opcua",
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
    /// "baud", ... and what else changed with it).
    pub buses_reopened: Vec<(String, Vec<String>)>,
    /// Buses kept whose changes are applied in place, the port kept open,
    /// each with what changed ("poll rates", "drives", ...).
    pub buses_retuned: Vec<(String, Vec<String>)>,
    /// Drives new in the file, by name.
    pub drives_added: Vec<String>,
    /// Drives gone from the file (or moved to another bus or unit: those
    /// are added again under the same name).
    pub drives_removed: Vec<String>,
    /// Drives kept (the same bus and unit) under a new name: old, new.
    pub drives_renamed: Vec<(String, String)>,
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
        let renamed: Vec<String> = self
            .drives_renamed
            .iter()
            .map(|(old, new)| format!("{old} to {new}"))
            .collect();
        list("drives renamed", &renamed);
        list("drives changed", &self.drives_changed);
        list("buses added", &self.buses_added);
        list("buses removed", &self.buses_removed);
        for (bus, why) in &self.buses_reopened {
            out.push(format!("bus {bus} reopened ({} changed)", why.join(", ")));
        }
        for (bus, what) in &self.buses_retuned {
            out.push(format!(
                "bus {bus} changed in place ({}), its port kept open",
                what.join(", ")
            ));
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

/// Buses added, removed, reopened with why, and changed in place with
/// what. A change of `[scope]` or `[monitor]` reopens every bus: their
/// settings size what each bus keeps, from its start.
fn buses(old: &Config, new: &Config, changes: &mut Changes) {
    let observers_changed = old.scope != new.scope || old.monitor != new.monitor;
    for bus in &new.buses {
        match old.buses.iter().find(|b| b.name() == bus.name()) {
            None => changes.buses_added.push(bus.name().to_string()),
            Some(before) => {
                let BusChange {
                    mut reopen,
                    in_place,
                } = bus_change(before, bus);
                if observers_changed {
                    reopen.push("[scope] or [monitor]".to_string());
                }
                let name = bus.name().to_string();
                if !reopen.is_empty() {
                    reopen.extend(in_place);
                    changes.buses_reopened.push((name, reopen));
                } else if !in_place.is_empty() {
                    changes.buses_retuned.push((name, in_place));
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

/// What a change of one bus's section asks of the running bus, key by key.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BusChange {
    /// Keys of its open port (`port`, `baud`, `[bus.rs485]`, and
    /// `[bus.sim]`, the simulated adapter): the port is reopened.
    pub reopen: Vec<String>,
    /// The rest: applied between two transactions, the port kept open.
    pub in_place: Vec<String>,
}

/// What changed from bus section `a` to `b` (the same bus), and what each
/// change asks of the running bus. Pure.
pub fn bus_change(a: &BusConfig, b: &BusConfig) -> BusChange {
    let mut change = BusChange::default();
    let mut reopen = |name: &str, differ: bool| {
        if differ {
            change.reopen.push(name.to_string());
        }
    };
    reopen("port", a.port != b.port);
    reopen("baud", a.baud != b.baud);
    reopen("rs485", a.rs485 != b.rs485);
    reopen("sim", a.sim != b.sim);
    let mut key = |name: &str, differ: bool| {
        if differ {
            change.in_place.push(name.to_string());
        }
    };
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
    key("drives", a.drives != b.drives);
    change
}

/// A drive's identity: the motor at a unit of a bus, whatever its name.
fn identity<'a>(bus: &'a BusConfig, d: &'a DriveConfig) -> (&'a str, u8) {
    (bus.name(), d.unit())
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
        let Some((_, o)) = before
            .iter()
            .find(|(b, o)| identity(b, o) == identity(bus, d))
        else {
            changes.drives_added.push(d.name().to_string());
            continue;
        };
        if o.name() != d.name() {
            changes
                .drives_renamed
                .push((o.name().to_string(), d.name().to_string()));
        }
        // What else changed with it, under its new name.
        let mut renamed = (*o).clone();
        renamed.name = d.name.clone();
        if renamed != *d {
            changes.drives_changed.push(d.name().to_string());
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
mod tests;
