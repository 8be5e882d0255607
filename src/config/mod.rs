//! The daemon's configuration: a TOML file, validated with errors that point
//! at the line and column to fix.
//!
//! Sections: `[http]`, `[modbus_tcp]`, `[mqtt]`, `[opcua]`, `[log]`, `[safety]`, `[monitor]`,
//! `[scope]`, `[history]` and one `[[bus]]`
//! per serial adapter, each with its `[[bus.drive]]` list (and optional
//! `[bus.rs485]`, `[bus.sim]`). `config/drivegate.toml` documents every key.

mod bus;
mod comm_loss;
mod declared;
mod diagnostics;
pub mod diff;
pub mod edit;
mod error;
pub mod file;
mod history;
pub mod http;
pub mod modbus_tcp;
mod modbus_tls;
pub mod mqtt;
pub mod opcua;
pub mod origins;
mod role;
mod safety;
pub mod text_diff;
pub(crate) mod values;
pub mod warnings;
mod wording;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use serde::Deserialize;

pub use bus::{BusConfig, DriveConfig, SimSection};
pub use declared::{ApplySettings, Declared, DeclaredKeys};
pub use diagnostics::{MonitorConfig, ScopeConfig};
pub use error::ConfigError;
pub use history::HistoryConfig;
pub use http::HttpConfig;
pub use modbus_tcp::ModbusTcpConfig;
pub use modbus_tls::ModbusTlsConfig;
pub use mqtt::MqttConfig;
pub use opcua::OpcUaConfig;
pub use role::{ROLE_EXTENSION, Role};
pub use safety::{SafetyConfig, StopAction};

use crate::logging::LogConfig;

/// The configuration the daemon runs with when none is given: one simulated
/// bus of four drives, HTTP on 127.0.0.1:8080, Modbus TCP on 127.0.0.1:5020.
pub const DEFAULT_CONFIG: &str = include_str!("../../config/default.toml");

/// The whole configuration.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// REST, WebSocket and metrics listener.
    #[serde(default)]
    pub http: HttpConfig,
    /// Modbus TCP passthrough listener.
    #[serde(default)]
    pub modbus_tcp: ModbusTcpConfig,
    /// The MQTT face (Sparkplug B); absent: off.
    #[serde(default)]
    pub mqtt: Option<MqttConfig>,
    /// The OPC UA server; absent: off.
    #[serde(default)]
    pub opcua: Option<OpcUaConfig>,
    /// Logging.
    #[serde(default)]
    pub log: LogConfig,
    /// What to do with moving motors when clients vanish or the daemon stops.
    #[serde(default)]
    pub safety: SafetyConfig,
    /// The bus monitor (frames kept per bus).
    #[serde(default)]
    pub monitor: MonitorConfig,
    /// The scope (capture limits, the floor rate of the other drives).
    #[serde(default)]
    pub scope: ScopeConfig,
    /// The trends: how long each drive's status is kept.
    #[serde(default)]
    pub history: HistoryConfig,
    /// The buses (serial adapters). None, or a bus without drives, is a
    /// valid configuration: the daemon waits to be told which drives to
    /// poll, and `drivegate probe` or a bus scan finds them.
    #[serde(rename = "bus", default)]
    pub buses: Vec<BusConfig>,
}

impl Config {
    /// Parses and validates a configuration; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Config, ConfigError> {
        let config: Config =
            toml::from_str(text).map_err(|e| ConfigError::parse(origin, text, &e))?;
        config.validate(origin, text)?;
        Ok(config)
    }

    /// Reads, parses and validates the file at `path`.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        Self::load_with_warnings(path).map(|(config, _)| config)
    }

    /// Reads, parses and validates the file at `path`, with what it holds
    /// that is valid but probably a mistake ([`warnings::warnings`]).
    pub fn load_with_warnings(path: &Path) -> Result<(Config, Vec<String>), ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.display().to_string(),
            source,
        })?;
        let origin = path.display().to_string();
        let config = Self::parse(&text, &origin)?;
        let warnings = warnings::warnings(&config, &text, &origin);
        Ok((config, warnings))
    }

    /// The embedded default configuration.
    pub fn embedded_default() -> Result<Config, ConfigError> {
        Self::parse(DEFAULT_CONFIG, "(built-in default)")
    }

    /// Cross-field checks that serde cannot do: unique names, units, ports.
    fn validate(&self, origin: &str, text: &str) -> Result<(), ConfigError> {
        let at = |span: std::ops::Range<usize>, message: String| {
            ConfigError::invalid(origin, text, span, message)
        };
        let mut bus_names = BTreeSet::new();
        let mut ports = BTreeSet::new();
        let mut drive_names: BTreeMap<&str, &str> = BTreeMap::new();
        for bus in &self.buses {
            if !bus_names.insert(bus.name()) {
                return Err(at(
                    bus.name.span(),
                    format!("bus name \"{}\" is used twice", bus.name()),
                ));
            }
            let port = bus.port.get_ref();
            if port != "sim" && !ports.insert(port.as_str()) {
                return Err(at(
                    bus.port.span(),
                    format!("port {port} is used by two buses: one bus per adapter"),
                ));
            }
            if let Some(address) = crate::bus::tcp_port::address(port) {
                address.map_err(|message| at(bus.port.span(), message))?;
                if bus.rs485.direction != crate::bus::port::Direction::Auto {
                    return Err(at(
                        bus.port.span(),
                        format!(
                            "{port} is a serial device server, which switches the RS-485 \
                             direction itself: remove [bus.rs485] direction (or set it to \"auto\")"
                        ),
                    ));
                }
            }
            let mut units = BTreeSet::new();
            for drive in &bus.drives {
                if !units.insert(*drive.unit.get_ref()) {
                    return Err(at(
                        drive.unit.span(),
                        format!(
                            "unit {} is used twice on bus \"{}\"",
                            drive.unit(),
                            bus.name()
                        ),
                    ));
                }
                if let Some(keys) = &drive.settings {
                    keys.get_ref().declared().map_err(|message| {
                        at(
                            keys.span(),
                            format!("drive \"{}\": {message}", drive.name()),
                        )
                    })?;
                }
                if let Some(other) = drive_names.insert(drive.name(), bus.name()) {
                    return Err(at(
                        drive.name.span(),
                        format!(
                            "drive name \"{}\" is already used (on bus \"{other}\"): names must be unique",
                            drive.name()
                        ),
                    ));
                }
            }
            if bus.sim.is_some() && port != "sim" {
                return Err(at(
                    bus.port.span(),
                    "a [bus.sim] section only applies to port = \"sim\"".to_string(),
                ));
            }
        }
        self.check_leases(origin, text)?;
        self.modbus_tcp
            .validate(self)
            .map_err(|(span, message)| at(span, message))?;
        if let Some(mqtt) = &self.mqtt {
            mqtt.validate()
                .map_err(|(span, message)| at(span, message))?;
        }
        if let Some(opcua) = &self.opcua {
            opcua
                .validate()
                .map_err(|(span, message)| at(span, message))?;
        }
        Ok(())
    }

    /// The lease bounds of `[safety]` hold together, and the console's jog
    /// lease and `[http]`'s default lease are within them; a refusal
    /// points at the key it names.
    fn check_leases(&self, origin: &str, text: &str) -> Result<(), ConfigError> {
        let at = LeaseKeys::find(text);
        let invalid = |span: Option<std::ops::Range<usize>>, message: String| {
            ConfigError::invalid(origin, text, span.unwrap_or(0..0), message)
        };
        let (min, max) = (self.safety.lease_min_ms, self.safety.lease_max_ms);
        if max < min {
            return Err(invalid(
                at.safety(|s| &s.lease_max_ms),
                format!(
                    "[safety] lease_max_ms = {max} is out of range: valid {min} to 86400000 (at least lease_min_ms)"
                ),
            ));
        }
        let jog = self.safety.jog_lease_ms;
        if !(min..=max).contains(&jog) {
            return Err(invalid(
                at.safety(|s| &s.jog_lease_ms),
                format!(
                    "[safety] jog_lease_ms = {jog} is out of range: valid {min} to {max} (lease_min_ms to lease_max_ms): the console's jog asks for this lease"
                ),
            ));
        }
        if let Some(default) = self.http.lease_default {
            let ms = u64::try_from(default.as_millis()).unwrap_or(u64::MAX);
            if !(min..=max).contains(&ms) {
                return Err(invalid(
                    at.http.and_then(|h| h.lease_default_ms).map(|k| k.span()),
                    format!(
                        "[http] lease_default_ms = {ms} is out of range: valid {min} to {max} ([safety] lease_min_ms to lease_max_ms), or 0 for no default lease"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Number of drives over all buses.
    pub fn drive_count(&self) -> usize {
        self.buses.iter().map(|b| b.drives.len()).sum()
    }
}

/// Where the file sets the keys of the lease bounds, for an error that
/// points at them (the sections themselves keep only their values).
#[derive(Deserialize, Default)]
struct LeaseKeys {
    safety: Option<SafetyLeaseKeys>,
    http: Option<HttpLeaseKeys>,
}

#[derive(Deserialize)]
struct SafetyLeaseKeys {
    lease_max_ms: Option<toml::Spanned<toml::Value>>,
    jog_lease_ms: Option<toml::Spanned<toml::Value>>,
}

#[derive(Deserialize)]
struct HttpLeaseKeys {
    lease_default_ms: Option<toml::Spanned<toml::Value>>,
}

impl LeaseKeys {
    fn find(text: &str) -> Self {
        toml::from_str(text).unwrap_or_default()
    }

    /// The span of a `[safety]` key, if the file sets it.
    fn safety(
        &self,
        key: impl Fn(&SafetyLeaseKeys) -> &Option<toml::Spanned<toml::Value>>,
    ) -> Option<std::ops::Range<usize>> {
        self.safety
            .as_ref()
            .and_then(|s| key(s).as_ref())
            .map(|k| k.span())
    }
}

#[cfg(test)]
mod tests;
