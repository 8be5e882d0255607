//! `[modbus_tcp.tls]`: Modbus/TCP Security, the Modbus Organization's
//! "MODBUS/TCP Security Protocol Specification": the ordinary MBAP frames
//! inside TLS 1.2 or later, port 802 by convention, every client
//! authenticated by an X.509 certificate signed by `client_ca`, its role in
//! the certificate (extension 1.3.6.1.4.1.50316.802.1, an ASN.1
//! UTF8String). The listener runs beside the plain one.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use serde::{Deserialize, Deserializer, de};

use super::comm_loss::CommLossConfig;
use super::role::Role;
use super::safety::StopAction;

/// The Modbus/TCP Security listener.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ModbusTlsConfig {
    /// Address and port to listen on (802 in deployment).
    #[serde(default = "default_listen")]
    pub listen: SocketAddr,
    /// The server's PEM certificate chain, its own certificate first.
    pub cert: PathBuf,
    /// Its PEM private key.
    pub key: PathBuf,
    /// The CA(s), PEM, whose client certificates are served: required.
    pub client_ca: PathBuf,
    /// The role of a client whose certificate has no role extension.
    #[serde(default = "default_role")]
    pub default_role: Role,
    /// Send saves to flash, factory reset, address setting and calibration
    /// even while the motor turns (refused with exception 0x06 otherwise).
    #[serde(default)]
    pub allow_saves_while_moving: bool,
    /// The communication-loss time of TLS clients, ms, as for a
    /// `[[modbus_tcp.clients]]` network. Absent: off.
    #[serde(default, deserialize_with = "comm_loss_ms")]
    pub comm_loss_ms: Option<u64>,
    /// What ends their leases (default `zero-speed`).
    #[serde(default)]
    pub comm_loss_action: Option<StopAction>,
}

/// The Modbus/TCP Security port.
const PORT: u16 = 802;

fn default_listen() -> SocketAddr {
    SocketAddr::from(([0, 0, 0, 0], PORT))
}

fn default_role() -> Role {
    Role::Viewer
}

/// Shortest and longest communication-loss times, as for networks.
const COMM_LOSS_MS: (u64, u64) = (20, 60_000);

fn comm_loss_ms<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    let v = i64::deserialize(d)?;
    let (min, max) = COMM_LOSS_MS;
    match u64::try_from(v) {
        Ok(ms) if (min..=max).contains(&ms) => Ok(Some(ms)),
        _ => Err(de::Error::custom(format!(
            "[modbus_tcp.tls] comm_loss_ms = {v} is out of range: valid {min} to {max} ms"
        ))),
    }
}

impl ModbusTlsConfig {
    /// The files, as the TLS module takes them.
    pub fn files(&self) -> crate::tls::TlsFiles {
        crate::tls::TlsFiles {
            cert: self.cert.clone(),
            key: self.key.clone(),
            client_ca: Some(self.client_ca.clone()),
        }
    }

    /// The communication-loss function of TLS clients, if it has a time.
    pub fn comm_loss(&self) -> Option<CommLossConfig> {
        Some(CommLossConfig {
            after: Duration::from_millis(self.comm_loss_ms?),
            action: self.comm_loss_action.unwrap_or(StopAction::ZeroSpeed),
        })
    }

    /// The role named in a certificate's role extension: `viewer`,
    /// `operator` or `admin`, in any case.
    pub fn role_named(text: &str) -> Option<Role> {
        match text.trim().to_ascii_lowercase().as_str() {
            "viewer" => Some(Role::Viewer),
            "operator" => Some(Role::Operator),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<ModbusTlsConfig, String> {
        toml::from_str(text).map_err(|e| e.to_string())
    }

    #[test]
    fn a_section_with_its_defaults() {
        let c = parse("cert = \"s.pem\"\nkey = \"s.key\"\nclient_ca = \"ca.pem\"").unwrap();
        assert_eq!(c.listen.to_string(), "0.0.0.0:802");
        assert_eq!(c.default_role, Role::Viewer);
        assert_eq!(c.comm_loss(), None);
        assert!(
            parse("cert = \"s.pem\"\nkey = \"s.key\"")
                .unwrap_err()
                .contains("client_ca")
        );
        let c = parse("cert = \"s.pem\"\nkey = \"s.key\"\nclient_ca = \"ca.pem\"\ndefault_role = \"operator\"\ncomm_loss_ms = 500\ncomm_loss_action = \"brake\"").unwrap();
        assert_eq!(c.default_role, Role::Operator);
        assert_eq!(
            c.comm_loss(),
            Some(CommLossConfig {
                after: Duration::from_millis(500),
                action: StopAction::Brake
            })
        );
        let e =
            parse("cert = \"s.pem\"\nkey = \"s.key\"\nclient_ca = \"ca.pem\"\ncomm_loss_ms = 5")
                .unwrap_err();
        assert!(e.contains("valid 20 to 60000 ms"), "{e}");
    }

    #[test]
    fn roles_are_read_in_any_case() {
        assert_eq!(
            ModbusTlsConfig::role_named("Operator"),
            Some(Role::Operator)
        );
        assert_eq!(ModbusTlsConfig::role_named("ADMIN"), Some(Role::Admin));
        assert_eq!(ModbusTlsConfig::role_named("viewer"), Some(Role::Viewer));
        assert_eq!(ModbusTlsConfig::role_named("boss"), None);
    }
}
