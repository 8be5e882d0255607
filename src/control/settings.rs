//! Settings documents: reading what a drive holds (sections 1.8 to 1.12),
//! and putting a whole document on it as one operation of the core, for
//! every face and for drivegate's own declared settings.
//!
//! A document is checked whole before anything is sent: every value
//! against the manual's ranges (all refusals together), then the rules of
//! every write it needs (role; with a save, or when drivegate applies it
//! on its own, standstill). Only then are the writes sent, one message at
//! a time through the one write path (each audited as any write); the
//! first that fails ends the operation, and what became of each setting
//! is reported, never left out. The drive is then read back, and one
//! audit line and one event tell the operation whole.

use std::sync::Arc;
use std::time::SystemTime;

use super::audit;
use super::caller::{Caller, Face};
use super::events::ControlEvent;
use super::outcome::Failure;
use super::policy::StillReason;
use super::request::ControlRequest;
use super::{Control, Target};
use crate::bus::handle::JobOptions;
use crate::bus::{BusError, Priority};
use crate::drive::settings::{self, BLOCKS, DriveSettings, REGISTERS};
use crate::drive::wanted::{self, Document, Refused, Setting, Wanted};

/// How a document is applied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ApplyOptions {
    /// Also write flash (every message of 1.8 to 1.11 the document names,
    /// with its save flag): the core's still-check applies.
    pub save: bool,
    /// The face's override of the still-check (HTTP `force`).
    pub force: bool,
    /// Only compare and check: nothing is written.
    pub dry_run: bool,
    /// drivegate applies it on its own: refused while the motor turns,
    /// whatever it writes.
    pub unattended: bool,
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
    Invalid(Vec<Refused>),
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

impl Control {
    /// Reads what the drive at `target` holds: its setpoints and settings
    /// (six reads at command priority, with the caller's turn on the bus).
    /// A read changes nothing, so it is not audited.
    pub async fn read_settings(
        &self,
        caller: &Caller,
        target: Target,
    ) -> Result<DriveSettings, BusError> {
        let bus = self.bus(target)?;
        let unit = target.unit;
        let options = JobOptions {
            priority: Priority::Command,
            source: caller.source,
            queue_timeout: None,
            max_attempts: None,
            origin: caller.origin.clone(),
        };
        let mut values = [0u16; REGISTERS];
        let mut at = 0;
        for (start, count) in BLOCKS {
            let exchange = bus
                .transact(unit, settings::read_pdu(start, count), options.clone())
                .await?;
            let block = settings::parse_read_reply(&exchange.reply, count)
                .map_err(|e| BusError::from_reply(unit, e))?;
            let Some(slot) = values.get_mut(at..at + block.len()) else {
                return Err(BusError::Unconfirmed {
                    unit,
                    detail: "a settings read returned more registers than asked",
                });
            };
            slot.copy_from_slice(&block);
            at += block.len();
        }
        Ok(DriveSettings::from_registers(&values))
    }

    /// Puts `document` on the drive at `target` for `caller`: checked whole
    /// (ranges, then every write's rules), then written message by message,
    /// then read back. With `dry_run`, only compared and checked.
    pub async fn apply_settings(
        &self,
        caller: &Caller,
        target: Target,
        document: &Document,
        options: ApplyOptions,
    ) -> Result<SettingsReport, SettingsError> {
        match document.check() {
            Ok(wanted) => self.apply_wanted(caller, target, &wanted, options).await,
            Err(r) => {
                let error = SettingsError::Invalid(r);
                if !options.dry_run {
                    let drive = self.name(target);
                    audit::settings_refused(caller.face.name(), &caller.who, &drive, &error);
                }
                Err(error)
            }
        }
    }

    /// [`apply_settings`](Self::apply_settings) of a document whose values
    /// were checked already (a declaration).
    pub(crate) async fn apply_wanted(
        &self,
        caller: &Caller,
        target: Target,
        wanted: &Wanted,
        options: ApplyOptions,
    ) -> Result<SettingsReport, SettingsError> {
        let drive_name = self.name(target);
        let refused = |error: SettingsError| {
            if !options.dry_run {
                audit::settings_refused(caller.face.name(), &caller.who, &drive_name, &error);
            }
            error
        };
        let wanted = *wanted;
        // The role before anything costs bus time.
        super::rules::role(caller, super::policy::for_settings())
            .map_err(|r| refused(SettingsError::Failed(Failure::Refused(r))))?;
        let held = self
            .read_settings(caller, target)
            .await
            .map_err(|e| refused(SettingsError::Failed(Failure::CheckFailed(e))))?;
        let steps = wanted::steps(&wanted, &held, options.save);
        let requests: Vec<ControlRequest> = steps
            .iter()
            .map(|step| {
                let request = ControlRequest::drive(step.request).forced(options.force);
                if options.unattended {
                    request.at_standstill(StillReason::Unattended)
                } else {
                    request
                }
            })
            .collect();
        self.check_all(caller, target, &requests)
            .await
            .map_err(|f| refused(SettingsError::Failed(f)))?;
        let mut outcomes = outcomes(&wanted, &held);
        if options.dry_run {
            for o in &mut outcomes {
                if steps.iter().any(|s| s.settings.contains(&o.setting)) {
                    o.result = SettingResult::WouldWrite;
                }
            }
        }
        let mut report = SettingsReport {
            drive: target.drive.unwrap_or(usize::MAX),
            settings: Vec::new(),
            dry_run: options.dry_run,
            save: options.save,
            failure: None,
            read_back_error: None,
        };
        if options.dry_run {
            report.settings = outcomes;
            return Ok(report);
        }
        for (step, request) in steps.iter().zip(requests) {
            let result = match &report.failure {
                Some(earlier) => SettingResult::NotSent(format!(
                    "not sent: an earlier write of the document failed ({earlier})"
                )),
                None => match self.write(caller, target, request).await {
                    Ok(_) => SettingResult::Written,
                    Err(failure) => {
                        let words = failure.to_string();
                        report.failure = Some(failure);
                        SettingResult::Failed(words)
                    }
                },
            };
            for o in outcomes
                .iter_mut()
                .filter(|o| step.settings.contains(&o.setting))
            {
                o.result = result.clone();
            }
        }
        let mut after = Some(held);
        if !steps.is_empty() {
            after = match self.read_settings(caller, target).await {
                Ok(after) => {
                    for o in &mut outcomes {
                        o.read_back = Some(o.setting.held(&after));
                    }
                    Some(after)
                }
                Err(e) => {
                    report.read_back_error = Some(e.to_string());
                    None
                }
            };
        }
        report.settings = outcomes;
        audit::settings_applied(caller.face.name(), &caller.who, &drive_name, &report);
        self.events().publish(
            Arc::new(ControlEvent::Settings(SettingsApplied {
                at: SystemTime::now(),
                face: caller.face,
                who: caller.who.clone(),
                report: report.clone(),
            })),
            None,
        );
        // Then, for a drive with a declaration, what it holds now.
        if let (Some(index), Some(after)) = (target.drive, after) {
            self.drift().after_apply(self, index, &after);
        }
        Ok(report)
    }
}

/// Each setting `wanted` names, before anything is written.
fn outcomes(wanted: &Wanted, held: &DriveSettings) -> Vec<SettingOutcome> {
    wanted::compare(wanted, held)
        .into_iter()
        .map(|d| SettingOutcome {
            setting: d.setting,
            before: d.before,
            wanted: d.after,
            read_back: None,
            result: SettingResult::Unchanged,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::BusError;

    fn outcome(
        setting: Setting,
        before: u32,
        wanted: u32,
        result: SettingResult,
    ) -> SettingOutcome {
        SettingOutcome {
            setting,
            before,
            wanted,
            read_back: None,
            result,
        }
    }

    #[test]
    fn a_report_says_what_changed_and_what_failed() {
        let timeout = BusError::Timeout {
            unit: 2,
            attempts: 2,
            timeout_ms: 250,
        };
        let report = SettingsReport {
            drive: 1,
            settings: vec![
                outcome(Setting::StallTime, 3000, 500, SettingResult::Written),
                outcome(
                    Setting::SpeedRamp,
                    500_000,
                    5000,
                    SettingResult::Failed("no answer".to_string()),
                ),
                outcome(
                    Setting::InertiaRatio,
                    1,
                    5,
                    SettingResult::NotSent("earlier".to_string()),
                ),
                outcome(Setting::Rs485Control, 1, 1, SettingResult::Unchanged),
            ],
            dry_run: false,
            save: false,
            failure: Some(Failure::Unknown {
                error: timeout,
                reply: None,
            }),
            read_back_error: None,
        };
        assert!(!report.complete());
        // Written: the value asked for; failed or not sent: as before.
        assert_eq!(report.changed(), 1);
        assert_eq!(
            report.words(),
            "protection.stall_ms 3000 ms -> 500 ms, speed_ramp.alpha 500000 -> 5000 FAILED: no answer, inertia_ratio 1 x rotor -> 5 x rotor not sent"
        );
        // A read-back decides the value after.
        let mut read = outcome(Setting::InertiaRatio, 1, 5, SettingResult::Written);
        read.read_back = Some(4);
        assert_eq!((read.after(), read.changed()), (4, true));
        let dry = outcome(Setting::InertiaRatio, 1, 5, SettingResult::WouldWrite);
        assert_eq!(dry.after(), 5);
        let nothing = SettingsReport {
            settings: vec![outcome(
                Setting::InertiaRatio,
                1,
                1,
                SettingResult::Unchanged,
            )],
            failure: None,
            save: true,
            ..report
        };
        assert_eq!(nothing.words(), "nothing to change; saved to flash");
    }
}
