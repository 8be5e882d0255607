//! `[modbus_tcp]` section.

use std::net::SocketAddr;

use serde::Deserialize;

/// The Modbus TCP listener.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ModbusTcpConfig {
    /// Serve Modbus TCP at all.
    pub enabled: bool,
    /// Address and port to listen on (502 in deployment).
    pub listen: SocketAddr,
}

impl Default for ModbusTcpConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            listen: SocketAddr::from(([127, 0, 0, 1], 5020)),
        }
    }
}

impl ModbusTcpConfig {
    /// Checks against the rest of the configuration (e.g. the unit map
    /// against the configured buses).
    pub fn validate(&self, _config: &crate::config::Config) -> Result<(), String> {
        Ok(())
    }
}
