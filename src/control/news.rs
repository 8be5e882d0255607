//! What the core tells: the payloads of its events ([`super::events`]) and
//! of its audit lines ([`super::audit`]), apart from the concepts that make
//! them (alarms, freshness, drift, settings, the start-up replay,
//! reloads). They stand at the bottom of the folder so that a concept can
//! publish and log them while the events and the audit log carry them
//! without knowing the concept.

use std::sync::Arc;
use std::time::SystemTime;

use super::alarms::book::Alarm;
use super::caller::Face;
use super::outcome::{Failure, Refusal};
use crate::bus::freshness::{Freshness, Verdict};
use crate::config::ApplySettings;
use crate::drive::wanted::{Difference, Refused as RefusedValue, Setting};

// Alarms.

/// News of an alarm, for whoever listens to the core.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AlarmNews {
    /// Raised (or an event repeated on it: `count` went up).
    Raised(Alarm),
    /// Its condition ended.
    Cleared(Alarm),
    /// An operator acknowledged it.
    Acknowledged(Alarm),
}

impl AlarmNews {
    /// The alarm as it now stands.
    pub fn alarm(&self) -> &Alarm {
        match self {
            AlarmNews::Raised(a) | AlarmNews::Cleared(a) | AlarmNews::Acknowledged(a) => a,
        }
    }
}

/// A drive's data changed freshness.
#[derive(Debug, Clone, PartialEq)]
pub struct FreshnessNews {
    /// The drive, by index in the plant.
    pub drive: usize,
    /// Its bus.
    pub bus: Arc<str>,
    /// Its unit address.
    pub unit: u8,
    /// What it was.
    pub was: Freshness,
    /// What it is now, why and since when.
    pub verdict: Verdict,
}

/// Where a drive stands with its declared settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DriftState {
    /// It holds them.
    Matches,
    /// It holds other values (the drift says which); nothing is done
    /// (`apply_settings = "never"`).
    Drifted,
    /// It holds other values, and they are written once the motor stands
    /// still (`on-drift`).
    WaitingForStandstill,
    /// Writing them failed (why); tried again when the drive next comes
    /// online.
    ApplyFailed(String),
    /// Its settings could not be read (why); compared when it next comes
    /// online.
    ReadFailed(String),
}

impl DriftState {
    /// Stable name for the API, events and metrics.
    pub fn name(&self) -> &'static str {
        match self {
            DriftState::Matches => "match",
            DriftState::Drifted => "drift",
            DriftState::WaitingForStandstill => "waiting-for-standstill",
            DriftState::ApplyFailed(_) => "apply-failed",
            DriftState::ReadFailed(_) => "read-failed",
        }
    }

    /// Why, for the failed states.
    pub fn detail(&self) -> Option<&str> {
        match self {
            DriftState::ApplyFailed(why) | DriftState::ReadFailed(why) => Some(why),
            _ => None,
        }
    }
}

/// The latest comparison of a drive with its declared settings.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftView {
    /// Where it stands.
    pub state: DriftState,
    /// The declared settings it does not hold (empty: none, or not
    /// known after a failed read).
    pub drift: Vec<Difference>,
    /// When it was compared (or the comparison failed).
    pub checked_at: SystemTime,
    /// What drivegate does about a drift.
    pub apply: ApplySettings,
}

impl DriftView {
    /// True when the drive is known not to hold its declared settings.
    pub fn drifted(&self) -> bool {
        !self.drift.is_empty()
    }
}

/// A drive's comparison with its declared settings, for the stream.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftChecked {
    /// The drive, by index in the plant.
    pub drive: usize,
    /// Its new state.
    pub view: DriftView,
}

/// What became of one setting of a document.
#[derive(Debug, Clone, PartialEq)]
pub enum SettingResult {
    /// The drive held it already; not written.
    Unchanged,
    /// A dry run: it would be written.
    WouldWrite,
    /// Written, and the drive confirmed it.
    Written,
    /// Its write failed (why, in words): it may or may not have been
    /// carried out, as the words say.
    Failed(String),
    /// Not sent, since an earlier write of the document failed.
    NotSent(String),
}

impl SettingResult {
    /// Stable name for the API and events.
    pub fn name(&self) -> &'static str {
        match self {
            SettingResult::Unchanged => "unchanged",
            SettingResult::WouldWrite => "would-write",
            SettingResult::Written => "written",
            SettingResult::Failed(_) => "failed",
            SettingResult::NotSent(_) => "not-sent",
        }
    }

    /// Why it failed or was not sent.
    pub fn detail(&self) -> Option<&str> {
        match self {
            SettingResult::Failed(why) | SettingResult::NotSent(why) => Some(why),
            _ => None,
        }
    }
}

/// One setting of a document: the drive's value before, the document's,
/// the value read back after, and what was done.
#[derive(Debug, Clone, PartialEq)]
pub struct SettingOutcome {
    /// The setting.
    pub setting: Setting,
    /// What the drive held before, raw.
    pub before: u32,
    /// What the document asks for, raw.
    pub wanted: u32,
    /// What the drive holds after, read back (absent for a dry run, or
    /// when the read-back failed).
    pub read_back: Option<u32>,
    /// What was done.
    pub result: SettingResult,
}

impl SettingOutcome {
    /// The value after the operation: as read back, else as asked for
    /// once written, else as before.
    pub fn after(&self) -> u32 {
        match (&self.result, self.read_back) {
            (_, Some(v)) => v,
            (SettingResult::Written | SettingResult::WouldWrite, None) => self.wanted,
            _ => self.before,
        }
    }

    /// True when the setting's value changes (or would, in a dry run).
    pub fn changed(&self) -> bool {
        self.after() != self.before
    }
}

/// What a document did to a drive.
#[derive(Debug, Clone, PartialEq)]
pub struct SettingsReport {
    /// The drive, by index in the plant.
    pub drive: usize,
    /// Each setting the document names, in document order.
    pub settings: Vec<SettingOutcome>,
    /// Nothing was written: only compared and checked.
    pub dry_run: bool,
    /// Saving to flash was asked for.
    pub save: bool,
    /// The write that failed, if one did (the later ones were not sent).
    pub failure: Option<Failure>,
    /// Why the read-back after the writes failed, if it did.
    pub read_back_error: Option<String>,
}

impl SettingsReport {
    /// True when every write the document needed was confirmed.
    pub fn complete(&self) -> bool {
        self.failure.is_none()
    }

    /// Settings whose value changed (or would).
    pub fn changed(&self) -> usize {
        self.settings.iter().filter(|s| s.changed()).count()
    }

    /// The operation in words, for the audit log: what changed, what
    /// failed.
    pub fn words(&self) -> String {
        let mut parts: Vec<String> = self
            .settings
            .iter()
            .filter(|s| s.changed() || !matches!(s.result, SettingResult::Unchanged))
            .map(|s| {
                let change = format!(
                    "{} {} -> {}",
                    s.setting.key(),
                    s.setting.words(s.before),
                    s.setting.words(s.wanted)
                );
                match &s.result {
                    SettingResult::Failed(why) => format!("{change} FAILED: {why}"),
                    SettingResult::NotSent(_) => format!("{change} not sent"),
                    _ => change,
                }
            })
            .collect();
        if parts.is_empty() {
            parts.push("nothing to change".to_string());
        }
        let mut text = parts.join(", ");
        if self.save {
            text.push_str("; saved to flash");
        }
        text
    }
}

/// Why a document was not applied at all.
#[derive(Debug, Clone, PartialEq)]
pub enum SettingsError {
    /// Values that cannot be taken (every one of them); nothing was sent.
    Invalid(Vec<RefusedValue>),
    /// Refused by a rule, or the drive could not be read: nothing was
    /// written.
    Failed(Failure),
}

/// A settings document put on a drive, for the stream and whoever listens.
#[derive(Debug, Clone, PartialEq)]
pub struct SettingsApplied {
    /// When it was settled.
    pub at: SystemTime,
    /// The face it came through.
    pub face: Face,
    /// Who sent it.
    pub who: Arc<str>,
    /// What it did.
    pub report: SettingsReport,
}

crate::listed::listed_enum! {
    /// The kind of a start-up decision: the metric's label, and what the
    /// stream and the audit log call it. Every kind has its series from
    /// start-up (`ALL`).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
    pub enum DecisionKind {
        /// A stop owed: the lease's holder ended with the old process.
        StopHolderGone,
        /// A stop owed: the lease ran out while the daemon was down.
        StopRanOut,
        /// A stop that was being retried, retried again.
        StopUnfinished,
        /// A brake sent but not confirmed, sent again.
        BrakeAgain,
        /// `on_unknown_state` on a moving drive: the journal was unreadable,
        /// or read in part and silent about the drive.
        StopUnknownState,
        /// `on_unknown_state` on a moving drive: the journal was lost
        /// (empty, only its header, or missing where an earlier run kept
        /// one).
        StopJournalLost,
        /// A drive found moving while the journal could not say who owned
        /// it, left moving: `on_unknown_state = "none"` (an alarm says so).
        UnknownStateLeft,
        /// An HTTP lease kept to its deadline.
        LeaseKept,
        /// No releasing stop: the drive's last confirmed command was a brake.
        BrakeHolds,
        /// The journal names a drive no longer configured.
        NotConfigured,
    }
}

impl DecisionKind {
    /// The label.
    pub fn name(self) -> &'static str {
        match self {
            DecisionKind::StopHolderGone => "stop-holder-gone",
            DecisionKind::StopRanOut => "stop-ran-out",
            DecisionKind::StopUnfinished => "stop-unfinished",
            DecisionKind::BrakeAgain => "brake-again",
            DecisionKind::StopUnknownState => "stop-unknown-state",
            DecisionKind::StopJournalLost => "stop-journal-lost",
            DecisionKind::UnknownStateLeft => "unknown-state-left",
            DecisionKind::LeaseKept => "lease-kept",
            DecisionKind::BrakeHolds => "brake-holds",
            DecisionKind::NotConfigured => "not-configured",
        }
    }
}

/// A start-up decision in words, for the audit log and the stream's
/// clients (who see what the daemon did to their drives when it started).
#[derive(Debug, Clone, PartialEq)]
pub struct RestartNote {
    /// The drive's name.
    pub drive: String,
    /// The decision's kind.
    pub decision: DecisionKind,
    /// Who held the lease concerned, if anyone.
    pub who: Option<String>,
    /// What was done and why, in words.
    pub text: String,
    /// When it was decided.
    pub at: SystemTime,
}

/// What a reload did, or why it did nothing.
pub type ReloadResult = Result<ReloadApplied, ReloadRefused>;

/// A reload that was applied.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReloadApplied {
    /// What changed, in words, one line each.
    pub changes: Vec<String>,
    /// What could not be done, in words: a bus whose port did not open
    /// (it stays out of the plant until the next reload), a listener that
    /// could not move (it stays where it was, with its previous settings,
    /// until the next reload). A reload with problems was applied in part.
    pub problems: Vec<String>,
    /// Every drive whose motion the reload changed, and why: drives that
    /// were moving when removed (or when their bus moved to another port)
    /// and what stopped them, and drives that report another motion after
    /// their bus reopened than before it.
    pub stopped: Vec<String>,
    /// Drives whose polling paused while their bus reopened, and for how
    /// long (their motion is unchanged unless `stopped` says otherwise).
    pub paused: Vec<String>,
}

/// A reload that left the running configuration as it was.
#[derive(Debug, Clone, PartialEq)]
pub enum ReloadRefused {
    /// The file does not pass the check: `file:line:column: why`.
    Invalid(String),
    /// The file changed on disk since the text to write was made from it.
    Changed(String),
    /// The daemon may not write its file (a read-only file system, a
    /// directory the service may not write): nothing changed.
    NotWritten(String),
    /// No reloader: started without a configuration file.
    Unavailable(String),
    /// The caller may not.
    Refused(Refusal),
}

impl std::fmt::Display for ReloadRefused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReloadRefused::Invalid(why)
            | ReloadRefused::Changed(why)
            | ReloadRefused::NotWritten(why)
            | ReloadRefused::Unavailable(why) => f.write_str(why),
            ReloadRefused::Refused(r) => f.write_str(&r.detail),
        }
    }
}
