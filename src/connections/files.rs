//! The process's file descriptors, and the reserve kept of them: every
//! connection is a file, and a process out of files can neither accept a
//! client nor open its journal, its serial port or a log file. So the
//! listeners look at how many are open before they take one more.
//!
//! The limit is the process's `RLIMIT_NOFILE` (the packaged unit sets
//! 4,096). Two reserves are kept below it: the shared one (an eighth of
//! the limit, at least 32), in which the heaviest address of the process
//! is refused while the others still get in, and the last one (a
//! thirty-second, at least 16), kept for what is open: a new connection
//! gets in there only by making room (see [`super::budget`]).
//!
//! Counting `/proc/self/fd` costs a directory read, so it is done at most
//! every [`RECOUNT`]; in between, the connections the listeners opened and
//! closed since are added to the last count.

use std::time::{Duration, Instant};

use super::budget::Files;

/// The longest a count of the open files is used before it is made again.
pub const RECOUNT: Duration = Duration::from_millis(100);

/// Where the reserves begin, for a limit of `limit` files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Reserve {
    /// The process's limit.
    pub limit: usize,
    /// From this many open files, the heaviest address is refused.
    pub short_at: usize,
    /// From this many, only a lighter address gets in, by making room.
    pub exhausted_at: usize,
}

impl Reserve {
    /// The reserves below `limit`.
    pub fn of(limit: usize) -> Reserve {
        let shared = (limit / 8).max(32);
        let last = (limit / 32).max(16);
        Reserve {
            limit,
            short_at: limit.saturating_sub(shared),
            exhausted_at: limit.saturating_sub(last),
        }
    }

    /// How near `open` files are to the limit.
    pub fn judge(&self, open: usize) -> Files {
        if open >= self.exhausted_at {
            Files::Exhausted
        } else if open >= self.short_at {
            Files::Short
        } else {
            Files::Plenty
        }
    }
}

/// The process's soft limit of open files, if it can be read.
pub fn limit() -> Option<usize> {
    let (soft, _) =
        nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_NOFILE).ok()?;
    usize::try_from(soft).ok()
}

/// The files the process has open now, if `/proc` says.
pub fn count_open() -> Option<usize> {
    Some(std::fs::read_dir("/proc/self/fd").ok()?.count())
}

/// The last count of open files, and the connections held when it was
/// made: the estimate in between.
#[derive(Debug, Clone, Copy, Default)]
pub struct Estimate {
    at: Option<Instant>,
    open: usize,
    held: usize,
    reserve: Option<Reserve>,
}

impl Estimate {
    /// Whether the count is older than [`RECOUNT`] at `now`.
    pub fn stale(&self, now: Instant) -> bool {
        self.at
            .is_none_or(|at| now.saturating_duration_since(at) >= RECOUNT)
    }

    /// A new count: `open` files, while the listeners held `held`
    /// connections, under `limit`.
    pub fn counted(
        &mut self,
        now: Instant,
        open: Option<usize>,
        held: usize,
        limit: Option<usize>,
    ) {
        self.at = Some(now);
        if let Some(open) = open {
            self.open = open;
            self.held = held;
        }
        if let Some(limit) = limit {
            self.reserve = Some(Reserve::of(limit));
        }
    }

    /// The files open now, estimated from the last count and the
    /// connections held now.
    pub fn open(&self, held: usize) -> usize {
        (self.open + held).saturating_sub(self.held)
    }

    /// The reserves, once the limit was read.
    pub fn reserve(&self) -> Option<Reserve> {
        self.reserve
    }

    /// How near the process is to its limit with `held` connections.
    pub fn judge(&self, held: usize) -> Files {
        self.reserve
            .map_or(Files::Plenty, |r| r.judge(self.open(held)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reserves_of_common_limits() {
        let r = Reserve::of(1024);
        assert_eq!((r.short_at, r.exhausted_at), (896, 992));
        let r = Reserve::of(4096);
        assert_eq!((r.short_at, r.exhausted_at), (3584, 3968));
        // A tiny limit keeps the floors.
        let r = Reserve::of(64);
        assert_eq!((r.short_at, r.exhausted_at), (32, 48));
        assert_eq!(r.judge(31), Files::Plenty);
        assert_eq!(r.judge(32), Files::Short);
        assert_eq!(r.judge(48), Files::Exhausted);
    }

    #[test]
    fn between_counts_the_connections_opened_are_added() {
        let t = Instant::now();
        let mut e = Estimate::default();
        assert!(e.stale(t));
        assert_eq!(e.judge(5000), Files::Plenty, "no limit known");
        e.counted(t, Some(100), 40, Some(1024));
        assert!(!e.stale(t + Duration::from_millis(50)));
        assert!(e.stale(t + RECOUNT));
        assert_eq!(e.open(840), 900);
        assert_eq!(e.judge(840), Files::Short);
        assert_eq!(e.judge(40), Files::Plenty);
        assert_eq!(e.open(0), 60);
        // A count that fails keeps the last one.
        e.counted(t + RECOUNT, None, 0, None);
        assert_eq!(e.open(40), 100);
    }

    #[test]
    fn this_process_has_a_limit_and_open_files() {
        let limit = limit().expect("RLIMIT_NOFILE");
        let open = count_open().expect("/proc/self/fd");
        assert!(open >= 3 && open < limit, "{open} of {limit}");
    }
}
