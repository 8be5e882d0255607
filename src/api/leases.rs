//! Motor-safety leases: a setpoint may come with a lease (`lease_ms`); if
//! the client does not renew it in time, or the WebSocket it came over
//! closes, the daemon stops that motor with `[safety] on_lease_expiry`
//! (zero speed or the brake), sent at emergency priority. A remote client
//! that crashes thus cannot leave a motor spinning.
//!
//! One lease per drive: a new leased setpoint replaces the lease (whoever
//! sent it), a setpoint without a lease leaves it in place, and the brake or
//! deactivation ends it (the motor is stopped already, and a zero-speed
//! setpoint would release the brake). Each lease has one watcher task that
//! sleeps until the deadline; renewing moves the deadline through a
//! `watch` channel, so renewals cost no task.
//!
//! The lease is put in place *before* its setpoint is sent, with a deadline
//! that allows for the bus queue, and is given its real deadline once the
//! drive confirmed: if the request is dropped halfway (the client went away
//! mid-request), the motor is still covered.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use utoipa::ToSchema;

use super::control::describe;
use super::hub::{Hub, ServerMessage};
use crate::audit;
use crate::drive::Mode;
use crate::plant::Plant;
use crate::safety::{self, StopAction, StopOutcome};

/// A lease as clients see it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct LeaseInfo {
    /// The drive it covers.
    pub drive: String,
    /// Who holds it (token name or client address).
    pub owner: String,
    /// Its length: each renewal pushes the deadline this far ahead.
    pub lease_ms: u64,
    /// Time left before the stop action, ms.
    pub expires_in_ms: u64,
    /// True when it also ends as soon as its WebSocket closes.
    pub websocket: bool,
}

struct Lease {
    id: u64,
    /// The mode its setpoint drives the motor in: the last resort for
    /// choosing the stop when the drive's mode cannot be read.
    mode: Mode,
    owner: Arc<str>,
    connection: Option<u64>,
    duration: Duration,
    deadline: watch::Sender<Instant>,
    /// False until its setpoint was sent: the deadline then still allows
    /// for the bus queue.
    confirmed: bool,
}

/// What [`LeaseBook::grant`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grant {
    /// The new lease's id.
    pub id: u64,
    /// True when it replaced a lease on the drive.
    pub replaced: bool,
}

enum Due {
    Expired(Lease),
    Later,
    Gone,
}

/// Every lease of the plant.
pub struct LeaseBook {
    plant: Arc<Plant>,
    hub: Arc<Hub>,
    action: StopAction,
    shutdown: CancellationToken,
    leases: Mutex<HashMap<usize, Lease>>,
    live_connections: Mutex<HashSet<u64>>,
    next_id: AtomicU64,
    tasks: TaskTracker,
}

impl LeaseBook {
    /// Leases for the drives of `plant`, stopped by `action` on expiry; the
    /// watchers end when `shutdown` fires (the daemon's own safe stop then
    /// takes over).
    pub fn new(
        plant: Arc<Plant>,
        hub: Arc<Hub>,
        action: StopAction,
        shutdown: CancellationToken,
    ) -> Arc<Self> {
        Arc::new(LeaseBook {
            plant,
            hub,
            action,
            shutdown,
            leases: Mutex::new(HashMap::new()),
            live_connections: Mutex::new(HashSet::new()),
            next_id: AtomicU64::new(1),
            tasks: TaskTracker::new(),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<usize, Lease>> {
        self.leases.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn live(&self) -> std::sync::MutexGuard<'_, HashSet<u64>> {
        self.live_connections
            .lock()
            .unwrap_or_else(|p| p.into_inner())
    }

    fn info(&self, index: usize, lease: &Lease) -> LeaseInfo {
        let left = lease
            .deadline
            .borrow()
            .saturating_duration_since(Instant::now());
        LeaseInfo {
            drive: self
                .plant
                .drives()
                .get(index)
                .map_or_else(String::new, |d| d.name.clone()),
            owner: lease.owner.to_string(),
            lease_ms: millis(lease.duration),
            expires_in_ms: millis(left),
            websocket: lease.connection.is_some(),
        }
    }

    /// Puts a lease of `duration` on drive `index` for `owner` (over the
    /// WebSocket `connection`, if any), covering a setpoint for `mode`,
    /// replacing any lease there. Until [`confirm`](Self::confirm) it runs
    /// for `duration + pending`, the time the setpoint may take to reach
    /// the drive.
    pub fn grant(
        self: &Arc<Self>,
        index: usize,
        mode: Mode,
        owner: &Arc<str>,
        connection: Option<u64>,
        duration: Duration,
        pending: Duration,
    ) -> Grant {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let (deadline, rx) = watch::channel(Instant::now() + duration + pending);
        let lease = Lease {
            id,
            mode,
            owner: owner.clone(),
            connection,
            duration,
            deadline,
            confirmed: false,
        };
        // Dropping a replaced lease drops its sender, which ends its watcher.
        let replaced = self.lock().insert(index, lease).is_some();
        let book = self.clone();
        self.tasks
            .spawn(async move { book.watch(index, id, rx).await });
        Grant { id, replaced }
    }

    /// The setpoint of lease `id` was sent: its deadline is now `duration`
    /// ahead. A lease whose WebSocket closed meanwhile expires at once.
    pub fn confirm(self: &Arc<Self>, index: usize, id: u64) -> Option<LeaseInfo> {
        let orphan = {
            let mut leases = self.lock();
            let closed = {
                let lease = leases.get(&index).filter(|l| l.id == id)?;
                lease.connection.is_some_and(|c| !self.live().contains(&c))
            };
            if !closed {
                let lease = leases.get_mut(&index)?;
                lease.confirmed = true;
                lease.deadline.send_replace(Instant::now() + lease.duration);
                return Some(self.info(index, lease));
            }
            leases.remove(&index)
        };
        if let Some(lease) = orphan {
            self.spawn_expiry(index, lease, "its WebSocket closed");
        }
        None
    }

    /// Takes lease `id` back without a stop (its setpoint surely did not
    /// reach the drive and it replaced no other lease).
    pub fn withdraw(&self, index: usize, id: u64) {
        let mut leases = self.lock();
        if leases.get(&index).is_some_and(|l| l.id == id) {
            leases.remove(&index);
        }
    }

    /// Pushes the deadline of drive `index`'s lease ahead by its length (or
    /// by a new `duration`); `None` when there is no lease (it expired).
    /// While its setpoint waits for the bus the deadline is never brought
    /// closer: the lease would end, and the stop go out at emergency
    /// priority, before the setpoint it covers, which would then leave the
    /// motor running with no lease.
    pub fn renew(&self, index: usize, duration: Option<Duration>) -> Option<LeaseInfo> {
        let mut leases = self.lock();
        let lease = leases.get_mut(&index)?;
        if let Some(d) = duration {
            lease.duration = d;
        }
        let renewed = Instant::now() + lease.duration;
        let deadline = if lease.confirmed {
            renewed
        } else {
            renewed.max(*lease.deadline.borrow())
        };
        lease.deadline.send_replace(deadline);
        Some(self.info(index, lease))
    }

    /// Ends drive `index`'s lease without a stop action.
    pub fn release(&self, index: usize) -> Option<LeaseInfo> {
        let lease = self.lock().remove(&index)?;
        Some(self.info(index, &lease))
    }

    /// Drive `index`'s lease, if any.
    pub fn get(&self, index: usize) -> Option<LeaseInfo> {
        let leases = self.lock();
        leases.get(&index).map(|l| self.info(index, l))
    }

    /// A WebSocket connection opened: leases may be tied to it.
    pub fn connection_opened(&self, connection: u64) {
        self.live().insert(connection);
    }

    /// A WebSocket connection closed: its leases expire now.
    pub fn connection_closed(self: &Arc<Self>, connection: u64) {
        self.live().remove(&connection);
        let ended: Vec<(usize, Lease)> = {
            let mut leases = self.lock();
            let indexes: Vec<usize> = leases
                .iter()
                .filter(|(_, l)| l.connection == Some(connection))
                .map(|(i, _)| *i)
                .collect();
            indexes
                .into_iter()
                .filter_map(|i| leases.remove(&i).map(|l| (i, l)))
                .collect()
        };
        for (index, lease) in ended {
            self.spawn_expiry(index, lease, "its WebSocket closed");
        }
    }

    /// Waits for the watchers and stop actions to finish (after shutdown).
    pub async fn wait(&self) {
        self.tasks.close();
        self.tasks.wait().await;
    }

    fn take_if_due(&self, index: usize, id: u64) -> Due {
        let mut leases = self.lock();
        match leases.get(&index) {
            Some(l) if l.id == id => {
                if *l.deadline.borrow() <= Instant::now() {
                    leases.remove(&index).map_or(Due::Gone, Due::Expired)
                } else {
                    Due::Later
                }
            }
            _ => Due::Gone,
        }
    }

    async fn watch(self: Arc<Self>, index: usize, id: u64, mut rx: watch::Receiver<Instant>) {
        loop {
            let deadline = *rx.borrow_and_update();
            tokio::select! {
                () = self.shutdown.cancelled() => return,
                () = tokio::time::sleep_until(deadline.into()) => {
                    match self.take_if_due(index, id) {
                        Due::Expired(lease) => {
                            self.expire(index, lease, "it was not renewed in time").await;
                            return;
                        }
                        Due::Later => {}
                        Due::Gone => return,
                    }
                }
                changed = rx.changed() => {
                    if changed.is_err() {
                        return; // released or replaced
                    }
                }
            }
        }
    }

    fn spawn_expiry(self: &Arc<Self>, index: usize, lease: Lease, why: &'static str) {
        if self.shutdown.is_cancelled() {
            return; // the daemon's safe stop covers every moving drive
        }
        let book = self.clone();
        self.tasks
            .spawn(async move { book.expire(index, lease, why).await });
    }

    /// Applies the stop action to drive `index` because `lease` ended.
    async fn expire(&self, index: usize, lease: Lease, why: &str) {
        let Some(drive) = self.plant.drives().get(index) else {
            return;
        };
        let bus = self.plant.handle_of(drive);
        let unit = drive.unit;
        let who = format!("lease-expiry ({})", lease.owner);
        let outcome = safety::stop_drive(bus, unit, self.action, false, Some(lease.mode)).await;
        let (sent, result) = match outcome {
            Ok(StopOutcome {
                sent: Some(request),
                ..
            }) => {
                let result = Ok("confirmed by the drive".to_string());
                audit::write(&who, bus.name(), unit, &describe(&request), &result);
                (Some(describe(&request)), result)
            }
            Ok(StopOutcome { mode, .. }) if self.action != StopAction::None => (
                None,
                Ok(format!(
                    "nothing to send: {} in {} mode holds the motor",
                    self.action.name(),
                    mode.map_or("unknown", |m| m.name())
                )),
            ),
            Ok(_) => (
                None,
                Ok("on_lease_expiry = \"none\": nothing sent".to_string()),
            ),
            Err(e) => {
                let result = Err(e.to_string());
                audit::write(&who, bus.name(), unit, self.action.name(), &result);
                (Some(self.action.name().to_string()), result)
            }
        };
        match &result {
            Ok(r) => tracing::warn!(
                drive = %drive.name,
                owner = %lease.owner,
                action = self.action.name(),
                "lease ended because {why}: {r}"
            ),
            Err(e) => tracing::error!(
                drive = %drive.name,
                owner = %lease.owner,
                action = self.action.name(),
                "lease ended because {why}, but the stop action failed: {e}"
            ),
        }
        self.hub.publish(
            Some(index),
            &ServerMessage::LeaseExpired {
                drive: drive.name.clone(),
                bus: bus.name().to_string(),
                unit,
                owner: lease.owner.to_string(),
                reason: why.to_string(),
                action: self.action.name().to_string(),
                sent,
                ok: result.is_ok(),
                result: result.unwrap_or_else(|e| e),
            },
        );
    }
}

fn millis(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}
