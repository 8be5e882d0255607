//! The core's clock: the time the lease driver decides at, the wall-clock
//! time the safety journal keeps a deadline as, and the sleep until the
//! next deadline. In the daemon it is the system's. The model of the core
//! (`control/model/`, a test) turns it by hand, so that a random sequence
//! of leases, faults and restarts replays the same way every time, and an
//! hour of leases takes milliseconds.

use std::time::{Instant, SystemTime};

/// Where the core reads the time.
#[derive(Clone, Default)]
pub enum Clock {
    /// The system's clocks: monotonic for deadlines, the wall clock for
    /// the journal.
    #[default]
    System,
    /// Moved by hand (the model of the core).
    #[cfg(test)]
    Manual(std::sync::Arc<manual::Manual>),
}

impl Clock {
    /// Now.
    pub fn now(&self) -> Instant {
        match self {
            Clock::System => Instant::now(),
            #[cfg(test)]
            Clock::Manual(m) => m.now(),
        }
    }

    /// The wall-clock time of `at` (what survives a restart).
    pub fn wall(&self, at: Instant) -> SystemTime {
        match self {
            Clock::System => {
                let now = Instant::now();
                let wall = SystemTime::now();
                if at >= now {
                    wall + (at - now)
                } else {
                    wall.checked_sub(now - at).unwrap_or(wall)
                }
            }
            #[cfg(test)]
            Clock::Manual(m) => m.wall(at),
        }
    }

    /// The wall-clock time now.
    pub fn wall_now(&self) -> SystemTime {
        match self {
            Clock::System => SystemTime::now(),
            #[cfg(test)]
            Clock::Manual(m) => m.wall(m.now()),
        }
    }

    /// Sleeps until `at` (returns at once if it has passed).
    pub async fn sleep_until(&self, at: Instant) {
        match self {
            Clock::System => tokio::time::sleep_until(at.into()).await,
            #[cfg(test)]
            Clock::Manual(m) => m.sleep_until(at).await,
        }
    }
}

#[cfg(test)]
pub mod manual {
    //! A clock moved by hand: [`Manual::set`] moves it to an instant and
    //! wakes whoever sleeps until then; [`Manual::next_wake`] says when the
    //! next sleeper wants to wake, so a test moves it from wake to wake.

    use std::collections::BTreeMap;
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::{Duration, Instant, SystemTime};

    use tokio::sync::watch;

    /// A clock moved by hand, with a wall clock that moves with it.
    pub struct Manual {
        now: watch::Sender<Instant>,
        /// An instant and its wall-clock time.
        origin: (Instant, SystemTime),
        /// Sleeps in progress, by id: their deadlines.
        sleepers: Mutex<BTreeMap<u64, Instant>>,
        next_id: AtomicU64,
    }

    impl Manual {
        /// A clock at `wall` (in wall-clock time) now.
        pub fn new(wall: SystemTime) -> Self {
            let start = Instant::now();
            Manual {
                now: watch::Sender::new(start),
                origin: (start, wall),
                sleepers: Mutex::new(BTreeMap::new()),
                next_id: AtomicU64::new(0),
            }
        }

        /// Now.
        pub fn now(&self) -> Instant {
            *self.now.borrow()
        }

        /// The wall-clock time of `at`.
        pub fn wall(&self, at: Instant) -> SystemTime {
            let (origin, wall) = self.origin;
            if at >= origin {
                wall + (at - origin)
            } else {
                wall - (origin - at)
            }
        }

        /// Moves the clock to `at` (never back), waking the sleeps due.
        pub fn set(&self, at: Instant) {
            self.now.send_if_modified(|now| {
                let later = at > *now;
                if later {
                    *now = at;
                }
                later
            });
        }

        /// Moves the clock on by `by`.
        pub fn advance(&self, by: Duration) {
            self.set(self.now() + by);
        }

        /// The earliest deadline of a sleep in progress.
        pub fn next_wake(&self) -> Option<Instant> {
            let sleepers = self.sleepers.lock().unwrap_or_else(|p| p.into_inner());
            sleepers.values().min().copied()
        }

        /// Sleeps until the clock is moved to `at` or past it.
        pub async fn sleep_until(&self, at: Instant) {
            let id = self.next_id.fetch_add(1, Ordering::Relaxed);
            self.sleepers
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(id, at);
            let _registered = Registered { clock: self, id };
            let mut now = self.now.subscribe();
            // The sender lives as long as `self`: the wait ends by time.
            let _ = now.wait_for(|now| *now >= at).await;
        }
    }

    /// A sleep's deadline, taken back when the sleep ends or is dropped.
    struct Registered<'a> {
        clock: &'a Manual,
        id: u64,
    }

    impl Drop for Registered<'_> {
        fn drop(&mut self) {
            self.clock
                .sleepers
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .remove(&self.id);
        }
    }
}
