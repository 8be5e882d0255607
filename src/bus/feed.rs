//! Each of a bus's events handed to everyone above who follows them, in
//! one task: a poll costs one wake-up of the daemon's runtime, not one per
//! follower (the history, the alarms, the freshness, the stream, the OPC UA
//! address space each woke a task of its own on another thread, and each
//! wake-up cost more than the follower's work).
//!
//! A [`BusFollower`] is called in that task, in the order the events came,
//! after the others: it must not wait (it takes a lock at most, never an
//! await). The task takes, at each wake-up, every event that came
//! meanwhile, so a runtime that was busy elsewhere catches up in one.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{Notify, broadcast};
use tokio_util::sync::CancellationToken;

use super::cache::BusEvent;

/// Follows a bus's events from above it.
pub trait BusFollower: Send + Sync {
    /// An event of the bus (a status polled or read, a drive online or
    /// offline, the port up or down), in order. Must not wait.
    fn event(&self, event: &BusEvent);
    /// `missed` events were lost: the runtime was starved of CPU for a
    /// thousand of them.
    fn lagged(&self, missed: u64) {
        let _ = missed;
    }
}

type Entry = (u64, Arc<dyn BusFollower>, CancellationToken);

/// The followers of one bus and the task that calls them.
#[derive(Default)]
pub struct Feed {
    followers: Mutex<Vec<Entry>>,
    /// Bumped at each change of `followers`, so the task copies the list
    /// only then (not at every event).
    version: AtomicU64,
    next_id: AtomicU64,
    /// The task was started (at the first follower).
    started: AtomicBool,
    /// Tells the task the list changed (a follower that stopped must not
    /// wait for the next event to be let go: it may hold the bus).
    changed: Notify,
}

impl Feed {
    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Entry>> {
        self.followers.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn changed(&self) {
        self.version.fetch_add(1, Ordering::Release);
        self.changed.notify_one();
    }

    /// Adds `follower` until `stop` fires. `subscribe` gives the task its
    /// receiver when this is the first follower; called in a tokio runtime
    /// (outside one, nothing is followed: a tool without a daemon).
    pub fn follow(
        self: &Arc<Self>,
        follower: Arc<dyn BusFollower>,
        stop: CancellationToken,
        subscribe: impl FnOnce() -> broadcast::Receiver<BusEvent>,
    ) {
        if tokio::runtime::Handle::try_current().is_err() {
            return;
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        self.lock().push((id, follower, stop.clone()));
        self.changed();
        if !self.started.swap(true, Ordering::AcqRel) {
            tokio::spawn(run(self.clone(), subscribe()));
        }
        let feed = self.clone();
        tokio::spawn(async move {
            stop.cancelled().await;
            feed.lock().retain(|(i, _, _)| *i != id);
            feed.changed();
        });
    }

    /// How many follow the bus now.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// True when nobody follows the bus.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The task: every event to every follower still following.
async fn run(feed: Arc<Feed>, mut rx: broadcast::Receiver<BusEvent>) {
    let mut seen = u64::MAX;
    let mut followers: Vec<Entry> = Vec::new();
    loop {
        let first = tokio::select! {
            biased;
            () = feed.changed.notified() => None,
            e = rx.recv() => Some(e),
        };
        let version = feed.version.load(Ordering::Acquire);
        if version != seen {
            seen = version;
            followers.clone_from(&feed.lock());
        }
        followers.retain(|(_, _, stop)| !stop.is_cancelled());
        let Some(mut next) = first else { continue };
        // This event, then whatever else came meanwhile.
        loop {
            match next {
                Ok(event) => {
                    for (_, f, _) in &followers {
                        f.event(&event);
                    }
                }
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    for (_, f, _) in &followers {
                        f.lagged(n);
                    }
                }
                Err(broadcast::error::RecvError::Closed) => return,
            }
            next = match rx.try_recv() {
                Ok(e) => Ok(e),
                Err(broadcast::error::TryRecvError::Empty) => break,
                Err(broadcast::error::TryRecvError::Lagged(n)) => {
                    Err(broadcast::error::RecvError::Lagged(n))
                }
                Err(broadcast::error::TryRecvError::Closed) => {
                    Err(broadcast::error::RecvError::Closed)
                }
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[derive(Default)]
    struct Seen(Mutex<Vec<u8>>, AtomicU64);

    impl BusFollower for Seen {
        fn event(&self, event: &BusEvent) {
            if let BusEvent::Online { unit, .. } = event {
                self.0.lock().unwrap().push(*unit);
            }
        }
        fn lagged(&self, missed: u64) {
            self.1.fetch_add(missed, Ordering::Relaxed);
        }
    }

    fn online(unit: u8) -> BusEvent {
        BusEvent::Online {
            bus: "line1".into(),
            unit,
        }
    }

    async fn until(what: impl Fn() -> bool) {
        let t0 = std::time::Instant::now();
        while !what() {
            assert!(t0.elapsed() < Duration::from_secs(10), "never happened");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    #[tokio::test]
    async fn every_follower_sees_every_event_in_order_until_it_stops() {
        let (tx, _) = broadcast::channel(16);
        let feed = Arc::new(Feed::default());
        let (a, b) = (Arc::new(Seen::default()), Arc::new(Seen::default()));
        let (stop_a, stop_b) = (CancellationToken::new(), CancellationToken::new());
        feed.follow(a.clone(), stop_a.clone(), || tx.subscribe());
        feed.follow(b.clone(), stop_b.clone(), || unreachable!("one task"));
        for unit in 1..=3 {
            tx.send(online(unit)).unwrap();
        }
        until(|| a.0.lock().unwrap().len() == 3 && b.0.lock().unwrap().len() == 3).await;
        assert_eq!(*a.0.lock().unwrap(), [1, 2, 3]);
        assert_eq!(*b.0.lock().unwrap(), [1, 2, 3]);
        // A follower that stopped is let go at once, without an event.
        stop_a.cancel();
        until(|| feed.len() == 1).await;
        until(|| Arc::strong_count(&a) == 1).await;
        tx.send(online(4)).unwrap();
        until(|| b.0.lock().unwrap().len() == 4).await;
        assert_eq!(a.0.lock().unwrap().len(), 3);
    }

    #[tokio::test]
    async fn a_follower_is_told_what_it_missed() {
        let (tx, _) = broadcast::channel(2);
        let feed = Arc::new(Feed::default());
        let seen = Arc::new(Seen::default());
        // Current thread: the task cannot run before all five are sent.
        feed.follow(seen.clone(), CancellationToken::new(), || tx.subscribe());
        for unit in 1..=5 {
            tx.send(online(unit)).unwrap();
        }
        until(|| seen.0.lock().unwrap().len() == 2).await;
        assert_eq!(*seen.0.lock().unwrap(), [4, 5]);
        assert_eq!(seen.1.load(Ordering::Relaxed), 3);
    }
}
