//! Clients of networks that are not let in, refused at accept, and when to
//! say so in the log: once per address and second at most, less often as a
//! burst goes on (`crate::connections::repeats`, the one mechanism of every
//! listener's repeated warnings), so that a scanner or a flood writes a
//! handful of lines while `drivegate_modbus_tcp_connections_rejected_total
//! {reason="not_allowed"}` counts every one. Refusals for want of room are
//! the budget's (`crate::connections`), said in its words.

use std::net::{IpAddr, SocketAddr};
use std::time::Instant;

use tracing::warn;

use crate::connections::repeats::{CAPACITY, Repeats, Say, folded_words};
use crate::connections::{Face, host_key};

/// Why a connection was refused for want of room: the budget's reasons
/// (`not_allowed` is this face's own).
pub use crate::connections::Refused;

/// The refusals of strangers, per address (an IPv6 client by its /64).
#[derive(Debug, Default)]
pub struct NotAllowedLog {
    log: Repeats<IpAddr>,
}

impl NotAllowedLog {
    /// A client at `peer` was refused at `now` for its network: logs it
    /// if a line is due.
    pub fn refused(&mut self, face: Face, peer: SocketAddr, now: Instant) {
        if let Some(line) = self.line(face, peer, now) {
            warn!(client = %peer, "{line}");
        }
    }

    /// The line for a refusal of `peer` at `now`, if one is due.
    pub fn line(&mut self, face: Face, peer: SocketAddr, now: Instant) -> Option<String> {
        match self.log.note(host_key(peer.ip()), now) {
            Say::Quiet => None,
            Say::Many { folded } => Some(format!(
                "{} connections refused from more than {CAPACITY} addresses at once (not_allowed); further refusals of addresses not yet logged are counted in drivegate_modbus_tcp_connections_rejected_total, not logged{}",
                face.name,
                folded_words(folded, false)
            )),
            Say::Line { folded, first } => Some(format!(
                "{} connection refused: the address is in none of the networks of [modbus_tcp] allowed_networks (not set: loopback only) and [[modbus_tcp.clients]]; to let it in, add a [[modbus_tcp.clients]] entry with its network and a role. Counted in drivegate_modbus_tcp_connections_rejected_total{{reason=\"not_allowed\"}}; logged once per address and second at most{}",
                face.name,
                folded_words(folded, first)
            )),
        }
    }

    /// Addresses kept now.
    pub fn len(&self) -> usize {
        self.log.len()
    }

    /// True when none is kept.
    pub fn is_empty(&self) -> bool {
        self.log.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::connections::words::MODBUS_TCP;

    #[test]
    fn a_scan_writes_a_line_per_address_not_per_connection() {
        let mut log = NotAllowedLog::default();
        let t = Instant::now();
        let peer: SocketAddr = "10.1.2.3:40000".parse().unwrap();
        let first = log.line(MODBUS_TCP, peer, t).expect("the first is said");
        assert!(first.contains("[[modbus_tcp.clients]]"), "{first}");
        for i in 1..500 {
            let at = t + Duration::from_millis(i);
            assert_eq!(log.line(MODBUS_TCP, peer, at), None);
        }
        // A second later, one line for the 499.
        let again = log
            .line(MODBUS_TCP, peer, t + Duration::from_millis(1500))
            .expect("a line a second later");
        assert!(again.contains("499 more"), "{again}");
        // Another address of the same IPv6 /64 is the same address.
        let a: SocketAddr = "[2001:db8:1:2::1]:1".parse().unwrap();
        let b: SocketAddr = "[2001:db8:1:2:ffff::7]:1".parse().unwrap();
        assert!(log.line(MODBUS_TCP, a, t).is_some());
        assert!(log.line(MODBUS_TCP, b, t).is_none());
        assert_eq!(log.len(), 2);
    }
}
