//! The core follows how fresh each drive's data is and tells of every
//! change on its events ([`ControlEvent::Freshness`]): the stream, MQTT's
//! births and deaths and its retained statuses follow these, never a rule
//! of their own. What a state is, the bus decides
//! ([`crate::bus::freshness`]); here it is only watched: at every event of
//! a bus that may change it (a status of a drive not live, a drive
//! offline, the port down or up; as one of the bus's followers) and at the
//! moment a live value would turn stale if nothing new came, since no
//! event announces a poll that does not happen.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use super::events::{ControlEvent, Events};
pub use super::news::FreshnessNews;
use crate::bus::freshness::{Cause, Freshness, Verdict};
use crate::bus::{BusEvent, BusFollower, BusHandle};
use crate::plant::Plant;

/// Watches every bus of `plant` (and those a reload adds) until
/// `shutdown`, publishing each change on `events`.
pub(super) fn watch(plant: &Arc<Plant>, events: Arc<Events>, shutdown: &CancellationToken) {
    let watched = plant.clone();
    plant.for_each_bus(shutdown, move |slot, bus, stop| {
        let watcher = Arc::new(Watcher::new(
            watched.clone(),
            slot,
            bus.handle.clone(),
            events.clone(),
        ));
        bus.handle.follow(watcher.clone(), stop.clone());
        tokio::spawn(watcher.until_stale(stop));
    });
}

/// What makes news: the state, and the kind of its cause (a drive first
/// polled in vain stays `never`, but now with a reason worth telling).
type Known = (Freshness, std::mem::Discriminant<Cause>);

/// The changes between `known` and `now`'s verdicts (updating `known`),
/// and the earliest moment a live value turns stale.
fn changes(
    known: &mut BTreeMap<u8, Known>,
    now: Vec<(u8, Verdict)>,
) -> (Vec<(u8, Freshness, Verdict)>, Option<Instant>) {
    let mut changed = Vec::new();
    let mut next = None::<Instant>;
    for (unit, verdict) in now {
        if let Some(at) = verdict.stale_at {
            next = Some(next.map_or(at, |n| n.min(at)));
        }
        let key = (verdict.freshness, std::mem::discriminant(&verdict.cause));
        let was = known.insert(unit, key);
        if let Some(was) = was
            && was != key
        {
            changed.push((unit, was.0, verdict));
        }
    }
    (changed, next)
}

/// One bus's drives as last judged: what the bus's events and the
/// moment a value turns stale are compared with.
struct Watcher {
    plant: Arc<Plant>,
    slot: usize,
    handle: BusHandle,
    events: Arc<Events>,
    /// The verdicts known, and the earliest moment a live value turns
    /// stale.
    known: Mutex<(BTreeMap<u8, Known>, Option<Instant>)>,
    /// Wakes [`until_stale`](Self::until_stale) for a moment sooner than
    /// the one it sleeps for.
    sooner: Notify,
}

impl Watcher {
    fn new(plant: Arc<Plant>, slot: usize, handle: BusHandle, events: Arc<Events>) -> Self {
        let mut known = BTreeMap::new();
        let (_, next) = changes(&mut known, handle.freshness_all(Instant::now()));
        Watcher {
            plant,
            slot,
            handle,
            events,
            known: Mutex::new((known, next)),
            sooner: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (BTreeMap<u8, Known>, Option<Instant>)> {
        self.known.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Judges every drive now and publishes what changed.
    fn look(&self) {
        let (changed, sooner) = {
            let mut known = self.lock();
            let (changed, next) = changes(&mut known.0, self.handle.freshness_all(Instant::now()));
            let sooner = next.is_some_and(|n| known.1.is_none_or(|k| n < k));
            known.1 = next;
            (changed, sooner)
        };
        if sooner {
            self.sooner.notify_one();
        }
        if changed.is_empty() {
            return;
        }
        let directory = self.plant.now();
        for (unit, was, verdict) in changed {
            let Some(drive) = directory
                .indexed_drives()
                .find(|(_, d)| d.bus == self.slot && d.unit == unit)
                .map(|(i, _)| i)
            else {
                continue;
            };
            let news = FreshnessNews {
                drive,
                bus: self.handle.name_arc(),
                unit,
                was,
                verdict,
            };
            self.events
                .publish(Arc::new(ControlEvent::Freshness(news)), None);
        }
    }

    /// Looks again just after each moment a live value would turn stale
    /// (no event announces a poll that does not happen), until `stop`.
    async fn until_stale(self: Arc<Self>, stop: CancellationToken) {
        loop {
            let next = self.lock().1;
            // Just after the moment: at it, the value is still live.
            let wake = next.map(|t| tokio::time::Instant::from_std(t + Duration::from_millis(1)));
            tokio::select! {
                () = stop.cancelled() => return,
                () = self.sooner.notified() => continue,
                () = async {
                    match wake {
                        Some(at) => tokio::time::sleep_until(at).await,
                        None => std::future::pending().await,
                    }
                } => {}
            }
            self.look();
        }
    }
}

impl BusFollower for Watcher {
    fn event(&self, event: &BusEvent) {
        // A status of a drive already live changes nothing now: it only
        // moves the moment it would turn stale later, which the timer
        // finds when it comes.
        if let BusEvent::Status { unit, .. } = event
            && self
                .lock()
                .0
                .get(unit)
                .is_some_and(|(f, _)| *f == Freshness::Live)
        {
            return;
        }
        self.look();
    }

    fn lagged(&self, _missed: u64) {
        self.look();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn verdict(freshness: Freshness, stale_at: Option<Instant>) -> Verdict {
        let cause = match freshness {
            Freshness::Never => Cause::NotPolledYet,
            _ => Cause::Polled,
        };
        Verdict {
            freshness,
            since: None,
            age: None,
            cause,
            stale_at,
        }
    }

    #[test]
    fn only_changes_are_news_and_the_next_wake_is_the_soonest_stale() {
        let t = Instant::now();
        let mut known = BTreeMap::new();
        // The first look is no news: nothing was known before.
        let (c, next) = changes(
            &mut known,
            vec![
                (1, verdict(Freshness::Never, None)),
                (2, verdict(Freshness::Never, None)),
            ],
        );
        assert!(c.is_empty());
        assert_eq!(next, None);
        let later = t + Duration::from_secs(1);
        let (c, next) = changes(
            &mut known,
            vec![
                (1, verdict(Freshness::Live, Some(later))),
                (2, verdict(Freshness::Live, Some(t))),
            ],
        );
        assert_eq!(
            c.iter()
                .map(|(u, was, v)| (*u, *was, v.freshness))
                .collect::<Vec<_>>(),
            vec![
                (1, Freshness::Never, Freshness::Live),
                (2, Freshness::Never, Freshness::Live)
            ]
        );
        assert_eq!(next, Some(t));
        // Only what changed is news.
        let (c, _) = changes(
            &mut known,
            vec![
                (1, verdict(Freshness::Live, Some(later))),
                (2, verdict(Freshness::Stale, None)),
            ],
        );
        assert_eq!(c.len(), 1);
        assert_eq!((c[0].0, c[0].1), (2, Freshness::Live));
        let (c, next) = changes(
            &mut known,
            vec![
                (1, verdict(Freshness::BusDown, None)),
                (2, verdict(Freshness::BusDown, None)),
            ],
        );
        assert_eq!(c.len(), 2);
        assert_eq!(next, None);
        // Still never, but polled in vain now: news, with the reason.
        let mut known = BTreeMap::new();
        changes(&mut known, vec![(1, verdict(Freshness::Never, None))]);
        let polled = Verdict {
            cause: Cause::NeverAnswered {
                failures: 1,
                last_failure: None,
            },
            ..verdict(Freshness::Never, None)
        };
        let (c, _) = changes(&mut known, vec![(1, polled.clone())]);
        assert_eq!(c.len(), 1);
        assert_eq!(
            (c[0].1, c[0].2.freshness),
            (Freshness::Never, Freshness::Never)
        );
        // More failures are no news.
        let more = Verdict {
            cause: Cause::NeverAnswered {
                failures: 5,
                last_failure: Some("no reply".into()),
            },
            ..polled
        };
        assert!(changes(&mut known, vec![(1, more)]).0.is_empty());
    }
}
