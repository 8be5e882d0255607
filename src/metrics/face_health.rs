//! Whether each face serves, or is down after a crash (a panic in its
//! task, or its task ending on its own) and waits to be restarted, and how
//! often it was: for `/readyz`, the console's overview and `/metrics`
//! (`drivegate_face_restarts_total`). The daemon's supervisor says it; a
//! face whose task crashed is restarted alone, the others serve on.

use std::sync::Mutex;
use std::time::SystemTime;

use prometheus::{IntCounterVec, Opts, Registry};

use crate::config::diff::Face;

/// One face's health.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FaceState {
    /// The face.
    pub face: Face,
    /// Down now: since when, why, and when it is started again.
    pub down: Option<Down>,
    /// Restarts after a crash since the daemon started.
    pub restarts: u64,
    /// The last crash, in words, and when.
    pub last_crash: Option<(SystemTime, String)>,
}

/// A face down.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Down {
    /// Since when.
    pub since: SystemTime,
    /// Why, in words ("it panicked: ...").
    pub why: String,
    /// When it is started again.
    pub restart_at: SystemTime,
}

/// The faces' health.
pub struct FaceHealth {
    restarts: IntCounterVec,
    faces: Mutex<Vec<FaceState>>,
}

impl FaceHealth {
    /// Creates the series (every face at 0) and registers them.
    pub fn register(registry: &Registry) -> Self {
        let restarts = IntCounterVec::new(
            Opts::new(
                "drivegate_face_restarts_total",
                "Faces restarted after their task crashed (a panic, or an end on its own), by face; /readyz and the log say why.",
            ),
            &["face"],
        )
        .unwrap_or_else(|e| panic!("invalid metric definition drivegate_face_restarts_total: {e}"));
        let _ = registry.register(Box::new(restarts.clone()));
        for face in Face::ALL {
            restarts.with_label_values(&[face.key()]);
        }
        FaceHealth {
            restarts,
            faces: Mutex::new(Vec::new()),
        }
    }

    fn with(&self, face: Face, f: impl FnOnce(&mut FaceState)) {
        if let Ok(mut faces) = self.faces.lock() {
            let i = match faces.iter().position(|s| s.face == face) {
                Some(i) => i,
                None => {
                    faces.push(FaceState {
                        face,
                        down: None,
                        restarts: 0,
                        last_crash: None,
                    });
                    faces.len() - 1
                }
            };
            f(&mut faces[i]);
        }
    }

    /// `face` crashed (or could not be started again), `why`; it is
    /// started again at `restart_at`.
    pub fn down(&self, face: Face, why: String, restart_at: SystemTime) {
        let now = SystemTime::now();
        self.with(face, |s| {
            let since = s.down.as_ref().map_or(now, |d| d.since);
            s.last_crash = Some((now, why.clone()));
            s.down = Some(Down {
                since,
                why,
                restart_at,
            });
        });
    }

    /// `face` serves again after a crash.
    pub fn restarted(&self, face: Face) {
        self.restarts.with_label_values(&[face.key()]).inc();
        self.with(face, |s| {
            s.down = None;
            s.restarts += 1;
        });
    }

    /// `face` was started (at start-up, by a reload): not down. Stopped
    /// while down, it is not waiting for a restart either.
    pub fn serving(&self, face: Face) {
        if let Ok(mut faces) = self.faces.lock()
            && let Some(s) = faces.iter_mut().find(|s| s.face == face)
        {
            s.down = None;
        }
    }

    /// The faces that crashed since the daemon started, down or serving
    /// again.
    pub fn states(&self) -> Vec<FaceState> {
        self.faces.lock().map(|f| f.clone()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_crash_is_down_until_restarted_and_counted_then() {
        let registry = Registry::new();
        let health = FaceHealth::register(&registry);
        assert!(health.states().is_empty());
        let at = SystemTime::now();
        health.down(Face::Mqtt, "it panicked: boom".into(), at);
        let s = &health.states()[0];
        assert_eq!(s.face, Face::Mqtt);
        assert_eq!(
            s.down.as_ref().map(|d| d.why.as_str()),
            Some("it panicked: boom")
        );
        assert_eq!(s.restarts, 0);
        // Down again before it served: since stays the first crash's.
        let since = s.down.as_ref().map(|d| d.since);
        health.down(Face::Mqtt, "it panicked: again".into(), at);
        assert_eq!(health.states()[0].down.as_ref().map(|d| d.since), since);
        health.restarted(Face::Mqtt);
        let s = &health.states()[0];
        assert!(s.down.is_none());
        assert_eq!(s.restarts, 1);
        assert_eq!(
            s.last_crash.as_ref().map(|c| c.1.as_str()),
            Some("it panicked: again")
        );
        assert_eq!(
            health.restarts.with_label_values(&["mqtt"]).get(),
            1,
            "the counter"
        );
    }
}
