//! Slows down guessing: a client that fails to sign in too often in a
//! short time is refused for a while, whatever it sends (so a guess cannot
//! even be confirmed meanwhile). One rule for every face with sign-ins:
//! failures are counted per address (the API's tokens, which have no
//! name), and per address and user name where a sign-in names its user
//! (OPC UA): a name locked from one address still signs in from another,
//! so a stranger cannot lock an operator out.
//!
//! [`SignIns`] is that rule, which every face with sign-ins holds: a name
//! (or, for a sign-in that names nobody, as a bearer token, the address's
//! nameless sign-ins) is paused from an address after `[http]
//! token_guesses` failures within a minute, the whole address after three
//! times as many.
//!
//! A pure state machine with the time passed in. Addresses are tracked by
//! IPv4 address or IPv6 /64 (one host usually owns a whole /64), and the
//! table is bounded, so a flood from many addresses cannot grow it.

use std::collections::HashMap;
use std::hash::Hash;
use std::net::IpAddr;
use std::time::{Duration, Instant};

/// What failures are counted by: an address, or an address and a name.
pub trait Key: Hash + Eq + Clone {
    /// The key as counted: an IPv6 address by its /64, an IPv4-mapped one
    /// as IPv4.
    fn normal(self) -> Self;
}

impl Key for IpAddr {
    fn normal(self) -> Self {
        key(self)
    }
}

impl Key for (IpAddr, String) {
    fn normal(self) -> Self {
        (key(self.0), self.1)
    }
}

impl Key for (IpAddr, Option<String>) {
    fn normal(self) -> Self {
        (key(self.0), self.1)
    }
}

/// How many failures, over how long, start a pause of how long.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Policy {
    /// Failures within `window` that start a pause.
    pub burst: u32,
    /// The window failures are counted in, from the first one.
    pub window: Duration,
    /// How long the address is then refused.
    pub pause: Duration,
    /// Addresses tracked at once.
    pub max_peers: usize,
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            burst: 10,
            window: Duration::from_secs(60),
            pause: Duration::from_secs(60),
            max_peers: 4096,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Peer {
    first: Instant,
    failures: u32,
    paused_until: Option<Instant>,
}

/// What a failure did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// The first failure of a new burst: worth a log line.
    First,
    /// One more failure within the burst: counted, not logged.
    Again,
    /// This failure started a pause: logged once, with the count.
    Paused {
        /// Failures in the burst.
        failures: u32,
        /// How long the address is refused.
        pause: Duration,
    },
}

/// The failures of each address (or address and name).
#[derive(Debug)]
pub struct Throttle<K = IpAddr> {
    policy: Policy,
    peers: HashMap<K, Peer>,
}

/// The key of an address: IPv4 as is, IPv6 by its /64.
pub fn key(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V6(v6) => {
            let mut s = v6.segments();
            s[4..].fill(0);
            IpAddr::V6(s.into())
        }
        v4 => v4,
    }
}

impl<K: Key> Default for Throttle<K> {
    fn default() -> Self {
        Throttle::new(Policy::default())
    }
}

impl<K: Key> Throttle<K> {
    /// A throttle with `policy`.
    pub fn new(policy: Policy) -> Self {
        Throttle {
            policy,
            peers: HashMap::new(),
        }
    }

    /// `Err(wait)` while `ip` is paused: refuse, and say when to retry.
    pub fn check(&self, ip: K, now: Instant) -> Result<(), Duration> {
        match self.peers.get(&ip.normal()).and_then(|p| p.paused_until) {
            Some(until) if until > now => Err(until - now),
            _ => Ok(()),
        }
    }

    /// Notes a failed sign-in (an unknown token) from `ip`.
    pub fn failure(&mut self, ip: K, now: Instant) -> Failure {
        let policy = self.policy;
        let ip = ip.normal();
        if self.peers.len() >= policy.max_peers && !self.peers.contains_key(&ip) {
            self.forget_stale(now);
        }
        if self.peers.len() >= policy.max_peers && !self.peers.contains_key(&ip) {
            // Full of live entries (a flood from many addresses): this one
            // is counted in the metrics only, and what is known is kept.
            return Failure::Again;
        }
        let peer = self.peers.entry(ip).or_insert(Peer {
            first: now,
            failures: 0,
            paused_until: None,
        });
        let stale = now.duration_since(peer.first) >= policy.window
            || peer.paused_until.is_some_and(|u| u <= now);
        if stale {
            *peer = Peer {
                first: now,
                failures: 0,
                paused_until: None,
            };
        }
        peer.failures = peer.failures.saturating_add(1);
        if peer.failures == 1 {
            return Failure::First;
        }
        if peer.failures >= policy.burst && peer.paused_until.is_none() {
            peer.paused_until = Some(now + policy.pause);
            return Failure::Paused {
                failures: peer.failures,
                pause: policy.pause,
            };
        }
        Failure::Again
    }

    /// Addresses tracked now.
    pub fn len(&self) -> usize {
        self.peers.len()
    }

    /// True when no address is tracked.
    pub fn is_empty(&self) -> bool {
        self.peers.is_empty()
    }

    fn forget_stale(&mut self, now: Instant) {
        let window = self.policy.window;
        self.peers.retain(|_, p| match p.paused_until {
            Some(until) => until > now,
            None => now.duration_since(p.first) < window,
        });
    }
}

/// Failed sign-ins of one face, by address and by address and user name:
/// the one rule of every face with sign-ins (module doc).
#[derive(Debug)]
pub struct SignIns {
    by_address: Throttle<IpAddr>,
    by_name: Throttle<(IpAddr, Option<String>)>,
}

impl Default for SignIns {
    /// `[http] token_guesses`' default.
    fn default() -> Self {
        SignIns::new(Policy::default().burst)
    }
}

impl SignIns {
    /// A name (or the nameless sign-ins) is paused from an address after
    /// `allowed` failures within a minute, the address after three times
    /// as many.
    pub fn new(allowed: u32) -> Self {
        let policy = |burst| Policy {
            burst,
            ..Policy::default()
        };
        SignIns {
            by_address: Throttle::new(policy(allowed.saturating_mul(3))),
            by_name: Throttle::new(policy(allowed)),
        }
    }

    /// `Err(wait)` while the address, or `name` from it, is paused.
    pub fn check(&self, ip: IpAddr, name: Option<&str>, now: Instant) -> Result<(), Duration> {
        self.by_address.check(ip, now)?;
        self.by_name.check((ip, name.map(str::to_string)), now)
    }

    /// Notes a failed sign-in of `name` (`None`: one that names nobody)
    /// from `ip`; what it did, for the log (a pause it started, of the
    /// address or of the name).
    pub fn failed(&mut self, ip: IpAddr, name: Option<&str>, now: Instant) -> Failure {
        let address = self.by_address.failure(ip, now);
        let named = self.by_name.failure((ip, name.map(str::to_string)), now);
        match (address, named) {
            (paused @ Failure::Paused { .. }, _) => paused,
            (_, named) => named,
        }
    }

    /// Names and addresses tracked now.
    pub fn len(&self) -> usize {
        self.by_address.len() + self.by_name.len()
    }

    /// True when nothing is tracked.
    pub fn is_empty(&self) -> bool {
        self.by_address.is_empty() && self.by_name.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Duration = Duration::from_secs(1);

    fn policy() -> Policy {
        Policy {
            burst: 3,
            window: 10 * S,
            pause: 30 * S,
            max_peers: 4,
        }
    }

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn a_name_paused_from_one_address_is_not_paused_from_another() {
        let mut t: Throttle<(IpAddr, String)> = Throttle::new(policy());
        let t0 = Instant::now();
        let panel = |a: &str| (ip(a), "panel".to_string());
        for i in 0..3 {
            t.failure(panel("10.0.0.66"), t0 + i * S);
        }
        assert!(t.check(panel("10.0.0.66"), t0 + 3 * S).is_err());
        assert_eq!(t.check(panel("10.0.0.5"), t0 + 3 * S), Ok(()));
        assert_eq!(
            t.check((ip("10.0.0.66"), "scada".into()), t0 + 3 * S),
            Ok(())
        );
    }

    #[test]
    fn a_burst_of_failures_pauses_the_address() {
        let mut t: Throttle = Throttle::new(policy());
        let t0 = Instant::now();
        let a = ip("10.0.0.1");
        assert_eq!(t.failure(a, t0), Failure::First);
        assert_eq!(t.failure(a, t0 + S), Failure::Again);
        assert_eq!(t.check(a, t0 + S), Ok(()));
        assert_eq!(
            t.failure(a, t0 + 2 * S),
            Failure::Paused {
                failures: 3,
                pause: 30 * S
            }
        );
        assert_eq!(t.check(a, t0 + 2 * S), Err(30 * S));
        assert_eq!(t.check(a, t0 + 12 * S), Err(20 * S));
        // Other addresses are not concerned.
        assert_eq!(t.check(ip("10.0.0.2"), t0 + 2 * S), Ok(()));
        // Once the pause is over the address starts afresh.
        assert_eq!(t.check(a, t0 + 32 * S), Ok(()));
        assert_eq!(t.failure(a, t0 + 33 * S), Failure::First);
    }

    #[test]
    fn failures_spread_over_more_than_the_window_do_not_pause() {
        let mut t: Throttle = Throttle::new(policy());
        let t0 = Instant::now();
        let a = ip("10.0.0.1");
        assert_eq!(t.failure(a, t0), Failure::First);
        assert_eq!(t.failure(a, t0 + 9 * S), Failure::Again);
        assert_eq!(t.failure(a, t0 + 10 * S), Failure::First);
        assert_eq!(t.failure(a, t0 + 11 * S), Failure::Again);
        assert_eq!(t.check(a, t0 + 11 * S), Ok(()));
    }

    #[test]
    fn a_burst_is_reported_paused_once() {
        let mut t: Throttle = Throttle::new(policy());
        let t0 = Instant::now();
        let a = ip("10.0.0.1");
        for i in 0..3 {
            t.failure(a, t0 + i * S);
        }
        // Failures during the pause (refused before their token is even
        // looked at, but counted if they come) do not log again.
        assert_eq!(t.failure(a, t0 + 4 * S), Failure::Again);
    }

    #[test]
    fn ipv6_hosts_are_tracked_by_their_64() {
        let mut t: Throttle = Throttle::new(policy());
        let t0 = Instant::now();
        t.failure(ip("2001:db8:1:2::1"), t0);
        t.failure(ip("2001:db8:1:2::2"), t0);
        t.failure(ip("2001:db8:1:2:ffff::3"), t0);
        assert!(t.check(ip("2001:db8:1:2::99"), t0).is_err());
        assert_eq!(t.check(ip("2001:db8:1:3::1"), t0), Ok(()));
        // An IPv4-mapped address is its IPv4 address.
        t.failure(ip("::ffff:10.0.0.9"), t0);
        assert_eq!(t.len(), 2);
        assert_eq!(t.failure(ip("10.0.0.9"), t0), Failure::Again);
    }

    #[test]
    fn the_table_is_bounded() {
        let mut t: Throttle = Throttle::new(policy());
        let t0 = Instant::now();
        for i in 0..10 {
            t.failure(ip(&format!("10.0.1.{i}")), t0);
        }
        assert_eq!(t.len(), 4);
        // Stale entries make room.
        assert_eq!(t.failure(ip("10.0.2.1"), t0 + 11 * S), Failure::First);
        assert_eq!(t.len(), 1);
    }

    #[test]
    fn a_name_is_paused_from_its_address_and_the_address_after_three_times_as_many() {
        let mut g = SignIns::new(3);
        let t0 = Instant::now();
        let (a, b) = (ip("10.0.0.66"), ip("10.0.0.5"));
        let panel = Some("panel");
        for i in 0..3 {
            assert!(g.check(a, panel, t0).is_ok(), "after {i}");
            g.failed(a, panel, t0 + Duration::from_secs(i));
        }
        assert!(g.check(a, panel, t0 + 10 * S).is_err());
        assert!(g.check(b, panel, t0 + 10 * S).is_ok());
        assert!(g.check(a, Some("scada"), t0 + 10 * S).is_ok());
        for name in ["a", "b", "c", "d", "e", "f"] {
            g.failed(a, Some(name), t0 + 11 * S);
        }
        assert!(g.check(a, Some("scada"), t0 + 12 * S).is_err());
        assert!(g.check(b, Some("scada"), t0 + 12 * S).is_ok());
        assert!(g.check(a, panel, t0 + 75 * S).is_ok());
    }

    #[test]
    fn nameless_sign_ins_pause_their_address_at_the_names_count() {
        // A bearer token names nobody: its failures are the address's
        // nameless ones, paused after `allowed`, as a name would be; the
        // same address's named sign-ins and other addresses go on.
        let mut g = SignIns::new(3);
        let t0 = Instant::now();
        let (a, b) = (ip("10.0.0.66"), ip("10.0.0.5"));
        assert_eq!(g.failed(a, None, t0), Failure::First);
        assert_eq!(g.failed(a, None, t0), Failure::Again);
        assert!(matches!(
            g.failed(a, None, t0 + S),
            Failure::Paused { failures: 3, .. }
        ));
        assert!(g.check(a, None, t0 + 2 * S).is_err());
        assert!(g.check(b, None, t0 + 2 * S).is_ok());
        assert!(g.check(a, Some("panel"), t0 + 2 * S).is_ok());
        assert!(g.check(a, None, t0 + 62 * S).is_ok());
        assert!(!g.is_empty());
    }
}
