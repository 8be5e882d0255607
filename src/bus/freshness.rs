//! How fresh a drive's data is: one answer for every face, decided here
//! from what the bus knows (the port's state, the drive's last status and
//! its failed polls, how often it is polled), so the REST status, the
//! stream, `/readyz`, the metrics, MQTT and the console never disagree
//! about whether a value is live.
//!
//! - `live`: polled within its expected period;
//! - `stale`: polls missing for longer than that, not yet offline;
//! - `offline`: it stopped answering (`offline_after` failed polls);
//! - `never`: it has not answered once since its bus opened;
//! - `bus-down`: its bus's port is gone (the adapter unplugged, the serial
//!   device server unreachable), whatever the drive last said.
//!
//! [`judge`] is pure, with the time passed in; the cache gathers the facts
//! ([`Facts`]) and the handle asks at the moment a face wants to know.

use std::time::{Duration, Instant, SystemTime};

use serde::Serialize;

use super::link::{Link, PortState};
use crate::modbus::timing::LineTiming;

/// Room beyond a drive's poll period and a poll's own worst case before
/// its data counts as stale: a loaded machine may hold the bus thread back
/// for a while, and a value half a second late is no news to anyone.
pub const GRACE: Duration = Duration::from_secs(1);

/// The freshness of a drive's data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Freshness {
    /// Polled within its expected period.
    Live,
    /// Polls missing for longer than expected; not yet offline.
    Stale,
    /// The drive stopped answering.
    Offline,
    /// Not answered once since its bus opened.
    Never,
    /// Its bus's port is gone.
    BusDown,
}

impl Freshness {
    /// Every state, in order.
    pub const ALL: [Freshness; 5] = [
        Freshness::Live,
        Freshness::Stale,
        Freshness::Offline,
        Freshness::Never,
        Freshness::BusDown,
    ];

    /// Its name in the API, the stream, MQTT and the metrics.
    pub fn name(self) -> &'static str {
        match self {
            Freshness::Live => "live",
            Freshness::Stale => "stale",
            Freshness::Offline => "offline",
            Freshness::Never => "never",
            Freshness::BusDown => "bus-down",
        }
    }

    /// True only for `live`.
    pub fn is_live(self) -> bool {
        self == Freshness::Live
    }
}

/// Why the data is as fresh as it is, typed; [`Verdict::words`] says it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Cause {
    /// Live.
    Polled,
    /// Stale: the last status is older than the drive's poll period
    /// allows.
    Late {
        /// How often it is polled (0: as fast as the bus allows).
        period: Duration,
    },
    /// Offline after failed polls.
    NoAnswer {
        /// Failed polls in a row.
        failures: u32,
        /// The last failure, in words.
        last_failure: Option<String>,
    },
    /// Never answered: not polled yet.
    NotPolledYet,
    /// Never answered, though polled.
    NeverAnswered {
        /// Failed polls in a row.
        failures: u32,
        /// The last failure, in words.
        last_failure: Option<String>,
    },
    /// The port has not opened yet.
    PortNotOpen,
    /// The port is down.
    PortDown {
        /// Why, as the bus said it.
        reason: String,
    },
}

/// How often a drive is polled, and how long a poll may take at worst:
/// what its data's age is measured against.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Expected {
    /// Its poll interval, or (polled as fast as the bus allows) one round
    /// of the bus's drives, each poll after its share of commands: the
    /// longest it may wait for its next poll.
    pub period: Duration,
    /// Its poll interval, or one round of the bus's status polls alone at
    /// the line's shortest silences: how often it is polled on a bus that
    /// nothing else uses, never later than it can be. Its OPC UA
    /// variables' minimum sampling interval.
    pub poll: Duration,
    /// The longest one poll may take (every attempt timing out), plus
    /// [`GRACE`].
    pub slack: Duration,
}

impl Expected {
    /// For a drive polled every `interval` (zero: round robin at full
    /// rate) on a bus of `drives` drives at `line`, whose shortest silence
    /// between two frames is `silence` (t3.5 with `interframe = "spec"`),
    /// where commands may take `poll_share` transactions for each poll,
    /// with `attempts` of `response_timeout` each per poll.
    pub fn new(
        interval: Duration,
        (drives, poll_share): (usize, u32),
        (line, silence): (LineTiming, Duration),
        attempts: u32,
        response_timeout: Duration,
    ) -> Self {
        // A status poll: 8 bytes out, 19 back, the silences and a
        // drive's millisecond to think; a round of the bus's drives, each
        // poll after as many commands as the poll share lets go first.
        let one = line.transaction_time(8, 19, Duration::from_millis(1));
        let polls = u32::try_from(drives.max(1)).unwrap_or(u32::MAX);
        let round = one * polls * poll_share.saturating_add(1);
        // The same round without commands: each poll its two frames on the
        // wire and the silence before its request, the drive answering at
        // once. No two polls of a drive are closer than that.
        let fastest = (line.wire_time(8 + 19) + silence) * polls;
        Expected {
            period: interval.max(round),
            poll: interval.max(fastest),
            slack: response_timeout * attempts.max(1) + GRACE,
        }
    }

    /// The oldest a value may be and still be live.
    pub fn allowance(&self) -> Duration {
        self.period + self.slack
    }
}

/// What the bus knows of one drive, for [`judge`].
#[derive(Debug, Clone, PartialEq)]
pub struct Facts {
    /// When its last good status was read (wall clock), if ever.
    pub seen_at: Option<SystemTime>,
    /// The same, monotonic: what its age is measured with.
    pub seen_instant: Option<Instant>,
    /// Answering or not.
    pub link: Link,
    /// Failed polls in a row.
    pub failures: u32,
    /// When it was marked offline.
    pub offline_since: Option<SystemTime>,
    /// The last failure, in words.
    pub last_failure: Option<String>,
}

/// The freshness of one drive's data at one moment, with why and since
/// when.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The state.
    pub freshness: Freshness,
    /// Since when the data has not been live (for `never`: since the bus
    /// opened); `None` when live, or when not known.
    pub since: Option<SystemTime>,
    /// Age of the last value; `None` when there is none.
    pub age: Option<Duration>,
    /// Why.
    pub cause: Cause,
    /// When a live value turns stale if no new one comes.
    pub stale_at: Option<Instant>,
}

/// The freshness of a drive's data at `now`, from its bus's port state,
/// what the bus knows of it, and how often it is polled.
pub fn judge(port: &PortState, facts: &Facts, expected: Expected, now: Instant) -> Verdict {
    let age = facts.seen_instant.map(|t| now.saturating_duration_since(t));
    let verdict = |freshness, since, cause| Verdict {
        freshness,
        since,
        age,
        cause,
        stale_at: None,
    };
    let opened = match port {
        PortState::Down { since, reason } => {
            return verdict(
                Freshness::BusDown,
                Some(*since),
                Cause::PortDown {
                    reason: reason.clone(),
                },
            );
        }
        PortState::Opening => None,
        PortState::Up { since } => Some(*since),
    };
    if facts.seen_instant.is_none() {
        let cause = if opened.is_none() {
            Cause::PortNotOpen
        } else if facts.failures == 0 && facts.link == Link::Unknown {
            Cause::NotPolledYet
        } else {
            Cause::NeverAnswered {
                failures: facts.failures,
                last_failure: facts.last_failure.clone(),
            }
        };
        return verdict(Freshness::Never, opened, cause);
    }
    if facts.link == Link::Offline {
        return verdict(
            Freshness::Offline,
            facts.offline_since,
            Cause::NoAnswer {
                failures: facts.failures,
                last_failure: facts.last_failure.clone(),
            },
        );
    }
    let allowance = expected.allowance();
    if age.is_some_and(|a| a > allowance) {
        return verdict(
            Freshness::Stale,
            facts.seen_at.map(|t| t + allowance),
            Cause::Late {
                period: expected.period,
            },
        );
    }
    Verdict {
        stale_at: facts.seen_instant.map(|t| t + allowance),
        ..verdict(Freshness::Live, None, Cause::Polled)
    }
}

impl Verdict {
    /// Why the data is not live, in a plant engineer's words (`None` when
    /// live), for drive `unit` of bus `bus` at `baud`.
    pub fn words(&self, bus: &str, unit: u8, baud: u32) -> Option<String> {
        let failed = |failures: u32, last: &Option<String>| {
            let polls = if failures == 1 { "poll" } else { "polls" };
            match last {
                Some(why) => format!("{failures} {polls} failed, the last: {why}"),
                None => format!("{failures} {polls} failed"),
            }
        };
        Some(match &self.cause {
            Cause::Polled => return None,
            // No age: it grows, and the words are told once, when the
            // data turns stale (the age is a field of its own).
            Cause::Late { period } => {
                let every = if period.is_zero() {
                    "as often as the bus allows".to_string()
                } else {
                    format!("every {}", seconds(*period))
                };
                format!(
                    "polls missing: the drive is polled {every}, and its last status is \
                     older than that and a poll's own time allow"
                )
            }
            Cause::NoAnswer {
                failures,
                last_failure,
            } => format!(
                "the drive stopped answering ({})",
                failed(*failures, last_failure)
            ),
            Cause::NotPolledYet => "not polled yet".to_string(),
            // No count: it grows with every poll, and the words are
            // told once, when the drive is first polled in vain.
            Cause::NeverAnswered { last_failure, .. } => {
                let last = last_failure
                    .as_ref()
                    .map_or_else(String::new, |why| format!(" (the last poll: {why})"));
                format!(
                    "no answer since bus {bus} opened{last}: check the baud rate (the bus \
                     runs at {baud} baud) and the unit address ({unit}), then the drive's \
                     power and wiring"
                )
            }
            Cause::PortNotOpen => format!("bus {bus}'s port is not open yet"),
            Cause::PortDown { reason } => format!("bus {bus} is down: {reason}"),
        })
    }
}

/// A duration as a person reads it: "250 ms", "1.5 s", "12 s".
fn seconds(d: Duration) -> String {
    let ms = d.as_millis();
    if ms < 1000 {
        format!("{ms} ms")
    } else if ms < 10_000 {
        format!("{:.1} s", d.as_secs_f64())
    } else {
        format!("{} s", d.as_secs())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXPECTED: Expected = Expected {
        period: Duration::from_secs(1),
        poll: Duration::from_secs(1),
        slack: Duration::from_millis(600),
    };

    fn up(at: SystemTime) -> PortState {
        PortState::Up { since: at }
    }

    fn answered(at: Instant, wall: SystemTime) -> Facts {
        Facts {
            seen_at: Some(wall),
            seen_instant: Some(at),
            link: Link::Online,
            failures: 0,
            offline_since: None,
            last_failure: None,
        }
    }

    fn never() -> Facts {
        Facts {
            seen_at: None,
            seen_instant: None,
            link: Link::Unknown,
            failures: 0,
            offline_since: None,
            last_failure: None,
        }
    }

    #[test]
    fn a_value_is_live_within_its_period_and_slack_then_stale() {
        let (t0, wall) = (Instant::now(), SystemTime::now());
        let facts = answered(t0, wall);
        let live = judge(
            &up(wall),
            &facts,
            EXPECTED,
            t0 + Duration::from_millis(1600),
        );
        assert_eq!(live.freshness, Freshness::Live);
        assert_eq!(live.age, Some(Duration::from_millis(1600)));
        assert_eq!(live.since, None);
        assert_eq!(live.stale_at, Some(t0 + Duration::from_millis(1600)));
        assert_eq!(live.words("line1", 1, 115_200), None);

        // A failed poll within the allowance does not make it stale.
        let one_failure = Facts {
            failures: 1,
            ..facts.clone()
        };
        let still = judge(
            &up(wall),
            &one_failure,
            EXPECTED,
            t0 + Duration::from_secs(1),
        );
        assert_eq!(still.freshness, Freshness::Live);

        let stale = judge(
            &up(wall),
            &one_failure,
            EXPECTED,
            t0 + Duration::from_millis(2500),
        );
        assert_eq!(stale.freshness, Freshness::Stale);
        assert_eq!(stale.since, Some(wall + Duration::from_millis(1600)));
        assert_eq!(stale.age, Some(Duration::from_millis(2500)));
        assert_eq!(stale.stale_at, None);
        assert_eq!(
            stale.words("line1", 1, 115_200).as_deref(),
            Some(
                "polls missing: the drive is polled every 1.0 s, and its last status is older \
                 than that and a poll's own time allow"
            )
        );
    }

    #[test]
    fn offline_and_bus_down_keep_the_age_of_the_last_value() {
        let (t0, wall) = (Instant::now(), SystemTime::now());
        let went = wall + Duration::from_secs(2);
        let offline = Facts {
            link: Link::Offline,
            failures: 3,
            offline_since: Some(went),
            last_failure: Some("no reply within 50 ms".into()),
            ..answered(t0, wall)
        };
        // Offline wins over the age: it is not merely late.
        let v = judge(
            &up(wall),
            &offline,
            EXPECTED,
            t0 + Duration::from_millis(100),
        );
        assert_eq!(v.freshness, Freshness::Offline);
        assert_eq!(v.since, Some(went));
        assert_eq!(v.age, Some(Duration::from_millis(100)));
        assert_eq!(
            v.words("line1", 2, 115_200).as_deref(),
            Some("the drive stopped answering (3 polls failed, the last: no reply within 50 ms)")
        );

        // The port gone wins over everything, a live value included.
        let down_at = wall + Duration::from_secs(5);
        let down = PortState::Down {
            since: down_at,
            reason: "serial port /dev/ttyUSB0 failed: gone".into(),
        };
        for facts in [answered(t0, wall), offline, never()] {
            let v = judge(&down, &facts, EXPECTED, t0 + Duration::from_millis(10));
            assert_eq!(v.freshness, Freshness::BusDown);
            assert_eq!(v.since, Some(down_at));
            assert_eq!(v.age.is_some(), facts.seen_instant.is_some());
            assert_eq!(
                v.words("line1", 1, 115_200).as_deref(),
                Some("bus line1 is down: serial port /dev/ttyUSB0 failed: gone")
            );
        }
    }

    #[test]
    fn a_drive_that_never_answered_is_never_whatever_its_link() {
        let (t0, wall) = (Instant::now(), SystemTime::now());
        let v = judge(&up(wall), &never(), EXPECTED, t0);
        assert_eq!(
            (v.freshness, &v.cause),
            (Freshness::Never, &Cause::NotPolledYet)
        );
        assert_eq!(v.since, Some(wall));
        assert_eq!(v.age, None);

        // Polled, never answered, marked offline: still "never", which is
        // what tells a wrong baud rate or address from a drive that died.
        let silent = Facts {
            link: Link::Offline,
            failures: 3,
            offline_since: Some(wall),
            last_failure: Some("no reply within 50 ms".into()),
            ..never()
        };
        let v = judge(&up(wall), &silent, EXPECTED, t0 + Duration::from_secs(3));
        assert_eq!(v.freshness, Freshness::Never);
        assert_eq!(v.since, Some(wall));
        let words = v.words("line1", 3, 11_520).unwrap();
        assert!(
            words.starts_with(
                "no answer since bus line1 opened (the last poll: no reply within 50 ms): "
            ) && words.contains("the baud rate (the bus runs at 11520 baud)")
                && words.contains("the unit address (3)"),
            "{words}"
        );

        // Before the port ever opened.
        let v = judge(&PortState::Opening, &never(), EXPECTED, t0);
        assert_eq!((v.freshness, v.since), (Freshness::Never, None));
        assert_eq!(
            v.words("line1", 1, 115_200).as_deref(),
            Some("bus line1's port is not open yet")
        );
    }

    #[test]
    fn the_period_is_the_interval_or_a_round_of_the_bus_and_the_poll_its_fastest() {
        let line = LineTiming::new_8n1(115_200);
        let timeout = Duration::from_millis(50);
        let spec = (line, line.t3_5());
        let slow = Expected::new(Duration::from_secs(1), (8, 4), spec, 2, timeout);
        assert_eq!(slow.period, Duration::from_secs(1));
        assert_eq!(slow.poll, Duration::from_secs(1));
        assert_eq!(slow.slack, Duration::from_millis(1100));
        // At full rate: one round of eight status polls, each after four
        // commands at most, about 275 ms.
        let fast = Expected::new(Duration::ZERO, (8, 4), spec, 2, timeout);
        assert!(
            fast.period > Duration::from_millis(230) && fast.period < Duration::from_millis(320),
            "{:?}",
            fast.period
        );
        // Polled alone, eight drives take at least 8 x 4.09 ms (27 bytes
        // and a t3.5 each) a round; with shorter silences (interframe
        // "auto" trying 1.5 characters), less.
        assert_eq!(fast.poll, Duration::from_micros(32_750));
        let auto = Expected::new(
            Duration::ZERO,
            (8, 4),
            (line, line.char_time() * 3 / 2),
            2,
            timeout,
        );
        assert!(auto.poll < Duration::from_millis(20), "{:?}", auto.poll);
        // At 9600 baud a round of thirty drives takes seconds.
        let long = Expected::new(
            Duration::ZERO,
            (30, 4),
            (LineTiming::new_8n1(9600), LineTiming::new_8n1(9600).t3_5()),
            1,
            timeout,
        );
        assert!(long.period > Duration::from_secs(5), "{:?}", long.period);
        assert!(long.poll < long.period, "{:?}", long.poll);
    }

    #[test]
    fn names_are_the_apis() {
        let names: Vec<&str> = Freshness::ALL.iter().map(|f| f.name()).collect();
        assert_eq!(names, ["live", "stale", "offline", "never", "bus-down"]);
        for f in Freshness::ALL {
            assert_eq!(serde_json::to_value(f).unwrap(), f.name());
        }
        assert!(Freshness::Live.is_live() && !Freshness::Stale.is_live());
    }
}
