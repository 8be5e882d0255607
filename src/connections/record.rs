//! What a listener turned away, kept for the metrics and the console: the
//! refusals by reason, the connections closed to make room, and per
//! address, for a bounded number of addresses (the first [`NAMED`] turned
//! away have series of their own; the others are counted together as
//! `other`, so a flood from many addresses cannot grow `/metrics`), and
//! the last bursts, for the console's overview. Pure: time is passed in.

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use super::budget::Refused;

/// Addresses with series of their own.
pub const NAMED: usize = 16;

/// Bursts kept for the console.
pub const RECENT: usize = 8;

/// A burst of one address ends after this long without a refusal.
pub const BURST_GAP: Duration = Duration::from_secs(60);

/// What happened to a connection turned away.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Turned {
    /// Refused at connect, for a reason.
    Refused(Refused),
    /// Closed to make room for another address.
    Closed,
}

/// What one address had turned away (since the listener started).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counts {
    /// Connections refused.
    pub refused: u64,
    /// Connections closed to make room.
    pub closed: u64,
}

/// A burst of one address: what happened, how often, since and until when.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Burst {
    /// The address (IPv6: its /64).
    pub address: IpAddr,
    /// What happened, the last time.
    pub turned: Turned,
    /// Connections of the burst.
    pub count: u64,
    /// Its first.
    pub since: Instant,
    /// Its last.
    pub last: Instant,
}

/// What a listener turned away.
#[derive(Debug, Default, Clone)]
pub struct Record {
    reasons: HashMap<Refused, u64>,
    closed: u64,
    named: HashMap<IpAddr, Counts>,
    other: Counts,
    recent: Vec<Burst>,
}

impl Record {
    /// A connection of `address` turned away at `now`.
    pub fn note(&mut self, address: IpAddr, turned: Turned, now: Instant) {
        let counts = if self.named.contains_key(&address) || self.named.len() < NAMED {
            self.named.entry(address).or_default()
        } else {
            &mut self.other
        };
        match turned {
            Turned::Refused(reason) => {
                counts.refused += 1;
                *self.reasons.entry(reason).or_insert(0) += 1;
            }
            Turned::Closed => {
                counts.closed += 1;
                self.closed += 1;
            }
        }
        match self
            .recent
            .iter_mut()
            .find(|b| b.address == address && now.saturating_duration_since(b.last) < BURST_GAP)
        {
            Some(b) => {
                b.count += 1;
                b.last = now;
                b.turned = turned;
            }
            None => {
                if self.recent.len() >= RECENT {
                    // The burst that ended the longest ago makes way.
                    if let Some(oldest) = self
                        .recent
                        .iter()
                        .enumerate()
                        .min_by_key(|(_, b)| b.last)
                        .map(|(i, _)| i)
                    {
                        self.recent.remove(oldest);
                    }
                }
                self.recent.push(Burst {
                    address,
                    turned,
                    count: 1,
                    since: now,
                    last: now,
                });
            }
        }
    }

    /// Refusals for `reason`.
    pub fn refused(&self, reason: Refused) -> u64 {
        self.reasons.get(&reason).copied().unwrap_or(0)
    }

    /// Connections closed to make room.
    pub fn closed(&self) -> u64 {
        self.closed
    }

    /// Per address, the named ones and `None` for the others together.
    pub fn by_address(&self) -> Vec<(Option<IpAddr>, Counts)> {
        let mut all: Vec<(Option<IpAddr>, Counts)> =
            self.named.iter().map(|(a, c)| (Some(*a), *c)).collect();
        all.sort_by_key(|(a, _)| *a);
        all.push((None, self.other));
        all
    }

    /// The bursts, the latest first.
    pub fn recent(&self) -> Vec<Burst> {
        let mut out = self.recent.clone();
        out.sort_by_key(|b| std::cmp::Reverse(b.last));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_beyond_the_named_ones_are_counted_together() {
        let mut r = Record::default();
        let t = Instant::now();
        for i in 0..1000u32 {
            let a = IpAddr::from((0x0A00_0000 + i).to_be_bytes());
            r.note(a, Turned::Refused(Refused::Limit), t);
            r.note(a, Turned::Refused(Refused::Limit), t);
        }
        let by = r.by_address();
        assert_eq!(by.len(), NAMED + 1);
        assert_eq!(
            by.last().unwrap(),
            &(
                None,
                Counts {
                    refused: 1968,
                    closed: 0
                }
            )
        );
        assert_eq!(by[0].1.refused, 2);
        assert_eq!(r.refused(Refused::Limit), 2000);
        assert_eq!(r.recent().len(), RECENT);
    }

    #[test]
    fn a_burst_counts_until_its_address_is_quiet() {
        let mut r = Record::default();
        let t = Instant::now();
        let a: IpAddr = "10.0.0.5".parse().unwrap();
        for i in 0..12 {
            r.note(
                a,
                Turned::Refused(Refused::Limit),
                t + Duration::from_millis(i),
            );
        }
        r.note("10.0.0.66".parse().unwrap(), Turned::Closed, t);
        let recent = r.recent();
        assert_eq!(recent[0].address, a);
        assert_eq!(recent[0].count, 12);
        assert_eq!(r.closed(), 1);
        // A minute later: a new burst.
        r.note(
            a,
            Turned::Refused(Refused::Heaviest),
            t + BURST_GAP + Duration::from_secs(1),
        );
        let recent = r.recent();
        assert_eq!(
            (recent[0].count, recent[0].turned),
            (1, Turned::Refused(Refused::Heaviest))
        );
        assert_eq!(recent.len(), 3);
    }
}
