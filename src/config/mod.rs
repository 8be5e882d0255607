//! The daemon's configuration: a TOML file, validated with errors that point
//! at the line and column to fix.
//!
//! Sections: `[http]`, `[modbus_tcp]`, `[log]`, `[safety]`, `[monitor]`,
//! `[scope]` and one `[[bus]]`
//! per serial adapter, each with its `[[bus.drive]]` list (and optional
//! `[bus.rs485]`, `[bus.sim]`). `config/drivegate.toml` documents every key.

mod bus;
mod diagnostics;
mod error;
mod modbus_tls;
pub(crate) mod values;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use serde::Deserialize;

pub use bus::{BusConfig, DriveConfig, SimSection};
pub use diagnostics::{MonitorConfig, ScopeConfig};
pub use error::ConfigError;
pub use modbus_tls::ModbusTlsConfig;

use crate::api::config::HttpConfig;
use crate::logging::LogConfig;
use crate::modbus_tcp::config::ModbusTcpConfig;
use crate::safety::SafetyConfig;

/// The configuration the daemon runs with when none is given: one simulated
/// bus of four drives, HTTP on 127.0.0.1:8080, Modbus TCP on 127.0.0.1:5020.
pub const DEFAULT_CONFIG: &str = include_str!("../../config/default.toml");

/// The whole configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// REST, WebSocket and metrics listener.
    #[serde(default)]
    pub http: HttpConfig,
    /// Modbus TCP passthrough listener.
    #[serde(default)]
    pub modbus_tcp: ModbusTcpConfig,
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
    /// The buses (serial adapters), at least one.
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
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
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
        if self.buses.is_empty() {
            return Err(ConfigError::Invalid {
                origin: origin.to_string(),
                line: 1,
                column: 1,
                message: "no bus configured: add a [[bus]] section (port = \"sim\" for the built-in simulator)"
                    .to_string(),
            });
        }
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
            if bus.drives.is_empty() {
                return Err(at(
                    bus.name.span(),
                    format!(
                        "bus \"{}\" has no drives: add [[bus.drive]] sections",
                        bus.name()
                    ),
                ));
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
        self.modbus_tcp
            .validate(self)
            .map_err(|(span, message)| at(span, message))?;
        Ok(())
    }

    /// Number of drives over all buses.
    pub fn drive_count(&self) -> usize {
        self.buses.iter().map(|b| b.drives.len()).sum()
    }
}

#[cfg(test)]
mod tests;
