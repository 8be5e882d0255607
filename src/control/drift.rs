//! Declared settings (`[bus.drive.settings]`) and their drift: whenever a
//! drive with a declaration comes online (at start, after a power cycle
//! the poller noticed, a replaced drive), its settings are read and
//! compared with the declaration ([`wanted::drift`], pure). A drift is
//! reported: an event for the stream, the audit log, the drive's state
//! for the API and the metric. With `apply_settings = "on-drift"` the
//! declaration is then put on the drive through the core's one write path
//! (`settings::apply_wanted`), never while the motor turns (the core
//! refuses it; this waits for a status at standstill and tries again) and
//! never to flash unless `save = true` is declared; the read-back after
//! it says whether the drift is gone.
//!
//! The set of drives is read from the plant at each event, never kept.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

use super::audit;
use super::caller::Caller;
use super::events::ControlEvent;
pub use super::news::{DriftChecked, DriftState, DriftView};
use super::outcome::{Failure, Refusal, Rule};
use super::parts::Parts;
use super::request::Target;
use super::settings::{self, ApplyOptions, Done, SettingsError};
use crate::bus::BusEvent;
use crate::bus::cache::Link;
use crate::config::{ApplySettings, Declared};
use crate::drive::settings::DriveSettings;
use crate::drive::wanted::{self, Difference};

/// Who the audit log and the events name for drivegate's own checks and
/// writes of declared settings.
pub const WHO: &str = "declared-settings";

/// What drivegate does once a drive was compared with its declaration.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Next {
    /// Nothing more: it holds them, or the declaration only reports.
    Report,
    /// Write the declaration.
    Apply,
}

/// Pure: what follows a comparison that found `drift` under `apply`.
pub fn next(apply: ApplySettings, drift: &[Difference]) -> Next {
    match apply {
        ApplySettings::OnDrift if !drift.is_empty() => Next::Apply,
        ApplySettings::OnDrift | ApplySettings::Never => Next::Report,
    }
}

/// Every drive's latest comparison, by drive name, and the checks running.
#[derive(Default)]
pub struct DriftBook {
    views: Mutex<HashMap<String, DriftView>>,
    /// Drives being checked; true when another check was asked for
    /// meanwhile (it runs after).
    running: Mutex<HashMap<usize, bool>>,
    /// The core's parts and the daemon's shutdown, once the buses are
    /// followed.
    started: std::sync::OnceLock<(Arc<Parts>, CancellationToken)>,
}

impl DriftBook {
    /// The latest comparison of drive `name`; `None` before the first
    /// (or for a drive without a declaration).
    pub fn view(&self, name: &str) -> Option<DriftView> {
        lock(&self.views).get(name).cloned()
    }

    /// Drive `old` is named `new` now (the same motor, renamed by a
    /// reload): its latest comparison is its under the new name.
    pub(super) fn rename(&self, old: &str, new: &str) {
        let mut views = lock(&self.views);
        if let Some(view) = views.remove(old) {
            views.insert(new.to_string(), view);
        }
    }

    /// Records drive `drive`'s new state and tells the stream and the log.
    fn set(&self, parts: &Arc<Parts>, drive: usize, view: DriftView) {
        let Some(name) = parts.plant().now().drive_at(drive).map(|d| d.name.clone()) else {
            return;
        };
        match &view.state {
            DriftState::ReadFailed(why) | DriftState::ApplyFailed(why) => {
                audit::settings_trouble(&name, why);
            }
            DriftState::WaitingForStandstill => {}
            DriftState::Matches | DriftState::Drifted => {
                audit::settings_checked(&name, &view.drift, view.apply.name());
            }
        }
        lock(&self.views).insert(name, view.clone());
        parts.events().publish(
            Arc::new(ControlEvent::Drift(DriftChecked { drive, view })),
            None,
        );
    }

    /// After a settings document was put on drive `drive` (from any face,
    /// or by drivegate), with `held` read back: a drive with a declaration
    /// is compared with it again, so its state follows what it holds now.
    pub(super) fn after_apply(&self, parts: &Arc<Parts>, drive: usize, held: &DriveSettings) {
        let Some(declared) = parts.plant().now().drive_at(drive).and_then(|d| d.declared) else {
            return;
        };
        self.compared(parts, drive, &declared, held);
    }

    fn compared(
        &self,
        parts: &Arc<Parts>,
        drive: usize,
        declared: &Declared,
        held: &DriveSettings,
    ) -> Vec<Difference> {
        let drift = wanted::drift(&declared.wanted, held);
        let state = if drift.is_empty() {
            DriftState::Matches
        } else {
            DriftState::Drifted
        };
        self.set(
            parts,
            drive,
            DriftView {
                state,
                drift: drift.clone(),
                checked_at: SystemTime::now(),
                apply: declared.apply,
            },
        );
        drift
    }

    /// Keeps the known drift, with a new state.
    fn restate(&self, parts: &Arc<Parts>, drive: usize, apply: ApplySettings, state: DriftState) {
        let drift = parts
            .plant()
            .drives()
            .get(drive)
            .and_then(|d| self.view(&d.name))
            .map(|v| v.drift)
            .unwrap_or_default();
        self.set(
            parts,
            drive,
            DriftView {
                state,
                drift,
                checked_at: SystemTime::now(),
                apply,
            },
        );
    }

    /// Compares drive `drive` with its declaration again now (and applies
    /// it under `on-drift`), as when it comes online: for a declaration
    /// that changed while the drive was online. Nothing before the buses
    /// are followed, nor for a drive without a declaration.
    pub fn recheck(self: &Arc<Self>, drive: usize) {
        let Some((parts, shutdown)) = self.started.get() else {
            return;
        };
        let declared = parts
            .plant()
            .now()
            .drive_at(drive)
            .is_some_and(|d| d.declared.is_some());
        if declared {
            self.request(parts, drive, shutdown);
        }
    }

    /// Checks drive `drive` now, or once the check running for it ends.
    fn request(self: &Arc<Self>, parts: &Arc<Parts>, drive: usize, shutdown: &CancellationToken) {
        {
            let mut running = lock(&self.running);
            if let Some(again) = running.get_mut(&drive) {
                *again = true;
                return;
            }
            running.insert(drive, false);
        }
        let (book, parts, shutdown) = (self.clone(), parts.clone(), shutdown.clone());
        tokio::spawn(async move {
            loop {
                book.check(&parts, drive, &shutdown).await;
                let mut running = lock(&book.running);
                if running.get(&drive) == Some(&true) && !shutdown.is_cancelled() {
                    running.insert(drive, false);
                    continue;
                }
                running.remove(&drive);
                return;
            }
        });
    }

    /// Compares drive `drive` with its declaration and, with `on-drift`,
    /// applies it.
    async fn check(&self, parts: &Arc<Parts>, drive: usize, shutdown: &CancellationToken) {
        let now = parts.plant().now();
        let Some(d) = now.drive_at(drive).cloned() else {
            return;
        };
        let Some(declared) = d.declared else {
            return;
        };
        let Some(bus) = now.bus_at(d.bus).cloned() else {
            return;
        };
        // Subscribed before anything is read, so a standstill that comes
        // while the core refuses the writes is not missed.
        let mut events = bus.handle.subscribe();
        let target = Target {
            bus: d.bus,
            unit: d.unit,
            drive: Some(drive),
        };
        let caller = Caller::internal(WHO);
        let held = match settings::read_settings(parts, &caller, target).await {
            Ok(held) => held,
            Err(e) => {
                let why = format!("its settings could not be read: {e}");
                self.restate(parts, drive, declared.apply, DriftState::ReadFailed(why));
                return;
            }
        };
        let drift = self.compared(parts, drive, &declared, &held);
        if next(declared.apply, &drift) == Next::Report {
            return;
        }
        let options = ApplyOptions {
            save: declared.save,
            force: false,
            dry_run: false,
            unattended: true,
        };
        loop {
            let applied =
                settings::apply_wanted(parts, &caller, target, &declared.wanted, options).await;
            // What the drive holds after the writes, compared again.
            if let Ok(Done {
                held: Some(held), ..
            }) = &applied
            {
                self.after_apply(parts, drive, held);
            }
            match applied.map(|done| done.report) {
                Ok(report) if report.complete() => return,
                Ok(report) => {
                    let why = report
                        .failure
                        .map_or_else(|| "unknown".to_string(), |f| f.to_string());
                    let why = format!("writing the declared settings failed: {why}");
                    self.restate(parts, drive, declared.apply, DriftState::ApplyFailed(why));
                    return;
                }
                Err(SettingsError::Failed(Failure::Refused(Refusal {
                    rule: Rule::Moving { .. },
                    ..
                }))) => {
                    self.restate(
                        parts,
                        drive,
                        declared.apply,
                        DriftState::WaitingForStandstill,
                    );
                    if !standstill(&mut events, d.unit, shutdown).await {
                        return;
                    }
                }
                Err(e) => {
                    let why = match e {
                        SettingsError::Invalid(r) => format!("{r:?}"),
                        SettingsError::Failed(f) => f.to_string(),
                    };
                    let why = format!("the declared settings were not written: {why}");
                    self.restate(parts, drive, declared.apply, DriftState::ApplyFailed(why));
                    return;
                }
            }
        }
    }
}

/// Waits for a status of `unit` at standstill: true; false when it goes
/// offline (it is compared again when it comes back) or drivegate stops.
async fn standstill(
    events: &mut broadcast::Receiver<BusEvent>,
    unit: u8,
    shutdown: &CancellationToken,
) -> bool {
    loop {
        let event = tokio::select! {
            () = shutdown.cancelled() => return false,
            event = events.recv() => event,
        };
        match event {
            Ok(BusEvent::Status {
                unit: u, status, ..
            }) if u == unit && status.speed_rpm == 0 => {
                return true;
            }
            Ok(BusEvent::Offline { unit: u, .. }) if u == unit => return false,
            Ok(_) => {}
            // Fell behind: look again at once (the core reads the speed).
            Err(broadcast::error::RecvError::Lagged(_)) => return true,
            Err(broadcast::error::RecvError::Closed) => return false,
        }
    }
}

/// Follows every bus: each drive with a declaration is compared with it
/// when it comes online, and those online already now. Ends with
/// `shutdown`.
pub(super) fn start(book: &Arc<DriftBook>, parts: &Arc<Parts>, shutdown: &CancellationToken) {
    if tokio::runtime::Handle::try_current().is_err() {
        return;
    }
    let book = book.clone();
    let _ = book.started.set((parts.clone(), shutdown.clone()));
    // Follows the plant: each bus a reload adds or reopens gets its
    // watcher, one it removes or reopens loses its own. The buses of now
    // are subscribed to at once, before the drives online already are
    // asked for below: a drive that comes online in between is not missed.
    let (watcher_book, watcher_parts) = (book.clone(), parts.clone());
    parts
        .plant()
        .for_each_bus(shutdown, move |index, bus, stop| {
            watch_bus(
                watcher_book.clone(),
                watcher_parts.clone(),
                index,
                bus.handle.subscribe_links(),
                stop,
            );
        });
    // Online before the buses were followed.
    let now = parts.plant().now();
    for (drive, d) in now.indexed_drives() {
        let online = now
            .bus_at(d.bus)
            .and_then(|b| b.handle.drive(d.unit))
            .is_some_and(|s| s.link == Link::Online);
        if d.declared.is_some() && online {
            book.request(parts, drive, shutdown);
        }
    }
}

/// Asks for a comparison of each declared drive of bus `index` that comes
/// online, until `shutdown`.
fn watch_bus(
    book: Arc<DriftBook>,
    parts: Arc<Parts>,
    index: usize,
    mut rx: broadcast::Receiver<BusEvent>,
    shutdown: CancellationToken,
) {
    {
        tokio::spawn(async move {
            loop {
                let event = tokio::select! {
                    () = shutdown.cancelled() => return,
                    event = rx.recv() => event,
                };
                match event {
                    Ok(BusEvent::Online { unit, .. }) => {
                        let drive = parts
                            .plant()
                            .now()
                            .indexed_drives()
                            .find(|(_, d)| d.bus == index && d.unit == unit && d.declared.is_some())
                            .map(|(i, _)| i);
                        if let Some(drive) = drive {
                            book.request(&parts, drive, &shutdown);
                        }
                    }
                    Ok(_) => {}
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!("declared settings: fell {n} bus events behind");
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        });
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::wanted::Setting;

    #[test]
    fn only_a_drift_under_on_drift_is_applied() {
        let drift = [Difference {
            setting: Setting::InertiaRatio,
            before: 1,
            after: 5,
        }];
        assert_eq!(next(ApplySettings::OnDrift, &drift), Next::Apply);
        assert_eq!(next(ApplySettings::Never, &drift), Next::Report);
        assert_eq!(next(ApplySettings::OnDrift, &[]), Next::Report);
        assert_eq!(next(ApplySettings::Never, &[]), Next::Report);
        assert_eq!(ApplySettings::default(), ApplySettings::Never);
    }
}
