//! Who may connect to Modbus TCP from where, and with which role: the
//! allowed networks (CIDR), each with its rights.
//!
//! Modbus TCP has no authentication, so the network a client comes from is
//! the only thing the gateway can check before it lets a request move a
//! motor. A client in several networks gets the most specific one (the
//! longest prefix): a plant can allow 10.0.0.0/8 to read and still let the
//! PLC network 10.1.0.0/16 run the drives. The role is the core's to give
//! ([`super::identity::identify`] with `Credential::Network`); the face
//! asks here for the rest of its network's terms.

use std::net::IpAddr;

use ipnet::IpNet;

use crate::config::ModbusTcpConfig;
use crate::control::{CommLoss, Role};

/// What a client of one network may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rights {
    /// Its role.
    pub role: Role,
    /// Writes that need standstill are sent even while the motor turns.
    pub allow_saves_while_moving: bool,
    /// Its communication-loss function, if it has one.
    pub comm_loss: Option<CommLoss>,
}

/// The allowed client networks of a Modbus TCP listener, with their rights.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Networks {
    networks: Vec<(IpNet, Rights)>,
}

impl Networks {
    /// Allows `networks` with their rights (an empty list allows nobody).
    pub fn new(networks: Vec<(IpNet, Rights)>) -> Self {
        Self { networks }
    }

    /// The access `config` describes: `allowed_networks` (loopback when
    /// not set) with the admin role (viewer when `read_only`), and each
    /// `clients` entry with its own.
    pub fn from_config(config: &ModbusTcpConfig) -> Self {
        let plain = Rights {
            role: if config.read_only {
                Role::Viewer
            } else {
                Role::Admin
            },
            allow_saves_while_moving: false,
            comm_loss: None,
        };
        let mut networks: Vec<(IpNet, Rights)> =
            config.allowed().into_iter().map(|n| (n, plain)).collect();
        networks.extend(config.clients.iter().map(|c| {
            let role = if config.read_only {
                Role::Viewer
            } else {
                c.role()
            };
            (
                c.network,
                Rights {
                    role,
                    allow_saves_while_moving: c.allow_saves_while_moving,
                    comm_loss: c.comm_loss().map(|l| CommLoss {
                        after: l.after,
                        action: l.action,
                        face: crate::control::Face::ModbusTcp,
                    }),
                },
            )
        }));
        Self::new(networks)
    }

    /// The rights of a client at `ip`, `None` if it may not connect. An
    /// IPv4 client reaching an IPv6 socket appears as `::ffff:a.b.c.d` and
    /// is checked as IPv4. Of the networks it is in, the most specific
    /// decides; between equally specific ones, the lesser rights, and the
    /// one with a communication-loss function.
    pub fn rights(&self, ip: IpAddr) -> Option<Rights> {
        let ip = ip.to_canonical();
        self.networks
            .iter()
            .filter(|(n, _)| n.contains(&ip))
            .max_by(|(a, ra), (b, rb)| {
                a.prefix_len()
                    .cmp(&b.prefix_len())
                    .then(rb.role.cmp(&ra.role))
                    .then(
                        rb.allow_saves_while_moving
                            .cmp(&ra.allow_saves_while_moving),
                    )
                    .then(has_comm_loss(ra).cmp(&has_comm_loss(rb)))
            })
            .map(|(_, r)| *r)
    }

    /// True when `ip` may connect.
    pub fn allows(&self, ip: IpAddr) -> bool {
        self.rights(ip).is_some()
    }
}

fn has_comm_loss(rights: &Rights) -> bool {
    rights.comm_loss.is_some()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::modbus_tcp::default_allowed_networks;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    fn admin() -> Rights {
        Rights {
            role: Role::Admin,
            allow_saves_while_moving: false,
            comm_loss: None,
        }
    }

    fn plain(networks: &[&str]) -> Networks {
        Networks::new(
            networks
                .iter()
                .map(|n| (n.parse().unwrap(), admin()))
                .collect(),
        )
    }

    #[test]
    fn networks_are_matched_by_prefix() {
        let list = plain(&["192.168.10.0/24", "fd00::/8"]);
        assert!(list.allows(ip("192.168.10.77")));
        assert!(!list.allows(ip("192.168.11.1")));
        assert!(list.allows(ip("fd12::1")));
        assert!(!list.allows(ip("127.0.0.1")));
        // IPv4 through a dual-stack socket
        assert!(list.allows(ip("::ffff:192.168.10.5")));
        assert!(!plain(&[]).allows(ip("127.0.0.1")));
    }

    #[test]
    fn the_default_allows_loopback_only() {
        let list = Networks::from_config(&ModbusTcpConfig::default());
        for ok in ["127.0.0.1", "127.0.0.2", "::1", "::ffff:127.0.0.1"] {
            assert_eq!(list.rights(ip(ok)), Some(admin()), "{ok}");
        }
        // The private ranges and link-local, once admin by default, and
        // the internet.
        for refused in [
            "10.1.2.3",
            "172.20.0.9",
            "192.168.0.10",
            "169.254.3.4",
            "fd00::5",
            "fe80::1",
            "8.8.8.8",
            "2001:db8::1",
        ] {
            assert!(!list.allows(ip(refused)), "{refused}");
        }
        assert_eq!(default_allowed_networks().len(), 2);
        // A plant network comes in with the role it is given.
        let config: ModbusTcpConfig =
            toml::from_str("[[clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"").unwrap();
        let access = Networks::from_config(&config);
        assert_eq!(
            access.rights(ip("10.1.2.3")).map(|r| r.role),
            Some(Role::Operator)
        );
        assert_eq!(
            access.rights(ip("127.0.0.1")).map(|r| r.role),
            Some(Role::Admin)
        );
        assert!(!access.allows(ip("10.2.0.1")));
    }

    #[test]
    fn the_most_specific_network_decides_the_role() {
        let toml = r#"
allowed_networks = ["10.0.0.0/8"]
[[clients]]
network = "10.1.0.0/16"
role = "operator"
[[clients]]
network = "10.1.2.0/24"
role = "viewer"
[[clients]]
network = "10.1.3.0/24"
role = "admin"
allow_saves_while_moving = true
[[clients]]
network = "192.168.5.0/24"
role = "viewer"
"#;
        let config: ModbusTcpConfig = toml::from_str(toml).unwrap();
        let access = Networks::from_config(&config);
        let role = |s: &str| access.rights(ip(s)).map(|r| r.role);
        assert_eq!(role("10.9.9.9"), Some(Role::Admin));
        assert_eq!(role("10.1.9.9"), Some(Role::Operator));
        assert_eq!(role("10.1.2.3"), Some(Role::Viewer));
        assert_eq!(role("::ffff:10.1.2.3"), Some(Role::Viewer));
        assert_eq!(
            role("192.168.5.1"),
            Some(Role::Viewer),
            "a client network may connect"
        );
        assert_eq!(role("192.168.6.1"), None);
        assert!(
            access
                .rights(ip("10.1.3.1"))
                .unwrap()
                .allow_saves_while_moving
        );
        assert!(
            !access
                .rights(ip("10.1.9.9"))
                .unwrap()
                .allow_saves_while_moving
        );
    }

    #[test]
    fn read_only_makes_everybody_a_viewer() {
        let config = ModbusTcpConfig {
            read_only: true,
            ..ModbusTcpConfig::default()
        };
        let access = Networks::from_config(&config);
        assert_eq!(access.rights(ip("127.0.0.1")).unwrap().role, Role::Viewer);
    }

    #[test]
    fn equally_specific_networks_give_the_lesser_rights() {
        let viewer = Rights {
            role: Role::Viewer,
            allow_saves_while_moving: false,
            comm_loss: None,
        };
        let net: IpNet = "10.0.0.0/8".parse().unwrap();
        let access = Networks::new(vec![(net, admin()), (net, viewer)]);
        assert_eq!(access.rights(ip("10.0.0.1")), Some(viewer));
    }
}
