//! What the supervisor does when a face's task crashes: a panic (a bug, or
//! a crate's assertion) or an end on its own, while nobody asked it to
//! stop. The face is said down (the log, `/readyz`, the console's
//! overview), started again alone after a wait that grows while it keeps
//! crashing ([`Restarts`]), and counted (`drivegate_face_restarts_total`);
//! the buses and the other faces serve on.
//!
//! [`watched`] tells a crash from a stop; [`Restarts`] is the wait, pure
//! with time passed in.

use std::any::Any;
use std::time::Duration;

use tokio::task::JoinHandle;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::config::diff::Face;

/// The first wait before a crashed face is started again; it doubles to
/// [`WAIT_MAX`] while the face keeps crashing.
pub(super) const WAIT_MIN: Duration = Duration::from_secs(1);
/// The longest wait.
pub(super) const WAIT_MAX: Duration = Duration::from_secs(60);
/// A face that served this long before it crashed starts the waits over.
pub(super) const STABLE: Duration = Duration::from_secs(60);

/// How long a crashed face waits before it is started again.
#[derive(Debug, Clone)]
pub(super) struct Restarts {
    wait: Duration,
    /// When the face was last started.
    started: Instant,
}

impl Restarts {
    /// A face started at `now`.
    pub(super) fn new(now: Instant) -> Self {
        Restarts {
            wait: WAIT_MIN,
            started: now,
        }
    }

    /// It crashed at `now`: the wait before it is started again.
    pub(super) fn crashed(&mut self, now: Instant) -> Duration {
        if now.saturating_duration_since(self.started) >= STABLE {
            self.wait = WAIT_MIN;
        }
        let wait = self.wait;
        self.wait = (self.wait * 2).min(WAIT_MAX);
        wait
    }

    /// It was started again at `now` (or could not be: then it crashed
    /// again at once).
    pub(super) fn started(&mut self, now: Instant) {
        self.started = now;
    }
}

/// Each face's [`Restarts`].
#[derive(Debug, Default)]
pub(super) struct RestartBook(Vec<(Face, Restarts)>);

impl RestartBook {
    /// `face` was started at `now`.
    pub(super) fn started(&mut self, face: Face, now: Instant) {
        match self.0.iter_mut().find(|(f, _)| *f == face) {
            Some((_, r)) => r.started(now),
            None => self.0.push((face, Restarts::new(now))),
        }
    }

    /// `face` crashed at `now`: the wait before it is started again.
    pub(super) fn crashed(&mut self, face: Face, now: Instant) -> Duration {
        match self.0.iter_mut().find(|(f, _)| *f == face) {
            Some((_, r)) => r.crashed(now),
            None => WAIT_MIN,
        }
    }
}

/// Runs `task` to its end: `None` when `stop` had fired (a stop asked
/// for), else why it ended, in words ("it panicked: ...").
pub(super) async fn watched(task: JoinHandle<()>, stop: &CancellationToken) -> Option<String> {
    let end = task.await;
    if stop.is_cancelled() {
        return None;
    }
    Some(match end {
        Ok(()) => "its task ended on its own".to_string(),
        Err(e) if e.is_panic() => format!("it panicked: {}", panic_words(&*e.into_panic())),
        Err(_) => "its task was cancelled".to_string(),
    })
}

/// What a panic said (its message, when it is text).
pub(super) fn panic_words(payload: &(dyn Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "no message".to_string()
    }
}

/// What became of a crashed face's restart.
pub(super) enum Restart {
    /// It serves again.
    Done,
    /// A reload or the shutdown stopped or replaced it meanwhile.
    Replaced,
    /// It could not be started, in words.
    Failed(String),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wait_doubles_while_crashing_and_starts_over_after_a_stable_run() {
        let t0 = Instant::now();
        let mut r = Restarts::new(t0);
        let mut now = t0 + Duration::from_millis(10);
        let mut waits = Vec::new();
        for _ in 0..8 {
            let wait = r.crashed(now);
            waits.push(wait.as_secs());
            now += wait;
            r.started(now);
            now += Duration::from_millis(10);
        }
        assert_eq!(waits, [1, 2, 4, 8, 16, 32, 60, 60]);
        // A minute serving: the next crash waits the least again.
        now += STABLE;
        assert_eq!(r.crashed(now), WAIT_MIN);
    }

    #[tokio::test]
    async fn a_panic_is_told_from_a_stop() {
        let stop = CancellationToken::new();
        let panicking = tokio::spawn(async { panic!("Keep alives should be >= 5 secs") });
        assert_eq!(
            watched(panicking, &stop).await.as_deref(),
            Some("it panicked: Keep alives should be >= 5 secs")
        );
        let formatted = tokio::spawn(async {
            let n = 3;
            panic!("index {n} out of range")
        });
        assert_eq!(
            watched(formatted, &stop).await.as_deref(),
            Some("it panicked: index 3 out of range")
        );
        let ended = tokio::spawn(async {});
        assert_eq!(
            watched(ended, &stop).await.as_deref(),
            Some("its task ended on its own")
        );
        // Asked to stop: whatever its end, no crash.
        stop.cancel();
        let stopped = tokio::spawn(async { panic!("while stopping") });
        assert_eq!(watched(stopped, &stop).await, None);
    }
}
