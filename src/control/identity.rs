//! Who a caller is, and with which role: the one place where what a face
//! proved about its client becomes a (who, role).
//!
//! A face authenticates what only it can: a token's secret against its
//! digest, a certificate's signature and chain against the trust it was
//! configured with. It hands over what that proved ([`Credential`]), and
//! [`identify`] gives the role, read from the running configuration only.
//! A peer never grants itself a role: a certificate's role extension counts
//! only when a CA the configuration names for roles vouched for it
//! ([`Vouched::RoleCa`]); a certificate trusted one by one (an OPC UA user
//! certificate in `users/trusted/certs`) has the role the configuration
//! maps to its thumbprint or subject, or none.
//!
//! Per face (`docs/security.md`, "Where a role comes from"):
//! - HTTP, the stream, OPC UA user names: the `[[http.token]]` whose secret
//!   was presented (`Credential::Token`);
//! - HTTP without tokens: every loopback client is admin
//!   (`Credential::Loopback`);
//! - Modbus/TCP Security: the certificate signed by `client_ca`: its role
//!   extension, else `default_role`; viewer when `read_only`;
//! - OPC UA user certificates: `[[opcua.user_certificate]]`, else the role
//!   extension of a certificate signed by `user_ca`;
//! - OPC UA anonymous sessions: viewer, or refused (`[opcua] anonymous`);
//! - plain Modbus TCP, whose clients prove nothing but their address: the
//!   most specific of `allowed_networks` (admin) and `[[modbus_tcp.clients]]`
//!   (its role) that holds the address ([`super::networks`]); viewer when
//!   `read_only` (`Credential::Network`);
//! - MQTT, whose messages carry no publisher: `[mqtt] commands`, for every
//!   command arriving on drivegate's own broker login, named by that login
//!   and the primary host claimed (`Credential::Broker`).
//!
//! The API (`api/caller.rs`), Modbus TCP (`modbus_tcp/access.rs`),
//! Modbus/TCP Security (`modbus_tcp/server.rs`), MQTT (`mqtt/mod.rs`) and
//! OPC UA (`opcua/users.rs`) ask here.

use std::net::IpAddr;
use std::sync::Arc;

use sha2::{Digest, Sha256};

use super::Face;
use crate::config::opcua::Anonymous;
use crate::config::{Config, ROLE_EXTENSION, Role};

/// What a face proved about its client.
#[derive(Debug, Clone, Copy)]
pub enum Credential<'a> {
    /// The secret of the `[[http.token]]` with this name (an API bearer
    /// token, an OPC UA user name and password), checked by the face.
    Token(&'a str),
    /// A loopback client of an API without tokens, named by its address.
    Loopback(&'a str),
    /// A certificate (DER) whose signature and chain the face verified,
    /// and what vouched for it.
    Certificate {
        /// The certificate.
        der: &'a [u8],
        /// Who vouched for it.
        vouched: Vouched,
    },
    /// Nothing: an anonymous OPC UA session.
    Anonymous,
    /// Only the address a plain Modbus TCP client connects from.
    Network(IpAddr),
    /// A command from the MQTT broker: all drivegate knows is how it
    /// logged in itself (`login`, as the broker knows the connection) and,
    /// with Sparkplug, the primary host that claims to be in charge.
    Broker {
        /// The broker user, certificate or unauthenticated broker.
        login: &'a str,
        /// The primary host claimed, if any.
        primary_host: Option<&'a str>,
    },
}

/// What vouched for a certificate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Vouched {
    /// A CA the configuration names for this face's roles (Modbus/TCP
    /// Security's `client_ca`, OPC UA's `user_ca`): its role extension
    /// counts.
    RoleCa,
    /// A list of certificates trusted one by one: trusted, with no role of
    /// its own.
    TrustList,
}

/// Who a caller is, for the audit log, and its role.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    /// A token's name, a certificate's CN (or its SHA-1 thumbprint), the
    /// client's address, or `anonymous`.
    pub who: Arc<str>,
    /// Its role.
    pub role: Role,
}

/// The identity of the client of `face` that proved `credential`, under
/// `config`; or why it has none (in words, for the log).
pub fn identify(
    config: &Config,
    face: Face,
    credential: Credential<'_>,
) -> Result<Identity, String> {
    match credential {
        Credential::Token(name) => config
            .http
            .tokens
            .iter()
            .find(|t| t.name == name)
            .map(|t| Identity {
                who: name.into(),
                role: t.role,
            })
            .ok_or_else(|| format!("no [[http.token]] is named \"{name}\" (any more)")),
        Credential::Loopback(who) if config.http.tokens.is_empty() => Ok(Identity {
            who: who.into(),
            role: Role::Admin,
        }),
        Credential::Loopback(who) => Err(format!(
            "{who}: tokens are configured, so a client needs one"
        )),
        Credential::Anonymous => match config.opcua.as_ref().map(|o| o.anonymous) {
            Some(Anonymous::Viewer) => Ok(Identity {
                who: "anonymous".into(),
                role: Role::Viewer,
            }),
            _ => Err("an anonymous session ([opcua] anonymous = \"none\")".to_string()),
        },
        Credential::Certificate { der, vouched } => certificate(config, face, der, vouched),
        Credential::Network(ip) => network(config, face, ip),
        Credential::Broker {
            login,
            primary_host,
        } => broker(config, face, login, primary_host),
    }
}

/// A plain Modbus TCP client's identity: its address, and the role of the
/// most specific network that holds it.
fn network(config: &Config, face: Face, ip: IpAddr) -> Result<Identity, String> {
    if face != Face::ModbusTcp {
        return Err(format!("an address gives no role {}", face.words()));
    }
    let ip = ip.to_canonical();
    let rights = super::networks::Networks::from_config(&config.modbus_tcp)
        .rights(ip)
        .ok_or_else(|| {
            format!("{ip} is in none of [modbus_tcp] allowed_networks and [[modbus_tcp.clients]]")
        })?;
    Ok(Identity {
        who: ip.to_string().into(),
        role: rights.role,
    })
}

/// The identity of commands from the MQTT broker: drivegate's own login
/// and the primary host claimed, with the role of `[mqtt] commands`.
fn broker(
    config: &Config,
    face: Face,
    login: &str,
    primary_host: Option<&str>,
) -> Result<Identity, String> {
    if face != Face::Mqtt {
        return Err(format!("a broker login gives no role {}", face.words()));
    }
    let mqtt = config.mqtt.as_ref().ok_or("MQTT is not configured")?;
    let who = match primary_host {
        Some(host) => format!("{login}; primary host \"{host}\" claimed"),
        None => login.to_string(),
    };
    Ok(Identity {
        who: who.into(),
        role: mqtt.commands().role(),
    })
}

/// A certificate's identity: see [`identify`].
fn certificate(
    config: &Config,
    face: Face,
    der: &[u8],
    vouched: Vouched,
) -> Result<Identity, String> {
    let facts = crate::tls::peer_identity(&der.to_vec().into(), ROLE_EXTENSION)?;
    let sha1 = crate::tls::sha1_fingerprint(der);
    let who: Arc<str> = facts
        .common_name
        .clone()
        .unwrap_or_else(|| hex(&sha1))
        .into();
    let extension = || -> Result<Option<Role>, String> {
        match &facts.extension {
            None => Ok(None),
            Some(Err(e)) => Err(format!("the certificate of {who}: its role extension: {e}")),
            Some(Ok(name)) => Role::from_name(&name.trim().to_ascii_lowercase()).map(Some).ok_or_else(|| {
                format!(
                    "the certificate's role \"{name}\" is none of viewer, operator, admin (the certificate of {who})"
                )
            }),
        }
    };
    let role = match face {
        Face::ModbusTcp => {
            let tls = config
                .modbus_tcp
                .tls
                .as_ref()
                .ok_or("Modbus/TCP Security is not configured")?;
            if vouched != Vouched::RoleCa {
                return Err(format!(
                    "the certificate of {who} is not signed by client_ca"
                ));
            }
            let role = extension()?.unwrap_or(tls.default_role);
            if config.modbus_tcp.read_only {
                Role::Viewer
            } else {
                role
            }
        }
        Face::OpcUa => {
            let opcua = config.opcua.as_ref().ok_or("OPC UA is not configured")?;
            let sha256: [u8; 32] = Sha256::digest(der).into();
            let mapped = opcua
                .user_certificates
                .iter()
                .find(|u| u.names(&sha1, &sha256, &facts.subject))
                .map(|u| u.role);
            match (mapped, vouched) {
                (Some(role), _) => role,
                (None, Vouched::RoleCa) => extension()?.ok_or_else(|| {
                    format!(
                        "the user certificate of {who} has no role extension {ROLE_EXTENSION} \
                         and no [[opcua.user_certificate]] names it"
                    )
                })?,
                (None, Vouched::TrustList) => {
                    return Err(format!(
                        "the user certificate of {who} (SHA-1 {}) is trusted, but no \
                         [[opcua.user_certificate]] gives it a role (a role extension counts \
                         only when user_ca signed the certificate)",
                        hex(&sha1)
                    ));
                }
            }
        }
        other => {
            return Err(format!("certificates give no role {}", other.words()));
        }
    };
    Ok(Identity { who, role })
}

/// Bytes in hex, upper case with colons, as openssl prints fingerprints.
pub fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(":")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(text: &str) -> Config {
        Config::parse(text, "test.toml").unwrap()
    }

    const TOKEN: &str = "[[http.token]]\nname = \"panel\"\nrole = \"operator\"\nsha256 = \"0000000000000000000000000000000000000000000000000000000000000000\"\n";

    #[test]
    fn a_token_has_its_configured_role_and_loopback_is_admin_only_without_tokens() {
        let c = config(TOKEN);
        let panel = identify(&c, Face::OpcUa, Credential::Token("panel")).unwrap();
        assert_eq!((&*panel.who, panel.role), ("panel", Role::Operator));
        assert!(identify(&c, Face::Http, Credential::Token("ghost")).is_err());
        assert!(identify(&c, Face::Http, Credential::Loopback("127.0.0.1:5000")).is_err());
        let open = config("");
        let local = identify(&open, Face::Http, Credential::Loopback("127.0.0.1:5000")).unwrap();
        assert_eq!(local.role, Role::Admin);
    }

    #[test]
    fn anonymous_is_a_viewer_only_when_the_configuration_says_so() {
        let on = config("[opcua]\nanonymous = \"viewer\"\n");
        assert_eq!(
            identify(&on, Face::OpcUa, Credential::Anonymous)
                .unwrap()
                .role,
            Role::Viewer
        );
        let off = config("[opcua]\nanonymous = \"none\"\n");
        assert!(identify(&off, Face::OpcUa, Credential::Anonymous).is_err());
        assert!(identify(&config(""), Face::OpcUa, Credential::Anonymous).is_err());
    }

    #[test]
    fn a_plain_modbus_client_has_the_role_of_its_most_specific_network() {
        let c = config(
            "[modbus_tcp]\nallowed_networks = [\"10.0.0.0/8\"]\n\
             [[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\n",
        );
        let of = |ip: &str| {
            identify(
                &c,
                Face::ModbusTcp,
                Credential::Network(ip.parse().unwrap()),
            )
        };
        let plc = of("::ffff:10.1.2.3").unwrap();
        assert_eq!((&*plc.who, plc.role), ("10.1.2.3", Role::Operator));
        assert_eq!(of("10.9.9.9").unwrap().role, Role::Admin);
        let stranger = of("192.168.1.1").unwrap_err();
        assert!(stranger.contains("192.168.1.1 is in none of"), "{stranger}");
        // An address is a role over plain Modbus TCP only.
        let ip = "10.1.2.3".parse().unwrap();
        assert!(identify(&c, Face::Http, Credential::Network(ip)).is_err());
        assert!(identify(&c, Face::OpcUa, Credential::Network(ip)).is_err());
        // read_only makes every network a viewer's.
        let ro = config("[modbus_tcp]\nread_only = true\n");
        let local = identify(
            &ro,
            Face::ModbusTcp,
            Credential::Network(ip_of("127.0.0.1")),
        );
        assert_eq!(local.unwrap().role, Role::Viewer);
    }

    fn ip_of(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn mqtt_commands_have_the_configured_role_and_name_the_login() {
        let c = config(
            "[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"\ncommands = \"operator\"\n\
             username = \"gw1\"\npassword_file = \"/x\"\n",
        );
        let broker = |face, host| {
            identify(
                &c,
                face,
                Credential::Broker {
                    login: "broker user gw1",
                    primary_host: host,
                },
            )
        };
        let claimed = broker(Face::Mqtt, Some("scada")).unwrap();
        assert_eq!(
            (&*claimed.who, claimed.role),
            (
                "broker user gw1; primary host \"scada\" claimed",
                Role::Operator
            )
        );
        assert_eq!(&*broker(Face::Mqtt, None).unwrap().who, "broker user gw1");
        // A broker login is a role over MQTT only, and only with [mqtt].
        assert!(broker(Face::ModbusTcp, None).is_err());
        let none = identify(
            &config(""),
            Face::Mqtt,
            Credential::Broker {
                login: "x",
                primary_host: None,
            },
        );
        assert!(none.is_err());
    }

    #[test]
    fn garbage_is_no_certificate() {
        let c = config("[opcua]\n");
        let e = identify(
            &c,
            Face::OpcUa,
            Credential::Certificate {
                der: b"not a certificate",
                vouched: Vouched::RoleCa,
            },
        )
        .unwrap_err();
        assert!(e.contains("not valid X.509"), "{e}");
        assert_eq!(hex(&[0x3a, 0x07]), "3A:07");
    }
}
