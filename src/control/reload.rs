//! Reloads of the configuration, as the core sees them: who may ask
//! (`Operation::Reload`, admin), the audit line, the running configuration
//! every face follows, what became of the last reload (for `/readyz` and
//! the metrics), and the stop of a drive a reload removes.
//!
//! The core does not read files or start buses: the daemon's reloader
//! (`crate::daemon::reloader`) does, and registers itself here with
//! [`Control::attach_reloader`]. A face asks [`Control::reload`] like it
//! asks any write, and renders the answer.

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use tokio::sync::{broadcast, mpsc, oneshot, watch};

use super::caller::{Caller, Face};
use super::events::{ControlEvent, Published, WriteEnd};
use super::lease_book::LeaseEvent;
pub use super::news::{ReloadApplied as Applied, ReloadRefused as Refused, ReloadResult};
use super::parts::Parts;
use super::policy::Operation;
use super::{audit, rules};
use crate::bus::{BusHandle, Origin};
use crate::config::Config;
use crate::config::edit::sha256_hex;
use crate::config::text_diff::{self, Hunk};
use crate::control::stop_action::{self, StopAction, StopOutcome};
use crate::drive::{Mode, Status};
use crate::plant::{Directory, Drive};

/// A reload asked for, with where its answer goes.
pub struct ReloadRequest {
    /// Who asked, in the audit log's words ("http admin-token", "SIGHUP").
    pub by: String,
    /// The file's new text, to write before reloading (the console's
    /// "add to configuration"), with the hash of the text it was made from:
    /// refused if the file changed on disk since.
    pub write: Option<NewText>,
    /// The answer.
    pub reply: oneshot::Sender<ReloadResult>,
}

/// A new text for the configuration file.
pub struct NewText {
    /// The text to write.
    pub text: String,
    /// SHA-256 (hex) of the file as it was read to make `text`.
    pub base_sha256: String,
    /// What the change is, in words, for the audit log ("configuration
    /// edited", "API token \"scada\" made (operator)").
    pub what: String,
    /// Its lines: what differs from the text it was made from.
    pub hunks: Vec<Hunk>,
}

impl NewText {
    /// `text`, made from `base` (the file as read), described as `what`.
    pub fn new(base: &str, text: String, what: impl Into<String>) -> Self {
        NewText {
            base_sha256: sha256_hex(base),
            hunks: text_diff::diff(base, &text),
            text,
            what: what.into(),
        }
    }
}

/// What became of reloads since start-up.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReloadStatus {
    /// Reloads applied whole.
    pub applied: u64,
    /// Reloads applied in part: something could not be done (a port that
    /// did not open, a listener that could not move).
    pub partial: u64,
    /// Reloads refused because the file did not pass the check.
    pub invalid: u64,
    /// False while the file on disk is one the last reload refused, or
    /// applied only in part.
    pub last_ok: bool,
    /// Why the last reload was refused (`file:line:column: why`), or what
    /// of it could not be done, while it is the last one.
    pub last_error: Option<String>,
    /// When the running configuration was last loaded (start-up or a
    /// reload).
    pub last_good_at: Option<SystemTime>,
}

/// What holds the running configuration: the core's handle
/// ([`super::Control`]), which a face hands to [`ConfigFollower::new`].
pub trait RunningConfig {
    /// A receiver of the running configuration, as last loaded.
    fn running_config(&self) -> watch::Receiver<Option<Arc<Config>>>;
}

/// A face's view of the running configuration, asked on its request path:
/// [`changed`](Self::changed) answers each new configuration once, so
/// what a reload changes applies from the very next request (the reloader
/// publishes before it answers).
pub struct ConfigFollower(std::sync::Mutex<watch::Receiver<Option<Arc<Config>>>>);

impl ConfigFollower {
    /// Follows `control`'s running configuration from now on.
    pub fn new(control: &impl RunningConfig) -> Self {
        let mut rx = control.running_config();
        rx.mark_unchanged();
        ConfigFollower(std::sync::Mutex::new(rx))
    }

    /// The running configuration, if it changed since the last call.
    pub fn changed(&self) -> Option<Arc<Config>> {
        let mut rx = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if rx.has_changed().unwrap_or(false) {
            rx.borrow_and_update().clone()
        } else {
            None
        }
    }
}

/// The core's part of reloads: the reloader's channel, the running
/// configuration, the status.
pub(super) struct Reloads {
    reloader: std::sync::Mutex<Option<mpsc::Sender<ReloadRequest>>>,
    /// The file the reloader reads.
    file: std::sync::Mutex<Option<std::path::PathBuf>>,
    running: watch::Sender<Option<Arc<Config>>>,
    status: std::sync::Mutex<ReloadStatus>,
}

impl Default for Reloads {
    fn default() -> Self {
        Reloads {
            reloader: std::sync::Mutex::new(None),
            file: std::sync::Mutex::new(None),
            running: watch::channel(None).0,
            status: std::sync::Mutex::new(ReloadStatus {
                last_ok: true,
                last_good_at: Some(SystemTime::now()),
                ..ReloadStatus::default()
            }),
        }
    }
}

/// How long the stop of a removed drive may take before the reload goes
/// on without its confirmation (the stop is still audited when it ends).
const RETIRE_LIMIT: Duration = Duration::from_secs(3);

impl Reloads {
    /// The daemon's reloader of `file` takes reloads from here on.
    pub(super) fn attach(&self, reloader: mpsc::Sender<ReloadRequest>, file: &std::path::Path) {
        *lock(&self.file) = Some(file.to_path_buf());
        *lock(&self.reloader) = Some(reloader);
    }

    /// Asks the reloader, for a caller the daemon vouches for (SIGHUP).
    pub(super) async fn ask(&self, by: String, write: Option<NewText>) -> ReloadResult {
        let reloader = lock(&self.reloader).clone();
        let Some(reloader) = reloader else {
            return Err(Refused::Unavailable(
                "no configuration file to reload: drivegate was started without --config"
                    .to_string(),
            ));
        };
        let (reply, answer) = oneshot::channel();
        let request = ReloadRequest { by, write, reply };
        let gone = || Refused::Unavailable("drivegate is stopping".to_string());
        reloader.send(request).await.map_err(|_| gone())?;
        answer.await.map_err(|_| gone())?
    }

    /// The configuration file a reload reads, if drivegate was started
    /// with one.
    pub(super) fn file(&self) -> Option<std::path::PathBuf> {
        lock(&self.file).clone()
    }

    /// What became of reloads since start-up.
    pub(super) fn status(&self) -> ReloadStatus {
        lock(&self.status).clone()
    }

    /// Records what became of a reload (by the reloader).
    pub(super) fn record(&self, result: &ReloadResult) {
        let mut status = lock(&self.status);
        match result {
            Ok(applied) if !applied.problems.is_empty() => {
                status.partial += 1;
                status.last_ok = false;
                status.last_error = Some(format!(
                    "applied in part; not done: {}",
                    applied.problems.join("; ")
                ));
                status.last_good_at = Some(SystemTime::now());
            }
            Ok(_) => {
                status.applied += 1;
                status.last_ok = true;
                status.last_error = None;
                status.last_good_at = Some(SystemTime::now());
            }
            Err(Refused::Invalid(why)) => {
                status.invalid += 1;
                status.last_ok = false;
                status.last_error = Some(why.clone());
            }
            Err(_) => {}
        }
    }

    /// The running configuration, as last loaded.
    pub(super) fn follow(&self) -> watch::Receiver<Option<Arc<Config>>> {
        self.running.subscribe()
    }

    /// Publishes the running configuration.
    pub(super) fn publish(&self, config: Arc<Config>) {
        self.running.send_replace(Some(config));
    }
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Reloads the configuration for `caller` (an admin), optionally
/// writing `write` into the file first; audited either way.
pub(super) async fn reload(
    reloads: &Reloads,
    caller: &Caller,
    write: Option<NewText>,
) -> ReloadResult {
    let by = format!("{} {}", caller.face.name(), caller.who);
    let change = write
        .as_ref()
        .map(|w| (w.what.clone(), text_diff::unified(&w.hunks)));
    let audit = |result: &ReloadResult| match &change {
        Some((what, diff)) => audit::config_written(&by, what, diff, result),
        None => audit::reload(&by, result),
    };
    if let Err(refusal) = rules::role(caller, Operation::Reload.needs()) {
        let refused = Err(Refused::Refused(refusal));
        audit(&refused);
        return refused;
    }
    let result = reloads.ask(by.clone(), write).await;
    audit(&result);
    result
}

/// A drive's motion, as its status says it.
fn motion(s: &Status) -> String {
    let mode = match s.mode() {
        Mode::OpenLoop => "open loop",
        Mode::Speed => "speed mode",
        Mode::Position => "position mode",
        Mode::Torque => "torque mode",
    };
    match (s.active(), s.speed_rpm) {
        (false, 0) => "inactive, at standstill".to_string(),
        (false, rpm) => format!("inactive, turning at {rpm} rpm"),
        (true, 0) => format!("active in {mode}, at standstill"),
        (true, rpm) => format!("active in {mode}, turning at {rpm} rpm"),
    }
}

/// What a reload's `why` (e.g. "bus line1 reopened") did to drive
/// `name`'s motion, from the drive's own statuses before and after it:
/// `None` while it is as active, in the same mode, as much turning or at
/// standstill as it was (a speed that settles, or a position that moves on,
/// is the drive's own doing). Pure.
pub fn motion_changed(name: &str, why: &str, before: &Status, after: &Status) -> Option<String> {
    let still = |s: &Status| s.speed_rpm == 0;
    let same = before.active() == after.active()
        && before.mode() == after.mode()
        && still(before) == still(after);
    (!same).then(|| {
        format!(
            "drive {name} was {} before {why}, and is {} after it (as the drive reports)",
            motion(before),
            motion(after)
        )
    })
}

/// Stops the drives (slot indices) a reload removes, while their bus
/// still runs: a drive with a lease gets its lease's stop, the others
/// `on_shutdown` if they move; each stop audited. Returns what was
/// done, in words, once every stop ended (or after a few seconds).
pub(super) async fn retire(
    parts: &Parts,
    drives: &[usize],
    on_shutdown: StopAction,
) -> Vec<String> {
    let mut news = parts.subscribe();
    let mut leased = Vec::new();
    let mut unleased = Vec::new();
    for &drive in drives {
        let had = parts.leases().with(|book, now| book.retire(drive, now));
        if had {
            leased.push(drive);
        } else {
            unleased.push(drive);
        }
    }
    let mut done = Vec::new();
    let now = parts.plant().now();
    let stops = unleased.iter().filter_map(|&index| {
        let drive = now.drive_at(index)?.clone();
        let handle = now.handle_of(&drive)?.clone();
        Some(stop_unleased(handle, drive, on_shutdown))
    });
    let unleased_stops = futures_util::future::join_all(stops);
    let leased_stops = lease_stops(&mut news, &leased, &now);
    let both = async { tokio::join!(unleased_stops, leased_stops) };
    match tokio::time::timeout(RETIRE_LIMIT, both).await {
        Ok((unleased, leased)) => {
            done.extend(unleased.into_iter().flatten());
            done.extend(leased);
        }
        Err(_) => done.push(format!(
            "the stops of the removed drives did not end within {} s",
            RETIRE_LIMIT.as_secs()
        )),
    }
    done
}

/// Stops a removed drive that held no lease with `on_shutdown`, if it
/// moves; audited. What was done, in words, if anything.
async fn stop_unleased(handle: BusHandle, drive: Drive, on_shutdown: StopAction) -> Option<String> {
    let result =
        stop_action::stop_drive(&handle, drive.unit, on_shutdown, true, Origin::Internal).await;
    match result {
        Ok(outcome @ StopOutcome { sent: Some(_), .. }) => {
            for request in outcome.requests() {
                audit::write(
                    Face::Internal.name(),
                    "reload",
                    handle.name(),
                    drive.unit,
                    request.name(),
                    &WriteEnd::Confirmed,
                );
            }
            Some(format!(
                "drive {} was moving: {} applied",
                drive.name,
                on_shutdown.name()
            ))
        }
        Ok(_) => None,
        Err(e) => {
            audit::write(
                Face::Internal.name(),
                "reload",
                handle.name(),
                drive.unit,
                on_shutdown.name(),
                &WriteEnd::bus_error(e.clone()),
            );
            Some(format!(
                "drive {}: {} failed: {e}",
                drive.name,
                on_shutdown.name()
            ))
        }
    }
}

/// Waits for the stops of the removed drives `leased` that held a lease
/// (their lease's own stop, told on the core's events). What they did, in
/// words.
async fn lease_stops(
    news: &mut broadcast::Receiver<Published>,
    leased: &[usize],
    now: &Directory,
) -> Vec<String> {
    let mut waiting = leased.to_vec();
    let mut words = Vec::new();
    while !waiting.is_empty() {
        match news.recv().await {
            Ok(published) => {
                if let ControlEvent::Lease(LeaseEvent::Expired {
                    drive,
                    sent,
                    result,
                    ..
                }) = &*published.event
                    && let Some(at) = waiting.iter().position(|d| d == drive)
                {
                    waiting.swap_remove(at);
                    let name = now.drive_at(*drive).map_or("?", |d| d.name.as_str());
                    words.push(format!(
                        "drive {name}'s lease ended with its stop ({}): {result}",
                        sent.as_deref().unwrap_or("nothing sent")
                    ));
                }
            }
            Err(broadcast::error::RecvError::Lagged(_)) => continue,
            Err(broadcast::error::RecvError::Closed) => break,
        }
    }
    words
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A status of a drive `active` in `mode` at `rpm`.
    fn status(active: bool, mode: Mode, rpm: i16) -> Status {
        let mut flags = mode.bits() << 3;
        if active {
            flags |= 1 << 7;
        }
        Status {
            speed_rpm: rpm,
            flags,
            ..Status::default()
        }
    }

    #[test]
    fn a_motion_is_changed_only_when_the_drive_says_so() {
        let turning = status(true, Mode::Speed, 100);
        assert!(
            turning.active() && turning.mode() == Mode::Speed,
            "{turning:?}"
        );
        let why = "bus line1 reopened";
        // The same, a speed settling, a position moving on: unchanged.
        assert_eq!(motion_changed("conveyor", why, &turning, &turning), None);
        let settled = status(true, Mode::Speed, 99);
        assert_eq!(motion_changed("conveyor", why, &turning, &settled), None);
        let still = status(true, Mode::Position, 0);
        assert_eq!(motion_changed("lift", why, &still, &still), None);
        // A drive restarted: inactive, in open loop.
        let reset = status(false, Mode::OpenLoop, 0);
        assert_eq!(
            motion_changed("conveyor", why, &turning, &reset).as_deref(),
            Some(
                "drive conveyor was active in speed mode, turning at 100 rpm before bus line1 \
                 reopened, and is inactive, at standstill after it (as the drive reports)"
            )
        );
        // Stopped in its mode, or set in motion.
        assert!(motion_changed("conveyor", why, &turning, &status(true, Mode::Speed, 0)).is_some());
        assert!(motion_changed("lift", why, &still, &status(true, Mode::Position, 30)).is_some());
    }
}
