//! Connections per client address: one host may hold at most
//! `max_connections_per_address` of a listener's connections, so that idle
//! sockets from one address (a scanner, a crashed HMI reconnecting in a
//! loop, an attacker) cannot take every slot and lock the PLCs out.
//!
//! An address is a [`host_key`](super::refusals::host_key): an IPv6 client
//! by its /64. Each connection holds an [`AddressSlot`]; dropping it gives
//! the slot back.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

use super::refusals::host_key;

/// The connections each address holds on one listener.
#[derive(Debug)]
pub struct Addresses {
    limit: usize,
    held: Mutex<HashMap<IpAddr, usize>>,
}

impl Addresses {
    /// At most `limit` connections per address.
    pub fn new(limit: usize) -> Arc<Self> {
        Arc::new(Addresses {
            limit,
            held: Mutex::new(HashMap::new()),
        })
    }

    /// The most one address may hold.
    pub fn limit(&self) -> usize {
        self.limit
    }

    /// A slot for a connection from `ip`, or `None` when its address
    /// holds the limit already.
    pub fn take(self: &Arc<Self>, ip: IpAddr) -> Option<AddressSlot> {
        let key = host_key(ip);
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        let count = held.entry(key).or_insert(0);
        if *count >= self.limit {
            return None;
        }
        *count += 1;
        Some(AddressSlot {
            book: self.clone(),
            key,
        })
    }

    /// Connections `ip`'s address holds now.
    pub fn held(&self, ip: IpAddr) -> usize {
        let held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        held.get(&host_key(ip)).copied().unwrap_or(0)
    }
}

/// One connection's place in its address's count.
#[derive(Debug)]
pub struct AddressSlot {
    book: Arc<Addresses>,
    key: IpAddr,
}

impl Drop for AddressSlot {
    fn drop(&mut self) {
        let mut held = self.book.held.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(count) = held.get_mut(&self.key) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                held.remove(&self.key);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn one_address_holds_at_most_the_limit() {
        let book = Addresses::new(2);
        let a = ip("127.0.0.1");
        let first = book.take(a).unwrap();
        let _second = book.take(a).unwrap();
        assert!(book.take(a).is_none());
        // Another address, and the same one through a dual-stack socket.
        assert!(book.take(ip("127.0.0.2")).is_some());
        assert!(book.take(ip("::ffff:127.0.0.1")).is_none());
        assert_eq!(book.held(a), 2);
        drop(first);
        assert_eq!(book.held(a), 1);
        assert!(book.take(a).is_some());
    }

    #[test]
    fn an_ipv6_host_counts_by_its_slash_64() {
        let book = Addresses::new(1);
        let _one = book.take(ip("2001:db8:0:1::1")).unwrap();
        assert!(book.take(ip("2001:db8:0:1::2")).is_none());
        assert!(book.take(ip("2001:db8:0:2::1")).is_some());
    }

    #[test]
    fn an_address_with_no_connection_is_forgotten() {
        let book = Addresses::new(3);
        for i in 0..100u8 {
            drop(book.take(IpAddr::from([10, 0, 0, i])).unwrap());
        }
        assert!(book.held.lock().unwrap().is_empty());
    }
}
