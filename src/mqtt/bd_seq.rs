//! The birth/death sequence number (Sparkplug 3.0: `bdSeq`, 0-255): one
//! per connection, carried by the NBIRTH and by the NDEATH registered as
//! the connection's will, so a host can tell which birth a death ends.
//!
//! It is kept in `[safety] state_dir` (file `mqtt-bdseq`) and goes on
//! from there after a restart: when a killed daemon's will is delivered
//! late (after its successor's NBIRTH), it names the old connection's
//! bdSeq, not the new one's, and the host does not take the new node for
//! dead. Without a state directory it starts at 0.

use std::path::{Path, PathBuf};

/// The node's bdSeq.
#[derive(Debug)]
pub(super) struct BdSeq {
    value: u8,
    file: Option<PathBuf>,
    warned: bool,
}

/// The file's name in the state directory.
const FILE: &str = "mqtt-bdseq";

impl BdSeq {
    /// The bdSeq after the last one used by an earlier process (0 when
    /// none is known).
    pub(super) fn load(state_dir: Option<&Path>) -> BdSeq {
        let file = state_dir.map(|d| d.join(FILE));
        let last = file
            .as_ref()
            .and_then(|f| std::fs::read_to_string(f).ok())
            .and_then(|text| text.trim().parse::<u8>().ok());
        BdSeq {
            value: last.map_or(0, |v| v.wrapping_add(1)),
            file,
            warned: false,
        }
    }

    /// The current connection's.
    pub(super) fn get(&self) -> u8 {
        self.value
    }

    /// A connection with the current value starts: it is written down
    /// before the broker can hold a will with it.
    pub(super) fn connecting(&mut self) {
        let Some(file) = &self.file else { return };
        if let Some(dir) = file.parent() {
            let _ = std::fs::create_dir_all(dir);
        }
        if let Err(e) = std::fs::write(file, format!("{}\n", self.value))
            && !self.warned
        {
            self.warned = true;
            tracing::warn!(
                "MQTT: cannot keep bdSeq in {} ({e}): after a restart it starts at 0 again",
                file.display()
            );
        }
    }

    /// The connection ended: the next one takes the next value.
    pub(super) fn next(&mut self) {
        self.value = self.value.wrapping_add(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn goes_on_after_a_restart_and_wraps() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = BdSeq::load(Some(dir.path()));
        assert_eq!(a.get(), 0);
        a.connecting();
        a.next();
        a.connecting();
        // A new process goes on after the last one used.
        let b = BdSeq::load(Some(dir.path()));
        assert_eq!(b.get(), 2);
        std::fs::write(dir.path().join(FILE), "255\n").unwrap();
        assert_eq!(BdSeq::load(Some(dir.path())).get(), 0);
        assert_eq!(BdSeq::load(None).get(), 0);
    }
}
