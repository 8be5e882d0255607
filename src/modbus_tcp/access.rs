//! Which client addresses may connect: a list of allowed networks (CIDR).
//!
//! Modbus TCP has no authentication, so the network a client comes from is
//! the only thing the gateway can check before it lets a request move a
//! motor.

use std::net::IpAddr;

use ipnet::IpNet;

/// The allowed client networks of a listener.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AllowList {
    networks: Vec<IpNet>,
}

impl AllowList {
    /// Allows clients in any of `networks` (an empty list allows nobody).
    pub fn new(networks: Vec<IpNet>) -> Self {
        Self { networks }
    }

    /// True when `ip` is in an allowed network. An IPv4 client reaching an
    /// IPv6 socket appears as `::ffff:a.b.c.d` and is checked as IPv4.
    pub fn allows(&self, ip: IpAddr) -> bool {
        let ip = ip.to_canonical();
        self.networks.iter().any(|n| n.contains(&ip))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus_tcp::config::default_allowed_networks;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn networks_are_matched_by_prefix() {
        let list = AllowList::new(vec![
            "192.168.10.0/24".parse().unwrap(),
            "fd00::/8".parse().unwrap(),
        ]);
        assert!(list.allows(ip("192.168.10.77")));
        assert!(!list.allows(ip("192.168.11.1")));
        assert!(list.allows(ip("fd12::1")));
        assert!(!list.allows(ip("127.0.0.1")));
        // IPv4 through a dual-stack socket
        assert!(list.allows(ip("::ffff:192.168.10.5")));
        assert!(!AllowList::new(vec![]).allows(ip("127.0.0.1")));
    }

    #[test]
    fn the_default_allows_plant_networks_not_the_internet() {
        let list = AllowList::new(default_allowed_networks());
        for ok in [
            "127.0.0.1",
            "10.1.2.3",
            "172.20.0.9",
            "192.168.0.10",
            "169.254.3.4",
            "::1",
            "fd00::5",
            "fe80::1",
        ] {
            assert!(list.allows(ip(ok)), "{ok}");
        }
        for refused in ["8.8.8.8", "172.32.0.1", "2001:db8::1", "100.64.0.1"] {
            assert!(!list.allows(ip(refused)), "{refused}");
        }
    }
}
