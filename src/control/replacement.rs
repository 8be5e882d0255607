//! A drive replacement as one procedure in the audit log: its start and
//! its end, between which its own writes (the address broadcast, the
//! settings, the calibration) are audited as every write is. A guided
//! client (the console's replace-a-drive page) says when it starts and
//! ends; the core checks the role and writes the line, so every face
//! words it the same.

use super::audit;
use super::caller::Caller;
use super::outcome::Refusal;
use super::parts::Parts;
use super::policy::Operation;
use super::rules;
use crate::listed_enum;

listed_enum! {
    /// Where a replacement procedure is.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum ReplacementEvent {
        /// The procedure started: the drive to replace is chosen.
        Started,
        /// Every step done: the new drive holds the settings.
        Finished,
        /// Left before its end (the page was closed, a step failed).
        Abandoned,
    }
}

impl ReplacementEvent {
    /// Its name in the API and the audit log.
    pub fn name(self) -> &'static str {
        match self {
            ReplacementEvent::Started => "started",
            ReplacementEvent::Finished => "finished",
            ReplacementEvent::Abandoned => "abandoned",
        }
    }
}

/// Notes in the audit log that `caller` started, finished or abandoned
/// the replacement of drive `drive` (an index in the plant), with
/// `detail` in the caller's words (where its settings came from, the
/// time it took). Commissioning work: the admin role.
pub(super) fn note_replacement(
    parts: &Parts,
    caller: &Caller,
    drive: usize,
    event: ReplacementEvent,
    detail: &str,
) -> Result<(), Refusal> {
    rules::role(caller, Operation::Replacement.needs())?;
    let name = parts.drive_name(drive);
    audit::replacement(caller.face.name(), &caller.who, &name, event.name(), detail);
    Ok(())
}
