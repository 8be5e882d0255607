//! New settings taken by a running bus between two transactions (a reload
//! applied in place): the port stays open, the cache keeps what it knows
//! of the drives kept, the poll plan their phases.

use std::time::Instant;

use tracing::{info, warn};

use super::{Scheduler, Tuned};
use crate::bus::master::RtuMaster;
use crate::bus::settings::{BusSettings, Reach};

impl Scheduler {
    /// Takes the settings handed over by `BusHandle::retune`, if any.
    pub(super) fn take_retune(&mut self, master: Option<&mut RtuMaster>) {
        let pending = self
            .shared
            .retune
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        let Some(pending) = pending else { return };
        if self.retune(pending.settings, master, Instant::now()) {
            // The one who asked may have gone; the settings stand.
            let _ = pending.taken.send(());
        }
    }

    /// Puts `new` in force at `now`, on `master`'s open port if there is
    /// one. False, and nothing changed, when `new` needs the port reopened
    /// (another port, baud rate or RS-485 settings): that is the plant's to
    /// do, with a new bus. The observers are the plant's, attached to the
    /// port when it opened: they stay.
    pub(super) fn retune(
        &mut self,
        new: BusSettings,
        master: Option<&mut RtuMaster>,
        now: Instant,
    ) -> bool {
        match self.settings.reach(&new) {
            Reach::Same => return true,
            Reach::InPlace => {}
            Reach::Reopen => {
                warn!(bus = %self.shared.name, "new settings that need the port reopened were not taken in place");
                return false;
            }
        }
        let observers = std::mem::take(&mut self.settings.observers);
        let old = std::mem::replace(&mut self.settings, new);
        self.settings.observers = observers;
        let new = &self.settings;
        self.plan.retune(
            new.drives.iter().copied(),
            new.offline_backoff.0,
            new.offline_backoff.1,
            now,
        );
        self.shared.cache.retune(
            new.drives.iter().map(|d| d.0),
            new.offline_after,
            new.expected(),
        );
        self.shared.queue.set_limits(new.queue);
        *self.shared.tuned.lock().unwrap_or_else(|p| p.into_inner()) = Tuned {
            response_timeout: new.master.response_timeout,
            queue_timeout: new.queue_timeout,
        };
        if old.reopen_backoff != new.reopen_backoff {
            self.reopen.retune(new.reopen_backoff);
        }
        if let Some(master) = master {
            master.retune(new.master);
        }
        info!(bus = %self.shared.name, drives = new.drives.len(), "new settings taken, the port kept open");
        true
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::bus::scheduler::{BusSettings, new_shared};

    const MS: Duration = Duration::from_millis(1);

    fn scheduler(settings: &BusSettings) -> Scheduler {
        Scheduler::new(settings.clone(), new_shared(settings))
    }

    #[test]
    fn new_settings_are_taken_by_the_plan_the_cache_and_the_handles() {
        let old = BusSettings::new(
            "line1",
            "/dev/null",
            115_200,
            vec![(1, Duration::ZERO), (2, Duration::ZERO)],
        );
        let mut s = scheduler(&old);
        let t0 = Instant::now();
        s.shared
            .cache
            .record_status(1, crate::drive::Status::default());
        let mut new = old.clone();
        new.drives = vec![(1, MS * 200), (3, Duration::ZERO)];
        new.master.response_timeout = MS * 300;
        new.queue_timeout = MS * 700;
        new.offline_after = 7;
        assert!(s.retune(new.clone(), None, t0));
        // The plan polls unit 3, no longer unit 2.
        assert_eq!(s.plan.units().collect::<Vec<_>>(), vec![1, 3]);
        // The cache keeps unit 1's status, knows unit 3, forgot unit 2,
        // and measures unit 1's age against its new period.
        let cache = &s.shared.cache;
        assert!(cache.get(1).and_then(|d| d.status).is_some());
        assert!(cache.get(2).is_none() && cache.get(3).is_some());
        assert_eq!(cache.expected(1).period, MS * 200);
        // What the handles read.
        let tuned = s.shared.tuned();
        assert_eq!(
            (tuned.response_timeout, tuned.queue_timeout),
            (MS * 300, MS * 700)
        );
        assert_eq!(s.settings.drives, new.drives);
        // The same again changes nothing and is taken.
        assert!(s.retune(new, None, t0));
    }

    #[test]
    fn settings_that_need_the_port_reopened_are_not_taken() {
        let old = BusSettings::new("line1", "/dev/null", 115_200, vec![(1, Duration::ZERO)]);
        let mut s = scheduler(&old);
        let mut new = old.clone();
        new.port = "/dev/ttyUSB1".into();
        new.drives.push((2, Duration::ZERO));
        assert!(!s.retune(new, None, Instant::now()));
        assert_eq!(s.settings.port, "/dev/null");
        assert_eq!(s.plan.units().collect::<Vec<_>>(), vec![1]);
    }

    #[test]
    fn the_handle_hands_over_and_hears_when_they_are_taken() {
        let old = BusSettings::new("line1", "/dev/null", 115_200, vec![(1, Duration::ZERO)]);
        let shared = new_shared(&old);
        let mut s = Scheduler::new(old.clone(), shared.clone());
        let handle = crate::bus::BusHandle { shared };
        let mut new = old.clone();
        new.drives.push((2, Duration::ZERO));
        let mut taken = handle.retune(new);
        assert!(taken.try_recv().is_err(), "taken before the boundary");
        s.take_retune(None);
        assert_eq!(taken.try_recv(), Ok(()));
        assert_eq!(handle.drives().len(), 2);
        // Refused: the receiver hears that it was not taken.
        let mut other = old.clone();
        other.port = "/dev/ttyUSB1".into();
        let mut refused = handle.retune(other);
        s.take_retune(None);
        assert!(matches!(
            refused.try_recv(),
            Err(tokio::sync::oneshot::error::TryRecvError::Closed)
        ));
    }
}
