//! Reloads of the configuration, as the core sees them: who may ask
//! (`Operation::Reload`, admin), the audit line, the running configuration
//! every face follows, what became of the last reload (for `/readyz` and
//! the metrics), and the stop of a drive a reload removes.
//!
//! The core does not read files or start buses: the daemon's reloader
//! (`crate::reload`) does, and registers itself here with
//! [`Control::attach_reloader`]. A face asks [`Control::reload`] like it
//! asks any write, and renders the answer.

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use tokio::sync::{broadcast, mpsc, oneshot, watch};

pub use super::news::{ReloadApplied as Applied, ReloadRefused as Refused, ReloadResult};
use super::{Caller, Control, ControlEvent, LeaseEvent, Operation, audit, rules};
use crate::bus::Origin;
use crate::config::Config;
use crate::safety::{self, StopAction, StopOutcome};

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

/// A face's view of the running configuration, asked on its request path:
/// [`changed`](Self::changed) answers each new configuration once, so
/// what a reload changes applies from the very next request (the reloader
/// publishes before it answers).
pub struct ConfigFollower(std::sync::Mutex<watch::Receiver<Option<Arc<Config>>>>);

impl ConfigFollower {
    /// Follows `control`'s running configuration from now on.
    pub fn new(control: &Control) -> Self {
        let mut rx = control.follow_config();
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

impl Control {
    /// The daemon's reloader of `file` takes reloads from here on.
    pub fn attach_reloader(&self, reloader: mpsc::Sender<ReloadRequest>, file: &std::path::Path) {
        *self
            .0
            .reloads
            .file
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(file.to_path_buf());
        *self
            .0
            .reloads
            .reloader
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(reloader);
    }

    /// Reloads the configuration for `caller` (an admin), optionally
    /// writing `write` into the file first; audited either way.
    pub async fn reload(&self, caller: &Caller, write: Option<NewText>) -> ReloadResult {
        let by = format!("{} {}", caller.face.name(), caller.who);
        if let Err(refusal) = rules::role(caller, Operation::Reload.needs()) {
            let refused = Refused::Refused(refusal);
            audit::reload(&by, &Err(refused.clone()));
            return Err(refused);
        }
        let result = self.reload_as(by.clone(), write).await;
        audit::reload(&by, &result);
        result
    }

    /// Asks the reloader, for a caller the daemon vouches for (SIGHUP).
    pub(crate) async fn reload_as(&self, by: String, write: Option<NewText>) -> ReloadResult {
        let reloader = self
            .0
            .reloads
            .reloader
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
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
    pub fn config_file(&self) -> Option<std::path::PathBuf> {
        self.0
            .reloads
            .file
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// What became of reloads since start-up.
    pub fn reload_status(&self) -> ReloadStatus {
        self.0
            .reloads
            .status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Records what became of a reload (by the reloader).
    pub fn record_reload(&self, result: &ReloadResult) {
        let mut status = self
            .0
            .reloads
            .status
            .lock()
            .unwrap_or_else(|p| p.into_inner());
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

    /// The running configuration, as last loaded; a face follows it for
    /// its own section (`changed().await`, then `borrow_and_update()`).
    pub fn follow_config(&self) -> watch::Receiver<Option<Arc<Config>>> {
        self.0.reloads.running.subscribe()
    }

    /// Publishes the running configuration: at start-up, and after each
    /// reload once the plant follows it. Applies `[safety]`'s lease bounds,
    /// jog lease and lease-expiry action to leases granted from now on.
    pub fn set_config(&self, config: Arc<Config>) {
        let safety = &config.safety;
        *self.0.settings.write().unwrap_or_else(|p| p.into_inner()) = super::Settings::of(safety);
        self.0
            .leases
            .with(|book, _| (book.set_action(safety.on_lease_expiry), Vec::new()));
        self.0.reloads.running.send_replace(Some(config));
    }

    /// Stops the drives (slot indices) a reload removes, while their bus
    /// still runs: a drive with a lease gets its lease's stop, the others
    /// `on_shutdown` if they move; each stop audited. Returns what was
    /// done, in words, once every stop ended (or after a few seconds).
    pub async fn retire(&self, drives: &[usize], on_shutdown: StopAction) -> Vec<String> {
        let mut news = self.subscribe();
        let mut leased = Vec::new();
        let mut unleased = Vec::new();
        for &drive in drives {
            let had = self.0.leases.with(|book, now| book.retire(drive, now));
            if had {
                leased.push(drive);
            } else {
                unleased.push(drive);
            }
        }
        let mut done = Vec::new();
        let now = self.plant().now();
        let stops = unleased.iter().filter_map(|&index| {
            let drive = now.drive_at(index)?.clone();
            let handle = now.handle_of(&drive)?.clone();
            Some(async move {
                let result = safety::stop_drive(
                    &handle,
                    drive.unit,
                    on_shutdown,
                    true,
                    None,
                    Origin::Internal,
                )
                .await;
                match result {
                    Ok(outcome @ StopOutcome { sent: Some(_), .. }) => {
                        for request in outcome.requests() {
                            audit::write(
                                super::Face::Internal.name(),
                                "reload",
                                handle.name(),
                                drive.unit,
                                request.name(),
                                &super::WriteEnd::Confirmed,
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
                            super::Face::Internal.name(),
                            "reload",
                            handle.name(),
                            drive.unit,
                            on_shutdown.name(),
                            &super::WriteEnd::bus_error(e.clone()),
                        );
                        Some(format!(
                            "drive {}: {} failed: {e}",
                            drive.name,
                            on_shutdown.name()
                        ))
                    }
                }
            })
        });
        let unleased_stops = futures_util::future::join_all(stops);
        let leased_stops = async {
            let mut waiting = leased.clone();
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
        };
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
}
