//! What the drives of a bus that a reload reopened did meanwhile, from
//! their own statuses: the last one before the port closed and the first
//! one after it opened again. How long their polling paused is measured
//! between the two; a drive that reports another motion after than before
//! (stopped, set going, in another mode, inactive) is named with both, so
//! the reload's answer says what the drives say, not what was meant.

use std::time::{Duration, Instant};

use tokio::sync::broadcast::error::RecvError;

use crate::bus::BusEvent;
use crate::control::reload::motion_changed;
use crate::drive::Status;
use crate::plant::Directory;

/// How long the answer waits for a reopened bus's drives to be polled
/// again: a port that does not open is the plant's problem to tell, a
/// drive slow to answer this one's.
const LIMIT: Duration = Duration::from_secs(5);

/// A drive of a bus about to reopen, as last polled.
struct Seen {
    slot: usize,
    name: String,
    bus: String,
    status: Status,
    at: Instant,
}

/// The drives of the buses about to reopen that answered, as last polled.
pub(super) struct Before(Vec<Seen>);

/// What the drives did while their buses reopened, in words.
#[derive(Debug, Default)]
pub(super) struct Told {
    /// Drives whose motion changed, with their statuses before and after.
    pub stopped: Vec<String>,
    /// Each reopened bus's drives, and how long their polling paused.
    pub paused: Vec<String>,
}

impl Before {
    /// The drives of `buses` (by name) in `now` with a status.
    pub(super) fn take(now: &Directory, buses: &[String]) -> Before {
        let mut seen = Vec::new();
        for (slot, d) in now.indexed_drives() {
            let Some(bus) = now.bus_at(d.bus) else {
                continue;
            };
            if !buses.iter().any(|b| b == bus.handle.name()) {
                continue;
            }
            let Some(snapshot) = bus.handle.drive(d.unit) else {
                continue;
            };
            if let (Some(status), Some(at)) = (snapshot.status, snapshot.seen_instant) {
                seen.push(Seen {
                    slot,
                    name: d.name.clone(),
                    bus: bus.handle.name().to_string(),
                    status,
                    at,
                });
            }
        }
        Before(seen)
    }

    /// Waits (at most [`LIMIT`]) for each drive's first status on its
    /// reopened bus in `after`, and tells what it says.
    pub(super) async fn after(self, after: &Directory) -> Told {
        let mut told = Told::default();
        let mut buses: Vec<&str> = self.0.iter().map(|s| s.bus.as_str()).collect();
        buses.sort_unstable();
        buses.dedup();
        let deadline = tokio::time::Instant::now() + LIMIT;
        for bus in buses {
            let drives: Vec<&Seen> = self.0.iter().filter(|s| s.bus == bus).collect();
            let polled = first_statuses(after, &drives, deadline).await;
            let why = format!("bus {bus} reopened");
            let mut longest = Duration::ZERO;
            let mut names = Vec::new();
            for (seen, first) in drives.iter().zip(&polled) {
                match first {
                    Some((status, at)) => {
                        longest = longest.max(at.saturating_duration_since(seen.at));
                        names.push(seen.name.as_str());
                        told.stopped
                            .extend(motion_changed(&seen.name, &why, &seen.status, status));
                    }
                    None => told.paused.push(format!(
                        "drive {} has not been polled since {why} ({} s)",
                        seen.name,
                        LIMIT.as_secs()
                    )),
                }
            }
            if !names.is_empty() {
                told.paused.push(format!(
                    "polling of {} paused {} ms while {why}",
                    names.join(", "),
                    longest.as_millis()
                ));
            }
        }
        told
    }
}

/// The first status of each of `drives` (by slot) on its bus in `after`,
/// with when it was read; `None` for one not polled by `deadline` (or no
/// longer configured).
async fn first_statuses(
    after: &Directory,
    drives: &[&Seen],
    deadline: tokio::time::Instant,
) -> Vec<Option<(Status, Instant)>> {
    let handles: Vec<_> = drives
        .iter()
        .map(|s| {
            let d = after.drive_at(s.slot)?;
            Some((after.handle_of(d)?.clone(), d.unit))
        })
        .collect();
    // Subscribed before the cache is read: no status falls between.
    let mut events = handles
        .iter()
        .flatten()
        .next()
        .map(|(handle, _)| handle.subscribe());
    loop {
        let firsts: Vec<Option<(Status, Instant)>> = handles
            .iter()
            .map(|h| {
                let (handle, unit) = h.as_ref()?;
                let snapshot = handle.drive(*unit)?;
                Some((snapshot.status?, snapshot.seen_instant?))
            })
            .collect();
        let waiting = handles
            .iter()
            .zip(&firsts)
            .any(|(h, f)| h.is_some() && f.is_none());
        let Some(rx) = events.as_mut().filter(|_| waiting) else {
            return firsts;
        };
        match tokio::time::timeout_at(deadline, rx.recv()).await {
            Ok(Ok(BusEvent::Status { .. }) | Err(RecvError::Lagged(_))) => {}
            Ok(Ok(_)) => continue,
            Ok(Err(RecvError::Closed)) | Err(_) => return firsts,
        }
    }
}
