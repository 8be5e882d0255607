//! Connections refused at accept, and when to say so in the log: once per
//! address and burst, so that a scanner or a flood of 500 connections
//! writes one warning, not hundreds, while the metric counts every one.
//!
//! A burst is the refusals of one address (an IPv6 client by its /64) for
//! one reason, each less than [`QUIET`] after the one before. Its first
//! refusal is logged, with the key to set; the next burst's first line says
//! how many the last one held. The book is bounded: once it holds
//! [`CAPACITY`] live bursts (a flood from many addresses), the refusals of
//! further addresses share one burst per reason. Pure: time is passed in.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr};
use std::time::{Duration, Instant};

use crate::listed::listed_enum;

/// Silence that ends an address's burst of refusals.
pub const QUIET: Duration = Duration::from_secs(60);

/// Addresses whose bursts are kept apart; more share one.
pub const CAPACITY: usize = 1024;

listed_enum! {
    /// Why a connection was refused at accept.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum Refused {
        /// Its address is in none of the allowed networks.
        NotAllowed,
        /// Its address holds `max_connections_per_address` already.
        PerAddress,
        /// `max_connections` are open.
        Limit,
    }
}

impl Refused {
    /// Stable label for `drivegate_modbus_tcp_connections_rejected_total`.
    pub fn label(self) -> &'static str {
        match self {
            Refused::NotAllowed => "not_allowed",
            Refused::PerAddress => "per_address",
            Refused::Limit => "limit",
        }
    }
}

/// The address a client is counted and logged by: an IPv4 address (also
/// when it reaches an IPv6 socket as `::ffff:a.b.c.d`), or an IPv6 client's
/// /64, which one host may fill with addresses of its own.
pub fn host_key(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V6(v6) => {
            let mut segments = v6.segments();
            segments[4..].fill(0);
            IpAddr::V6(Ipv6Addr::from(segments))
        }
        v4 => v4,
    }
}

/// Whether to log a refusal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Report {
    /// Log it: the first of a burst of its address. `before`: how many the
    /// address's last burst for this reason refused (0: none known).
    Log {
        /// The last burst's refusals.
        before: u64,
    },
    /// Log it: the first refusal of an address beyond [`CAPACITY`] in a
    /// flood from many addresses; further ones share its burst.
    LogMany,
    /// Counted, not logged: a later refusal of a burst already logged.
    Quiet,
}

#[derive(Debug, Clone, Copy)]
struct Burst {
    last: Instant,
    count: u64,
}

/// The bursts of refusals, per address and reason.
#[derive(Debug, Default)]
pub struct RefusalLog {
    bursts: HashMap<(IpAddr, Refused), Burst>,
    /// The shared burst of the addresses beyond the capacity, per reason.
    many: HashMap<Refused, Burst>,
}

impl RefusalLog {
    /// A connection from `ip` was refused for `reason` at `now`: whether
    /// to log it.
    pub fn refused(&mut self, ip: IpAddr, reason: Refused, now: Instant) -> Report {
        let key = (host_key(ip), reason);
        if !self.bursts.contains_key(&key) && self.bursts.len() >= CAPACITY {
            self.bursts
                .retain(|_, b| now.saturating_duration_since(b.last) < QUIET);
            if self.bursts.len() >= CAPACITY {
                return match self.many.get_mut(&reason) {
                    Some(b) if now.saturating_duration_since(b.last) < QUIET => {
                        b.last = now;
                        b.count += 1;
                        Report::Quiet
                    }
                    _ => {
                        self.many.insert(
                            reason,
                            Burst {
                                last: now,
                                count: 1,
                            },
                        );
                        Report::LogMany
                    }
                };
            }
        }
        match self.bursts.get_mut(&key) {
            Some(b) if now.saturating_duration_since(b.last) < QUIET => {
                b.last = now;
                b.count += 1;
                Report::Quiet
            }
            Some(b) => {
                let before = b.count;
                *b = Burst {
                    last: now,
                    count: 1,
                };
                Report::Log { before }
            }
            None => {
                self.bursts.insert(
                    key,
                    Burst {
                        last: now,
                        count: 1,
                    },
                );
                Report::Log { before: 0 }
            }
        }
    }

    /// Addresses whose bursts are kept now.
    pub fn len(&self) -> usize {
        self.bursts.len()
    }

    /// True when no burst is kept.
    pub fn is_empty(&self) -> bool {
        self.bursts.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn a_burst_is_logged_once_and_the_next_says_how_many_it_held() {
        let mut log = RefusalLog::default();
        let t0 = Instant::now();
        let a = ip("10.1.2.3");
        assert_eq!(
            log.refused(a, Refused::PerAddress, t0),
            Report::Log { before: 0 }
        );
        // 499 more, each 10 ms after the last: one burst, kept quiet.
        let mut t = t0;
        for _ in 0..499 {
            t += Duration::from_millis(10);
            assert_eq!(log.refused(a, Refused::PerAddress, t), Report::Quiet);
        }
        // Another reason, another address: their own bursts.
        assert_eq!(log.refused(a, Refused::Limit, t), Report::Log { before: 0 });
        assert_eq!(
            log.refused(ip("10.1.2.4"), Refused::PerAddress, t),
            Report::Log { before: 0 }
        );
        // A minute of silence ends the burst; the next one says the count.
        t += QUIET;
        assert_eq!(
            log.refused(a, Refused::PerAddress, t),
            Report::Log { before: 500 }
        );
        assert_eq!(log.len(), 3);
    }

    #[test]
    fn an_ipv6_host_is_one_address_whatever_its_interface_id() {
        let mut log = RefusalLog::default();
        let t = Instant::now();
        assert_eq!(
            log.refused(ip("2001:db8:1:2::1"), Refused::NotAllowed, t),
            Report::Log { before: 0 }
        );
        assert_eq!(
            log.refused(ip("2001:db8:1:2:ffff::7"), Refused::NotAllowed, t),
            Report::Quiet
        );
        assert_eq!(
            log.refused(ip("2001:db8:1:3::1"), Refused::NotAllowed, t),
            Report::Log { before: 0 }
        );
        assert_eq!(host_key(ip("::ffff:10.0.0.1")), ip("10.0.0.1"));
        assert_eq!(host_key(ip("10.0.0.1")), ip("10.0.0.1"));
    }

    #[test]
    fn a_flood_from_many_addresses_is_bounded() {
        let mut log = RefusalLog::default();
        let t = Instant::now();
        let mut logged = 0;
        for i in 0..(CAPACITY as u32 + 5000) {
            let a = IpAddr::from((0x0A00_0000u32 + i).to_be_bytes());
            if log.refused(a, Refused::NotAllowed, t) != Report::Quiet {
                logged += 1;
            }
        }
        // One line per kept address, one for all the others.
        assert_eq!(logged, CAPACITY + 1);
        assert_eq!(log.len(), CAPACITY);
        // Once the kept bursts are over, new addresses get their own again.
        let later = t + QUIET;
        assert_eq!(
            log.refused(ip("192.168.9.9"), Refused::NotAllowed, later),
            Report::Log { before: 0 }
        );
        assert_eq!(log.len(), 1);
    }
}
