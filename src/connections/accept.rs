//! Accept errors, which back off instead of spinning: out of file
//! descriptors (`EMFILE`, `ENFILE`) or kernel memory, the listener's socket
//! stays readable and `accept` fails again at once, so a loop that only
//! logs and retries burns a core and writes gigabytes of log. Each failure
//! in a row doubles the pause, from [`FIRST`] to [`LONGEST`], and the line
//! is written once per cause and second at most ([`super::repeats`]). A
//! client that went away before it was accepted is no failure of ours.

use std::io;
use std::time::{Duration, Instant};

use super::repeats::{Repeats, Say, folded_words};
use super::words::Face;

/// The pause after a first failure.
pub const FIRST: Duration = Duration::from_millis(10);

/// The longest pause.
pub const LONGEST: Duration = Duration::from_secs(1);

/// A listener's accept failures in a row, and their log.
#[derive(Debug)]
pub struct AcceptErrors {
    face: Face,
    streak: u32,
    log: Repeats<String>,
}

impl AcceptErrors {
    /// For the listener of `face`.
    pub fn new(face: Face) -> Self {
        AcceptErrors {
            face,
            streak: 0,
            log: Repeats::default(),
        }
    }

    /// A connection was accepted: the streak is over.
    pub fn accepted(&mut self) {
        self.streak = 0;
    }

    /// `accept` failed with `e`: how long to pause before the next (zero
    /// for a client that went away), the line written if one is due.
    pub fn failed(&mut self, e: &io::Error) -> Duration {
        let (pause, line) = self.judge(e, Instant::now());
        if let Some(line) = line {
            tracing::warn!(face = self.face.label, "{line}");
        }
        pause
    }

    /// The pause and the line for `e` at `now` (pure but for the count).
    pub fn judge(&mut self, e: &io::Error, now: Instant) -> (Duration, Option<String>) {
        if matches!(
            e.kind(),
            io::ErrorKind::ConnectionAborted | io::ErrorKind::ConnectionReset
        ) {
            return (Duration::ZERO, None);
        }
        let pause = FIRST.saturating_mul(1 << self.streak.min(10)).min(LONGEST);
        self.streak = self.streak.saturating_add(1);
        let hint = match e.raw_os_error() {
            Some(code) if code == nix::libc::EMFILE => {
                " (the process is out of file descriptors: LimitNOFILE in the unit; see drivegate_connections_held and process_open_fds)"
            }
            Some(code) if code == nix::libc::ENFILE => {
                " (the system is out of file descriptors: fs.file-max)"
            }
            _ => "",
        };
        let (folded, first) = match self.log.note(e.to_string(), now) {
            Say::Quiet => return (pause, None),
            Say::Line { folded, first } => (folded, first),
            Say::Many { folded } => (folded, false),
        };
        let line = format!(
            "{} accepts failing: {e}{hint}; pausing accepts {} ms, longer while it goes on{}",
            self.face.name,
            pause.as_millis(),
            folded_words(folded, first)
        );
        (pause, Some(line))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failures_in_a_row_back_off_and_log_once_per_second() {
        let mut errors = AcceptErrors::new(super::super::words::OPCUA);
        let emfile = io::Error::from_raw_os_error(nix::libc::EMFILE);
        let t0 = Instant::now();
        let mut lines = 0;
        let mut t = t0;
        let mut pauses = Vec::new();
        // Ten seconds of failures, each retried after its pause.
        while t < t0 + Duration::from_secs(10) {
            let (pause, line) = errors.judge(&emfile, t);
            pauses.push(pause);
            if let Some(line) = line {
                assert!(line.contains("LimitNOFILE"), "{line}");
                lines += 1;
            }
            t += pause;
        }
        assert_eq!(
            &pauses[..8],
            [10, 20, 40, 80, 160, 320, 640, 1000].map(Duration::from_millis)
        );
        // 0 s, 1 s, 3 s, 7 s (and one at the start of the next gap).
        assert!(lines <= 5, "{lines} lines");
        assert!(pauses.len() < 20, "{} accepts in 10 s", pauses.len());
        errors.accepted();
        assert_eq!(errors.judge(&emfile, t).0, FIRST);
        // A client gone before its accept costs nothing.
        let reset = io::Error::from(io::ErrorKind::ConnectionAborted);
        assert_eq!(errors.judge(&reset, t), (Duration::ZERO, None));
    }
}
