//! A warning that repeats is written once per cause and second at most,
//! with a count, and less often the longer it goes on: the first at once
//! (it names the key to change), the next after a second, then after 2, 4,
//! 8 ... up to [`SLOWEST`] between lines, each saying how many it stands
//! for. A cause quiet for [`QUIET`] starts over. So an accept loop failing
//! thousands of times a second writes a line a minute, not gigabytes, and
//! a listener's refusals of one address write one line per burst.
//!
//! Every repeated warning of the listeners goes through this (refusals,
//! connections closed to make room, accept errors). The book is bounded:
//! beyond [`CAPACITY`] causes (a flood from many addresses) further ones
//! share one. Pure: time is passed in.

use std::collections::HashMap;
use std::hash::Hash;
use std::time::{Duration, Instant};

/// The least time between two lines of one cause.
pub const FASTEST: Duration = Duration::from_secs(1);

/// The most time between two lines of a cause that goes on.
pub const SLOWEST: Duration = Duration::from_secs(60);

/// Silence that ends a cause's burst: its next occurrence is written at
/// once, as a new burst.
pub const QUIET: Duration = Duration::from_secs(60);

/// Causes kept apart; more share one.
pub const CAPACITY: usize = 1024;

/// Whether to write a line now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Say {
    /// Write it: the first of a burst (`folded` 0, or how many the last
    /// burst of the cause held beyond its lines, when it was not said), or
    /// a repeat standing for `folded` occurrences since the last line,
    /// this one included.
    Line {
        /// Occurrences this line stands for beyond itself.
        folded: u64,
        /// True for the first line of a burst.
        first: bool,
    },
    /// Write one line for the causes beyond [`CAPACITY`]: `folded` of them
    /// since the last such line.
    Many {
        /// Occurrences since the last such line.
        folded: u64,
    },
    /// Counted, not written.
    Quiet,
}

#[derive(Debug, Clone, Copy)]
struct Burst {
    /// When the last line was written.
    said: Instant,
    /// The wait before the next line.
    gap: Duration,
    /// When the cause last occurred.
    last: Instant,
    /// Occurrences since the last line.
    unsaid: u64,
}

impl Burst {
    fn new(now: Instant) -> Self {
        Burst {
            said: now,
            gap: FASTEST,
            last: now,
            unsaid: 0,
        }
    }

    /// The cause occurred again at `now` (within its burst).
    fn again(&mut self, now: Instant) -> Option<u64> {
        self.last = now;
        self.unsaid += 1;
        if now.saturating_duration_since(self.said) < self.gap {
            return None;
        }
        let folded = self.unsaid - 1;
        self.said = now;
        self.unsaid = 0;
        self.gap = (self.gap * 2).min(SLOWEST);
        Some(folded)
    }
}

/// The bursts of each cause `K`.
#[derive(Debug)]
pub struct Repeats<K> {
    bursts: HashMap<K, Burst>,
    many: Option<Burst>,
}

impl<K> Default for Repeats<K> {
    fn default() -> Self {
        Repeats {
            bursts: HashMap::new(),
            many: None,
        }
    }
}

impl<K: Hash + Eq> Repeats<K> {
    /// `cause` occurred at `now`: whether to write its line.
    pub fn note(&mut self, cause: K, now: Instant) -> Say {
        if !self.bursts.contains_key(&cause) && self.bursts.len() >= CAPACITY {
            self.bursts
                .retain(|_, b| now.saturating_duration_since(b.last) < QUIET);
            if self.bursts.len() >= CAPACITY {
                return match &mut self.many {
                    Some(b) if now.saturating_duration_since(b.last) < QUIET => {
                        match b.again(now) {
                            Some(folded) => Say::Many { folded },
                            None => Say::Quiet,
                        }
                    }
                    _ => {
                        self.many = Some(Burst::new(now));
                        Say::Many { folded: 0 }
                    }
                };
            }
        }
        match self.bursts.get_mut(&cause) {
            Some(b) if now.saturating_duration_since(b.last) < QUIET => match b.again(now) {
                Some(folded) => Say::Line {
                    folded,
                    first: false,
                },
                None => Say::Quiet,
            },
            Some(b) => {
                let folded = b.unsaid;
                *b = Burst::new(now);
                Say::Line {
                    folded,
                    first: true,
                }
            }
            None => {
                self.bursts.insert(cause, Burst::new(now));
                Say::Line {
                    folded: 0,
                    first: true,
                }
            }
        }
    }

    /// Causes kept now.
    pub fn len(&self) -> usize {
        self.bursts.len()
    }

    /// True when no cause is kept.
    pub fn is_empty(&self) -> bool {
        self.bursts.is_empty()
    }
}

/// A book of repeats that the tasks of one listener share (a warning
/// written from each connection's task, such as a failed TLS handshake).
#[derive(Debug)]
pub struct Shared<K>(std::sync::Mutex<Repeats<K>>);

impl<K> Default for Shared<K> {
    fn default() -> Self {
        Shared(std::sync::Mutex::new(Repeats::default()))
    }
}

impl<K: Hash + Eq> Shared<K> {
    /// `cause` occurred now: the end of its line if one is due (empty, or
    /// how many it stands for), `None` when it is to stay quiet.
    pub fn due(&self, cause: K) -> Option<String> {
        let say = self
            .0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .note(cause, Instant::now());
        match say {
            Say::Quiet => None,
            Say::Line { folded, first } => Some(folded_words(folded, first)),
            Say::Many { folded } => Some(format!(
                " (from more than {CAPACITY} addresses at once; further ones are not logged){}",
                folded_words(folded, false)
            )),
        }
    }
}

/// The words a repeated line ends with: how many it stands for, or nothing.
pub fn folded_words(folded: u64, first: bool) -> String {
    match (folded, first) {
        (0, _) => String::new(),
        (n, false) => format!(" ({n} more like it since the last such line)"),
        (n, true) => format!(" (the last burst had {n} more, not logged)"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cause_failing_thousands_of_times_a_second_writes_a_line_a_minute() {
        let mut r = Repeats::default();
        let t0 = Instant::now();
        let mut lines = Vec::new();
        // An accept loop failing every millisecond for 10 minutes.
        let mut t = t0;
        let step = Duration::from_millis(1);
        let mut total = 0u64;
        while t < t0 + Duration::from_secs(600) {
            total += 1;
            if let Say::Line { folded, .. } = r.note("accept", t) {
                lines.push((t - t0, folded));
            }
            t += step;
        }
        // 0, 1, 3, 7, 15, 31, 63 s, then a minute apart.
        let at: Vec<u64> = lines.iter().take(8).map(|(d, _)| d.as_secs()).collect();
        assert_eq!(at, [0, 1, 3, 7, 15, 31, 63, 123]);
        assert!(lines.len() <= 16, "{} lines", lines.len());
        // Never two lines in one second; every occurrence accounted for.
        for w in lines.windows(2) {
            assert!(w[1].0 - w[0].0 >= FASTEST);
        }
        let said: u64 = lines.iter().map(|(_, f)| f + 1).sum();
        let last_line = lines.last().unwrap().0;
        let after = (Duration::from_secs(600) - last_line).as_millis() as u64;
        assert_eq!(said + after - 1, total);
    }

    #[test]
    fn a_burst_is_said_once_and_a_new_burst_says_what_the_last_kept() {
        let mut r = Repeats::default();
        let t0 = Instant::now();
        assert_eq!(
            r.note("10.1.2.3", t0),
            Say::Line {
                folded: 0,
                first: true
            }
        );
        // 499 more within half a second: quiet.
        for i in 1..500u64 {
            assert_eq!(
                r.note("10.1.2.3", t0 + Duration::from_millis(i)),
                Say::Quiet
            );
        }
        // Another cause has its own line.
        assert!(matches!(
            r.note("10.1.2.4", t0),
            Say::Line { first: true, .. }
        ));
        // A minute of silence: the next burst's first line says the 499.
        let later = t0 + Duration::from_millis(499) + QUIET;
        assert_eq!(
            r.note("10.1.2.3", later),
            Say::Line {
                folded: 499,
                first: true
            }
        );
        assert_eq!(
            folded_words(499, true),
            " (the last burst had 499 more, not logged)"
        );
        assert_eq!(folded_words(0, false), "");
        assert_eq!(r.len(), 2);
    }

    #[test]
    fn a_shared_book_says_the_first_and_keeps_the_rest_quiet() {
        let shared = Shared::default();
        assert_eq!(shared.due("10.0.0.1"), Some(String::new()));
        assert_eq!(shared.due("10.0.0.1"), None);
        assert_eq!(shared.due("10.0.0.2"), Some(String::new()));
    }

    #[test]
    fn a_flood_of_causes_is_bounded() {
        let mut r = Repeats::default();
        let t = Instant::now();
        let mut written = 0;
        for i in 0..(CAPACITY as u32 + 5000) {
            if r.note(i, t) != Say::Quiet {
                written += 1;
            }
        }
        assert_eq!(written, CAPACITY + 1);
        assert_eq!(r.len(), CAPACITY);
        // Once the kept bursts are over, new causes get their own again.
        assert!(matches!(
            r.note(u32::MAX, t + QUIET),
            Say::Line { first: true, .. }
        ));
        assert_eq!(r.len(), 1);
    }
}
