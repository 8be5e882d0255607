//! The changes written into the configuration file through the core, the
//! newest last, kept in memory: who made the text the file holds now, so
//! that an apply refused because the file moved on since it was read can
//! name the other admin's change (`If-Match` in the API, the console's
//! editor). The audit log keeps them all; this keeps the last few.

use std::collections::VecDeque;
use std::sync::Mutex;
use std::time::SystemTime;

use super::caller::Caller;
use super::reload::NewText;
use crate::config::edit::sha256_hex;
use crate::config::text_diff;

/// Changes kept.
const KEPT: usize = 32;

/// One change written into the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigEdit {
    /// Who (`http commissioning`: the face and the token's name).
    pub by: String,
    /// When it was written.
    pub at: SystemTime,
    /// What, in words.
    pub what: String,
    /// Its lines in a few words (`line 24: name = "lift" became name =
    /// "hoist"`).
    pub lines: String,
    /// SHA-256 (hex) of the file before it.
    pub before: String,
    /// SHA-256 (hex) of the file it wrote.
    pub after: String,
}

impl ConfigEdit {
    /// The change `write` asked for by `caller`, as it is written now.
    pub(super) fn of(caller: &Caller, write: &NewText) -> Self {
        ConfigEdit {
            by: format!("{} {}", caller.face.name(), caller.who),
            at: SystemTime::now(),
            what: write.what.clone(),
            lines: text_diff::summary(&write.hunks),
            before: write.base_sha256.clone(),
            after: sha256_hex(&write.text),
        }
    }
}

/// The last changes.
#[derive(Default)]
pub(super) struct EditLog(Mutex<VecDeque<ConfigEdit>>);

impl EditLog {
    /// Keeps `edit`, dropping the oldest past [`KEPT`].
    pub(super) fn record(&self, edit: ConfigEdit) {
        let mut log = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if log.len() == KEPT {
            log.pop_front();
        }
        log.push_back(edit);
    }

    /// The changes kept, oldest first.
    pub(super) fn all(&self) -> Vec<ConfigEdit> {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .cloned()
            .collect()
    }
}

/// The changes that led from the file whose SHA-256 is `from` to the one
/// whose SHA-256 is `to`, oldest first, when `edits` hold the whole way
/// (`None` when some step was not made through drivegate: the file was
/// edited by hand).
pub fn between(edits: &[ConfigEdit], from: &str, to: &str) -> Option<Vec<ConfigEdit>> {
    let mut path = Vec::new();
    let mut at = to;
    while at != from {
        let step = edits.iter().rev().find(|e| e.after == at)?;
        if path.len() > edits.len() {
            return None;
        }
        path.push(step.clone());
        at = &step.before;
    }
    path.reverse();
    Some(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edit(by: &str, before: &str, after: &str) -> ConfigEdit {
        ConfigEdit {
            by: by.into(),
            at: SystemTime::UNIX_EPOCH,
            what: "configuration edited".into(),
            lines: String::new(),
            before: before.into(),
            after: after.into(),
        }
    }

    #[test]
    fn the_changes_since_a_version_are_found_or_said_unknown() {
        let edits = vec![
            edit("a", "s0", "s1"),
            edit("b", "s1", "s2"),
            edit("c", "s2", "s3"),
        ];
        let by =
            |v: Option<Vec<ConfigEdit>>| v.map(|v| v.into_iter().map(|e| e.by).collect::<Vec<_>>());
        assert_eq!(
            by(between(&edits, "s1", "s3")),
            Some(vec!["b".into(), "c".into()])
        );
        assert_eq!(by(between(&edits, "s3", "s3")), Some(vec![]));
        // Edited by hand in between: not known.
        assert_eq!(by(between(&edits, "s1", "s9")), None);
        // A loop (a change undone) does not run forever.
        let looped = vec![edit("a", "s0", "s1"), edit("b", "s1", "s0")];
        assert_eq!(by(between(&looped, "s9", "s1")), None);
    }

    #[test]
    fn the_log_keeps_the_last_changes() {
        let log = EditLog::default();
        for i in 0..(KEPT + 3) {
            log.record(edit("x", &format!("s{i}"), &format!("s{}", i + 1)));
        }
        let all = log.all();
        assert_eq!(all.len(), KEPT);
        assert_eq!(all[0].before, "s3");
    }
}
