//! The listeners' connections as `/readyz` and the console's overview show
//! them: where a face listens, the connections it holds, and what it
//! turned away lately, per address, in words ("12 connections from
//! 10.0.0.5 refused: the listener was full"). Read from the budget's book
//! (`crate::connections`), which the log and `/metrics` read too.

use std::time::{Duration, Instant, SystemTime};

use serde::Serialize;
use utoipa::ToSchema;

use crate::connections::record::Turned;
use crate::connections::{Face, View};
use crate::metrics::Metrics;

/// Bursts older than this are not shown.
const SHOWN_FOR: Duration = Duration::from_secs(600);

/// A listener in `/readyz`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct ListenerReadiness {
    /// Where it listens.
    pub listen: String,
    /// Connections open now.
    pub connections: usize,
    /// The most it serves at once (`max_connections`).
    pub max_connections: usize,
    /// Connections held per address, the heaviest first (at most 8).
    pub holders: Vec<Holder>,
    /// Addresses whose connections were refused or closed in the last ten
    /// minutes, the latest first: it never makes drivegate unready.
    pub turned_away: Vec<TurnedAway>,
}

/// An address and the connections it holds.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Holder {
    /// The address (an IPv6 host by its /64).
    pub address: String,
    /// Connections it holds.
    pub connections: usize,
}

/// A burst of connections of one address turned away.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct TurnedAway {
    /// The address (an IPv6 host by its /64).
    pub address: String,
    /// Connections of the burst.
    pub count: u64,
    /// `refused`, or `closed` (to make room for other addresses).
    pub what: String,
    /// Why: `limit`, `heaviest`, `per_address`, `files` (the reasons of
    /// `drivegate_connections_refused_total`), or `made_room`.
    pub reason: String,
    /// The whole line: "12 connections from 10.0.0.5 refused: the
    /// listener was full".
    pub text: String,
    /// The burst's last connection (RFC 3339).
    pub last: String,
}

/// The listener of `face`, if it runs.
pub fn readiness(metrics: &Metrics, face: Face) -> Option<ListenerReadiness> {
    let view = metrics.listeners().view(face)?;
    Some(of(&view, Instant::now(), SystemTime::now()))
}

/// `view` in `/readyz`'s words, at `now` (`wall`: the same moment).
pub fn of(view: &View, now: Instant, wall: SystemTime) -> ListenerReadiness {
    let unit = view.face.unit;
    ListenerReadiness {
        listen: view.bound.map_or_else(String::new, |b| b.to_string()),
        connections: view.held,
        max_connections: view.limits.max,
        holders: view
            .holders
            .iter()
            .take(8)
            .map(|(a, n)| Holder {
                address: a.to_string(),
                connections: *n,
            })
            .collect(),
        turned_away: view
            .recent
            .iter()
            .filter(|b| now.saturating_duration_since(b.last) < SHOWN_FOR)
            .map(|b| {
                let (what, reason) = match b.turned {
                    Turned::Refused(r) => ("refused", r.label()),
                    Turned::Closed => ("closed", "made_room"),
                };
                let plural = if b.count == 1 { "" } else { "s" };
                TurnedAway {
                    address: b.address.to_string(),
                    count: b.count,
                    what: what.to_string(),
                    reason: reason.to_string(),
                    text: format!(
                        "{} {unit}{plural} from {} {}",
                        b.count,
                        b.address,
                        crate::connections::words::turned_words(view.face, b.turned)
                    ),
                    last: crate::timestamp::rfc3339(wall - now.saturating_duration_since(b.last)),
                }
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::connections::words::MODBUS_TCP;
    use crate::connections::{Book, Limits};

    #[test]
    fn a_full_listener_says_who_was_refused() {
        let book = Book::new(false);
        let l = book.listener(
            MODBUS_TCP,
            Limits {
                max: 2,
                per_address: None,
            },
        );
        l.set_bound("127.0.0.1:5020".parse().unwrap());
        let a: std::net::IpAddr = "10.0.0.5".parse().unwrap();
        let b: std::net::IpAddr = "10.0.0.6".parse().unwrap();
        let _held = (l.admit(a).unwrap(), l.admit(b).unwrap());
        for _ in 0..12 {
            assert!(l.admit(a).is_err());
        }
        let r = of(&l.view(), Instant::now(), SystemTime::now());
        assert_eq!(
            (r.listen.as_str(), r.connections, r.max_connections),
            ("127.0.0.1:5020", 2, 2)
        );
        assert_eq!(r.turned_away.len(), 1);
        assert_eq!(
            r.turned_away[0].text,
            "12 connections from 10.0.0.5 refused: the listener was full"
        );
        assert_eq!(r.turned_away[0].reason, "limit");
        assert_eq!(r.holders.len(), 2);
    }
}
