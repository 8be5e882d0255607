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
//! mid-request), the motor is still covered. Should the lease end before
//! its setpoint is confirmed all the same, the stop is sent again once it
//! is: the setpoint may have landed after the stop.
//!
//! A stop is followed until it is done. One that fails (bus down, no
//! answer, not confirmed) is tried again with backoff, and at once when the
//! bus or the drive comes back, until the drive confirms it, until
//! something newer takes over the drive (a leased setpoint the drive
//! confirmed, or a confirmed setpoint, brake or deactivation), or until
//! shutdown, whose own safe stop covers every moving drive. How each
//! drive's last lease ended is kept, so a client that finds no lease is told
//! what really happened.
//!
//! A lease's end, and how its stop ended, are published on the stream for
//! the drive's subscribers, and sent directly to the stream session that
//! held the lease (if it is still open): that one cannot be skipped for a
//! client that reads slowly, and needs no subscription.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::ws::Utf8Bytes;
use serde::Serialize;
use tokio::sync::{broadcast, mpsc, watch};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use utoipa::ToSchema;

use super::control::describe;
use super::hub::{Hub, ServerMessage};
use crate::audit;
use crate::bus::{BusError, BusEvent, Origin};
use crate::drive::Mode;
use crate::plant::Plant;
use crate::safety::{self, StopAction, StopOutcome};

/// First wait before a failed stop is tried again; it doubles up to
/// [`RETRY_MAX`], and the bus or the drive coming back cuts it short.
const RETRY_FIRST: Duration = Duration::from_millis(250);
/// Longest wait between two tries of a failed stop.
const RETRY_MAX: Duration = Duration::from_secs(5);

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

/// How a drive's last lease ended.
struct Ended {
    /// The lease's id.
    id: u64,
    owner: Arc<str>,
    /// The stream session it was taken over, told how it ended.
    connection: Option<u64>,
    at: Instant,
    how: How,
}

impl Ended {
    /// `lease` ended now, `how`.
    fn now(lease: Lease, how: How) -> Self {
        Ended {
            id: lease.id,
            owner: lease.owner,
            connection: lease.connection,
            at: Instant::now(),
            how,
        }
    }
}

enum How {
    /// Ended without a stop (`DELETE .../lease`) by this caller.
    Released(Arc<str>),
    /// Ended by a confirmed write that stops the motor itself.
    EndedBy(String),
    /// Ran out, or its WebSocket closed: the stop action.
    Stopping {
        why: &'static str,
        mode: Mode,
        stop: Stop,
    },
}

/// Where a lease's stop stands.
enum Stop {
    /// Being sent, or waiting to be tried again after `failures` tries;
    /// `again`: sent once more even if the try under way succeeds.
    Pending {
        failures: u32,
        last_error: Option<String>,
        again: bool,
    },
    /// Carried out (or nothing was needed): what the drive confirmed.
    Done(String),
    /// Not tried again: this took over the drive first.
    Superseded(String),
    /// Left to the daemon's safe stop at shutdown.
    Abandoned,
}

/// What [`LeaseBook::grant`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grant {
    /// The new lease's id.
    pub id: u64,
    /// True when it replaced a lease on the drive.
    pub replaced: bool,
}

/// Everything the book holds, under one lock.
#[derive(Default)]
struct Book {
    leases: HashMap<usize, Lease>,
    ended: HashMap<usize, Ended>,
    /// Open stream sessions, each with the way to send it lease news.
    live_connections: HashMap<u64, mpsc::UnboundedSender<Utf8Bytes>>,
}

impl Book {
    /// True when drive `index`'s last lease has a stop still to be done.
    fn stop_pending(&self, index: usize) -> bool {
        matches!(
            self.ended.get(&index),
            Some(Ended {
                how: How::Stopping {
                    stop: Stop::Pending { .. },
                    ..
                },
                ..
            })
        )
    }

    /// Something newer took over drive `index`: a stop still to be done
    /// there is not tried again.
    fn supersede(&mut self, index: usize, by: &str) {
        if let Some(Ended {
            how: How::Stopping { stop, .. },
            ..
        }) = self.ended.get_mut(&index)
            && matches!(stop, Stop::Pending { .. })
        {
            *stop = Stop::Superseded(by.to_string());
        }
    }
}

/// What follows a try of a stop.
enum Next {
    /// Done, or no longer this stop's business.
    Done,
    /// It failed: try again after a pause.
    Retry,
    /// It succeeded, but the lease's setpoint landed meanwhile: once more.
    Again,
}

/// The next step of a stop.
enum Turn {
    /// Send it, deciding on `mode` if the drive's cannot be read.
    Go { mode: Mode },
    /// A newer lease covers the drive while its setpoint is unconfirmed:
    /// wait, and go on if that lease is withdrawn.
    Hold,
    /// Nothing more to do; `Some` names what took over.
    Over(Option<String>),
}

/// The lease a stop is for, as its messages name it.
#[derive(Clone, Copy)]
struct EndedLease<'a> {
    index: usize,
    owner: &'a str,
    connection: Option<u64>,
    why: &'static str,
}

/// Every lease of the plant.
pub struct LeaseBook {
    plant: Arc<Plant>,
    hub: Arc<Hub>,
    action: StopAction,
    shutdown: CancellationToken,
    book: Mutex<Book>,
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
            book: Mutex::new(Book::default()),
            next_id: AtomicU64::new(1),
            tasks: TaskTracker::new(),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Book> {
        self.book.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn drive_name(&self, index: usize) -> String {
        self.plant
            .drives()
            .get(index)
            .map_or_else(String::new, |d| d.name.clone())
    }

    fn info(&self, index: usize, lease: &Lease) -> LeaseInfo {
        let left = lease
            .deadline
            .borrow()
            .saturating_duration_since(Instant::now());
        LeaseInfo {
            drive: self.drive_name(index),
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
        let replaced = self.lock().leases.insert(index, lease).is_some();
        let book = self.clone();
        self.tasks
            .spawn(async move { book.watch(index, id, rx).await });
        Grant { id, replaced }
    }

    /// The setpoint of lease `id` was sent (`applied`: and the drive
    /// confirmed it): its deadline is now `duration` ahead, and a confirmed
    /// setpoint takes over from a stop still being tried. A lease whose
    /// WebSocket closed meanwhile ends at once, with its stop; one that
    /// ended already has its stop sent again, since the setpoint may have
    /// landed after it.
    pub fn confirm(self: &Arc<Self>, index: usize, id: u64, applied: bool) -> Option<LeaseInfo> {
        let mut book = self.lock();
        let Some(lease) = book.leases.get(&index).filter(|l| l.id == id) else {
            // It ended while its setpoint waited: the setpoint may have
            // landed after the stop and set the motor going again.
            if self.stop_again(&mut book, index, id) {
                drop(book);
                self.spawn_stop(index, id, true);
            }
            return None;
        };
        let closed = lease
            .connection
            .is_some_and(|c| !book.live_connections.contains_key(&c));
        if closed {
            let lease = book.leases.remove(&index)?;
            let go = self.begin_stop(&mut book, index, lease, "its WebSocket closed");
            drop(book);
            if let Some(id) = go {
                self.spawn_stop(index, id, false);
            }
            return None;
        }
        let lease = book.leases.get_mut(&index)?;
        lease.confirmed = true;
        lease.deadline.send_replace(Instant::now() + lease.duration);
        let info = self.info(index, lease);
        if applied {
            let by = format!("a leased setpoint from {}", lease.owner);
            book.supersede(index, &by);
        }
        Some(info)
    }

    /// Takes lease `id` back without a stop (its setpoint surely did not
    /// reach the drive and it replaced no other lease).
    pub fn withdraw(&self, index: usize, id: u64) {
        let mut book = self.lock();
        if book.leases.get(&index).is_some_and(|l| l.id == id) {
            book.leases.remove(&index);
        }
    }

    /// Pushes the deadline of drive `index`'s lease ahead by its length (or
    /// by a new `duration`). While its setpoint waits for the bus the
    /// deadline is never brought closer: the lease would end, and the stop
    /// go out at emergency priority, before the setpoint it covers, which
    /// would then leave the motor running with no lease. Without a lease,
    /// the error says what became of the last one.
    pub fn renew(&self, index: usize, duration: Option<Duration>) -> Result<LeaseInfo, String> {
        let mut book = self.lock();
        let Some(lease) = book.leases.get_mut(&index) else {
            return Err(self.no_lease(&book, index));
        };
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
        Ok(self.info(index, lease))
    }

    /// Ends drive `index`'s lease without a stop action, for `by`; without
    /// a lease, the error says what became of the last one.
    pub fn release(&self, index: usize, by: &Arc<str>) -> Result<LeaseInfo, String> {
        let mut book = self.lock();
        let Some(lease) = book.leases.remove(&index) else {
            return Err(self.no_lease(&book, index));
        };
        let info = self.info(index, &lease);
        // A stop still to be done for an older lease goes on: what it
        // stops was never confirmed to have changed.
        if !book.stop_pending(index) {
            book.ended
                .insert(index, Ended::now(lease, How::Released(by.clone())));
        }
        Ok(info)
    }

    /// A write that stops the motor itself (`what`: the brake, the
    /// deactivation) was confirmed on drive `index`: its lease ends without
    /// a stop action (a zero-speed setpoint would release the brake), and a
    /// stop still being tried there is not needed any more.
    pub fn end_by(&self, index: usize, what: &str) {
        let mut book = self.lock();
        book.supersede(index, what);
        if let Some(lease) = book.leases.remove(&index) {
            book.ended
                .insert(index, Ended::now(lease, How::EndedBy(what.to_string())));
        }
    }

    /// A setpoint without a lease (`what`) was confirmed on drive `index`:
    /// it takes over from a stop still being tried there. A lease in place
    /// stays.
    pub fn took_over(&self, index: usize, what: &str) {
        self.lock().supersede(index, what);
    }

    /// Drive `index`'s lease, if any.
    pub fn get(&self, index: usize) -> Option<LeaseInfo> {
        let book = self.lock();
        book.leases.get(&index).map(|l| self.info(index, l))
    }

    /// A WebSocket connection opened: leases may be tied to it, and news
    /// of their end goes to `notices`.
    pub fn connection_opened(&self, connection: u64, notices: mpsc::UnboundedSender<Utf8Bytes>) {
        self.lock().live_connections.insert(connection, notices);
    }

    /// A WebSocket connection closed: its leases end now, with their stop.
    pub fn connection_closed(self: &Arc<Self>, connection: u64) {
        let started: Vec<(usize, u64)> = {
            let mut book = self.lock();
            book.live_connections.remove(&connection);
            let indexes: Vec<usize> = book
                .leases
                .iter()
                .filter(|(_, l)| l.connection == Some(connection))
                .map(|(i, _)| *i)
                .collect();
            let mut started = Vec::new();
            for index in indexes {
                if let Some(lease) = book.leases.remove(&index)
                    && let Some(id) =
                        self.begin_stop(&mut book, index, lease, "its WebSocket closed")
                {
                    started.push((index, id));
                }
            }
            started
        };
        for (index, id) in started {
            self.spawn_stop(index, id, false);
        }
    }

    /// Waits for the watchers and stop actions to finish (after shutdown).
    pub async fn wait(&self) {
        self.tasks.close();
        self.tasks.wait().await;
    }

    /// What became of drive `index`'s last lease, for a client that finds
    /// none.
    fn no_lease(&self, book: &Book, index: usize) -> String {
        let drive = self.drive_name(index);
        let Some(ended) = book.ended.get(&index) else {
            return format!(
                "drive \"{drive}\" has no lease: none was granted since drivegate started"
            );
        };
        let ago = ended.at.elapsed().as_secs_f64();
        let head = format!(
            "drive \"{drive}\" has no lease: the last one, held by {}, ended {ago:.1} s ago",
            ended.owner
        );
        let action = self.action.name();
        match &ended.how {
            How::Released(by) => {
                format!("{head}, released by {by} without a stop; the motor kept its setpoint")
            }
            How::EndedBy(what) => format!("{head} when {what} was confirmed"),
            How::Stopping { why, stop, .. } => {
                let stop = match stop {
                    Stop::Pending { failures: 0, .. } => {
                        format!("its stop ({action}) is being sent")
                    }
                    Stop::Pending {
                        failures,
                        last_error,
                        ..
                    } => format!(
                        "its stop ({action}) is not confirmed yet: {failures} attempt(s) failed, the last with \"{}\"; drivegate keeps trying it until the drive confirms it",
                        last_error.as_deref().unwrap_or("no answer")
                    ),
                    Stop::Done(result) => format!("its stop ({action}) was carried out: {result}"),
                    Stop::Superseded(by) => format!(
                        "its stop ({action}) was not confirmed before {by} took over the drive, and is not tried again"
                    ),
                    Stop::Abandoned => format!(
                        "its stop ({action}) was left to the safe stop of drivegate, which was stopping"
                    ),
                };
                format!("{head} because {why}; {stop}")
            }
        }
    }

    /// Records that `lease` on drive `index` ended because `why`, with its
    /// stop pending; the stop's task is for the caller to start (outside
    /// the lock) with the id returned. `None` at shutdown: the daemon's
    /// safe stop covers every moving drive.
    fn begin_stop(
        &self,
        book: &mut Book,
        index: usize,
        lease: Lease,
        why: &'static str,
    ) -> Option<u64> {
        let shutting_down = self.shutdown.is_cancelled();
        let (id, mode) = (lease.id, lease.mode);
        let stop = if shutting_down {
            Stop::Abandoned
        } else {
            Stop::Pending {
                failures: 0,
                last_error: None,
                again: false,
            }
        };
        book.ended
            .insert(index, Ended::now(lease, How::Stopping { why, mode, stop }));
        (!shutting_down).then_some(id)
    }

    /// Starts the stop of lease `id` (`announced`: its end was published).
    fn spawn_stop(self: &Arc<Self>, index: usize, id: u64, announced: bool) {
        let book = self.clone();
        self.tasks
            .spawn(async move { book.carry_out_stop(index, id, announced).await });
    }

    /// Ends lease `id` on drive `index` if its deadline has passed; true
    /// when it did (its stop is then pending).
    fn end_if_due(&self, index: usize, id: u64) -> Option<bool> {
        let mut book = self.lock();
        let due = match book.leases.get(&index) {
            Some(l) if l.id == id => *l.deadline.borrow() <= Instant::now(),
            _ => return None,
        };
        if !due {
            return Some(false);
        }
        let lease = book.leases.remove(&index)?;
        Some(
            self.begin_stop(&mut book, index, lease, "it was not renewed in time")
                .is_some(),
        )
    }

    async fn watch(self: Arc<Self>, index: usize, id: u64, mut rx: watch::Receiver<Instant>) {
        loop {
            let deadline = *rx.borrow_and_update();
            tokio::select! {
                () = self.shutdown.cancelled() => return,
                () = tokio::time::sleep_until(deadline.into()) => {
                    match self.end_if_due(index, id) {
                        Some(true) => {
                            self.carry_out_stop(index, id, false).await;
                            return;
                        }
                        Some(false) => {}
                        None => return,
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

    /// What to do next for the stop of lease `id` on drive `index`.
    fn turn(&self, index: usize, id: u64) -> Turn {
        let book = self.lock();
        match book.ended.get(&index) {
            Some(Ended {
                id: ended,
                how: How::Stopping { mode, stop, .. },
                ..
            }) if *ended == id => match stop {
                Stop::Pending { .. } if book.leases.contains_key(&index) => Turn::Hold,
                Stop::Pending { .. } => Turn::Go { mode: *mode },
                Stop::Superseded(by) => Turn::Over(Some(by.clone())),
                Stop::Done(_) | Stop::Abandoned => Turn::Over(None),
            },
            _ => Turn::Over(None),
        }
    }

    /// Records a try of the stop of lease `id`: `Ok` with what the drive
    /// confirmed, or the error. Says whether to try again: after a pause
    /// when it failed, at once when the lease's own setpoint reached the
    /// drive during the try; not when it is done or something took over.
    fn record_try(&self, index: usize, id: u64, result: &Result<String, String>) -> Next {
        let mut book = self.lock();
        let Some(Ended {
            id: ended,
            how: How::Stopping { stop, .. },
            ..
        }) = book.ended.get_mut(&index)
        else {
            return Next::Done;
        };
        let Stop::Pending {
            failures, again, ..
        } = stop
        else {
            return Next::Done;
        };
        if *ended != id {
            return Next::Done;
        }
        let (failures, again) = (*failures, *again);
        match result {
            Ok(_) if again => {
                *stop = Stop::Pending {
                    failures,
                    last_error: None,
                    again: false,
                };
                Next::Again
            }
            Ok(done) => {
                *stop = Stop::Done(done.clone());
                Next::Done
            }
            Err(e) => {
                *stop = Stop::Pending {
                    failures: failures + 1,
                    last_error: Some(e.clone()),
                    again: false,
                };
                Next::Retry
            }
        }
    }

    /// Lease `id` on drive `index` ended before the drive confirmed its
    /// setpoint, so the stop may have gone out first and the setpoint
    /// landed after it: the stop is sent again, after the try under way if
    /// there is one. True when a new stop task is needed.
    fn stop_again(&self, book: &mut Book, index: usize, id: u64) -> bool {
        let Some(Ended {
            id: ended,
            how: How::Stopping { stop, .. },
            ..
        }) = book.ended.get_mut(&index)
        else {
            return false;
        };
        if *ended != id {
            return false;
        }
        let drive = self.drive_name(index);
        tracing::warn!(%drive, "a leased setpoint reached the drive after its lease had ended: sending the stop again");
        match stop {
            Stop::Pending { again, .. } => {
                *again = true;
                false
            }
            Stop::Done(_) if !self.shutdown.is_cancelled() => {
                *stop = Stop::Pending {
                    failures: 0,
                    last_error: None,
                    again: false,
                };
                true
            }
            // Taken over by something newer, or left to the safe stop.
            _ => false,
        }
    }

    fn abandon(&self, index: usize, id: u64) {
        let mut book = self.lock();
        if let Some(Ended {
            id: ended,
            how: How::Stopping { stop, .. },
            ..
        }) = book.ended.get_mut(&index)
            && *ended == id
            && matches!(stop, Stop::Pending { .. })
        {
            *stop = Stop::Abandoned;
        }
    }

    /// Carries out the stop of lease `id` on drive `index`, trying again
    /// after failures until it is done, taken over, or the daemon stops;
    /// `announced`: the lease's end was published already.
    async fn carry_out_stop(self: Arc<Self>, index: usize, id: u64, announced: bool) {
        let Some(drive) = self.plant.drives().get(index) else {
            return;
        };
        let Some((owner, connection, why)) = self.ended_lease(index, id) else {
            return;
        };
        let ended = EndedLease {
            index,
            owner: &owner,
            connection,
            why,
        };
        let bus = self.plant.handle_of(drive);
        let unit = drive.unit;
        let mut events = bus.subscribe();
        let mut wait = RETRY_FIRST;
        let mut tries: u32 = 0;
        loop {
            let mode = match self.turn(index, id) {
                Turn::Go { mode } => mode,
                Turn::Hold => {
                    self.pause(&mut events, unit, wait).await;
                    if self.shutdown.is_cancelled() {
                        self.abandon(index, id);
                        return;
                    }
                    continue;
                }
                Turn::Over(by) => {
                    if let Some(by) = by {
                        tracing::info!(drive = %drive.name, "the stop of an ended lease is not tried again: {by} took over the drive");
                        let result = Err(format!("not sent again: {by} took over the drive"));
                        if tries == 0 && !announced {
                            self.announce_expired(&ended, None, &result, false);
                        } else {
                            self.announce_retried(&ended, tries, None, result);
                        }
                    }
                    return;
                }
            };
            if self.shutdown.is_cancelled() {
                self.abandon(index, id);
                return;
            }
            tries += 1;
            let origin = Origin::LeaseExpiry {
                owner: owner.clone(),
            };
            let outcome =
                safety::stop_drive(bus, unit, self.action, false, Some(mode), origin).await;
            let (sent, result) = self.describe_outcome(&ended, outcome, tries == 1);
            let next = self.record_try(index, id, &result);
            if tries == 1 && !announced {
                self.announce_expired(&ended, sent.clone(), &result, matches!(next, Next::Retry));
            } else if matches!(next, Next::Done) && result.is_ok() {
                self.announce_retried(&ended, tries, sent, result.clone());
            }
            match next {
                Next::Done => return,
                Next::Again => {}
                Next::Retry => {
                    self.pause(&mut events, unit, wait).await;
                    wait = (wait * 2).min(RETRY_MAX);
                    if self.shutdown.is_cancelled() {
                        self.abandon(index, id);
                        return;
                    }
                }
            }
        }
    }

    /// Waits `wait`, or less if the bus opens or the drive answers again,
    /// or the daemon stops.
    async fn pause(&self, events: &mut broadcast::Receiver<BusEvent>, unit: u8, wait: Duration) {
        let back = async {
            loop {
                match events.recv().await {
                    Ok(BusEvent::BusUp { .. }) => return,
                    Ok(BusEvent::Online { unit: u, .. }) if u == unit => return,
                    Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                    Err(broadcast::error::RecvError::Closed) => std::future::pending().await,
                }
            }
        };
        tokio::select! {
            () = self.shutdown.cancelled() => {}
            () = tokio::time::sleep(wait) => {}
            () = back => {}
        }
    }

    /// The stop's outcome in words: what was sent, and what the drive
    /// confirmed (or why it failed); audited when something may have
    /// reached the drive, or on the first failure.
    fn describe_outcome(
        &self,
        ended: &EndedLease<'_>,
        outcome: Result<StopOutcome, BusError>,
        first: bool,
    ) -> (Option<String>, Result<String, String>) {
        let Some(drive) = self.plant.drives().get(ended.index) else {
            return (None, Err("no such drive".to_string()));
        };
        let bus = self.plant.handle_of(drive);
        let who = format!("lease-expiry ({})", ended.owner);
        match outcome {
            Ok(StopOutcome {
                sent: Some(request),
                ..
            }) => {
                let confirmed: Result<String, &str> = Ok("confirmed by the drive".to_string());
                audit::write(
                    &who,
                    bus.name(),
                    drive.unit,
                    &describe(&request),
                    &confirmed,
                );
                let sent = describe(&request);
                (
                    Some(sent.clone()),
                    Ok(format!("{sent} confirmed by the drive")),
                )
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
                if first || !e.not_sent() {
                    audit::write(
                        &who,
                        bus.name(),
                        drive.unit,
                        self.action.name(),
                        &Err::<String, _>(&e),
                    );
                }
                (Some(self.action.name().to_string()), Err(e.to_string()))
            }
        }
    }

    /// Logs and publishes the end of a lease and its first stop try.
    fn announce_expired(
        &self,
        ended: &EndedLease<'_>,
        sent: Option<String>,
        result: &Result<String, String>,
        retrying: bool,
    ) {
        let EndedLease {
            index, owner, why, ..
        } = *ended;
        let Some(drive) = self.plant.drives().get(index) else {
            return;
        };
        let action = self.action.name();
        match result {
            Ok(r) => {
                tracing::warn!(drive = %drive.name, %owner, action, "lease ended because {why}: {r}")
            }
            Err(e) if retrying => tracing::error!(
                drive = %drive.name, %owner, action,
                "lease ended because {why}, but the stop action failed: {e}; trying it again until the drive confirms it"
            ),
            Err(e) => {
                tracing::error!(drive = %drive.name, %owner, action, "lease ended because {why}, but the stop action failed: {e}")
            }
        }
        // What the stream shows as the result: the drive's answer, or why.
        let shown = match result {
            Ok(_) if sent.is_some() => Ok("confirmed by the drive".to_string()),
            other => other.clone(),
        };
        self.announce(
            ended,
            &ServerMessage::LeaseExpired {
                drive: drive.name.clone(),
                bus: self.plant.handle_of(drive).name().to_string(),
                unit: drive.unit,
                owner: owner.to_string(),
                reason: why.to_string(),
                action: action.to_string(),
                sent,
                ok: shown.is_ok(),
                result: shown.unwrap_or_else(|e| e),
                retrying,
            },
        );
    }

    /// Logs and publishes how a stop that failed at first ended: carried
    /// out after `tries` tries, or taken over.
    fn announce_retried(
        &self,
        ended: &EndedLease<'_>,
        tries: u32,
        sent: Option<String>,
        result: Result<String, String>,
    ) {
        let EndedLease { index, owner, .. } = *ended;
        let Some(drive) = self.plant.drives().get(index) else {
            return;
        };
        if let Ok(r) = &result {
            tracing::warn!(drive = %drive.name, %owner, "the stop of an ended lease was carried out at try {tries}: {r}");
        }
        let result = match result {
            Ok(_) if sent.is_some() => Ok("confirmed by the drive".to_string()),
            other => other,
        };
        self.announce(
            ended,
            &ServerMessage::LeaseStop {
                drive: drive.name.clone(),
                bus: self.plant.handle_of(drive).name().to_string(),
                unit: drive.unit,
                owner: owner.to_string(),
                action: self.action.name().to_string(),
                sent,
                stopped: result.is_ok(),
                attempts: tries,
                result: result.unwrap_or_else(|e| e),
            },
        );
    }

    /// Owner, stream session and reason of lease `id`, the last on drive
    /// `index`.
    fn ended_lease(&self, index: usize, id: u64) -> Option<(Arc<str>, Option<u64>, &'static str)> {
        let book = self.lock();
        match book.ended.get(&index)? {
            Ended {
                id: ended,
                owner,
                connection,
                how: How::Stopping { why, .. },
                ..
            } if *ended == id => Some((owner.clone(), *connection, why)),
            _ => None,
        }
    }

    /// Publishes `message` about a lease of `ended.index`, and sends it
    /// directly to the stream session that held the lease, if still open
    /// (which then skips the published copy).
    fn announce(&self, ended: &EndedLease<'_>, message: &ServerMessage) {
        let text = message.to_text();
        let owner = ended
            .connection
            .and_then(|c| Some((c, self.lock().live_connections.get(&c)?.clone())));
        let delivered_to =
            owner.and_then(|(c, notices)| notices.send(text.clone()).is_ok().then_some(c));
        self.hub.publish_text(Some(ended.index), delivered_to, text);
    }
}

fn millis(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}
