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
use super::caller::Caller;
use super::events::ControlEvent;
pub use super::news::{
    SettingOutcome, SettingResult, SettingsApplied, SettingsError, SettingsReport,
};
use super::outcome::Failure;
use super::parts::Parts;
use super::policy::StillReason;
use super::request::ControlRequest;
use super::request::Target;
use crate::bus::handle::JobOptions;
use crate::bus::{BusError, Priority};
use crate::drive::settings::{self, BLOCKS, DriveSettings, REGISTERS};
use crate::drive::wanted::{self, Document, Step, Wanted};

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

/// Reads what the drive at `target` holds: its setpoints and settings
/// (six reads at command priority, with the caller's turn on the bus).
/// A read changes nothing, so it is not audited.
pub(super) async fn read_settings(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
) -> Result<DriveSettings, BusError> {
    let bus = parts.bus(target)?;
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
pub(super) async fn apply_settings(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    document: &Document,
    options: ApplyOptions,
) -> Result<Done, SettingsError> {
    match document.check() {
        Ok(wanted) => apply_wanted(parts, caller, target, &wanted, options).await,
        Err(r) => {
            let error = SettingsError::Invalid(r);
            if !options.dry_run {
                let drive = parts.name(target);
                audit::settings_refused(caller.face.name(), &caller.who, &drive, &error);
            }
            Err(error)
        }
    }
}

/// A document put on a drive: what it did, and what the drive holds after
/// it (read back; none for a dry run or a failed read-back), for the
/// comparison with its declared settings that follows.
pub(super) struct Done {
    pub(super) report: SettingsReport,
    pub(super) held: Option<DriveSettings>,
}

/// [`apply_settings`] of a document whose values
/// were checked already (a declaration).
pub(super) async fn apply_wanted(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    wanted: &Wanted,
    options: ApplyOptions,
) -> Result<Done, SettingsError> {
    let drive_name = parts.name(target);
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
    let held = read_settings(parts, caller, target)
        .await
        .map_err(|e| refused(SettingsError::Failed(Failure::CheckFailed(e))))?;
    let steps = wanted::steps(&wanted, &held, options.save);
    let requests = requests(&steps, options);
    super::write::check_all(parts, caller, target, &requests)
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
        return Ok(Done { report, held: None });
    }
    report.failure = write_steps(parts, caller, target, &steps, requests, &mut outcomes).await;
    let mut after = Some(held);
    if !steps.is_empty() {
        after = match read_settings(parts, caller, target).await {
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
    parts.events().publish(
        Arc::new(ControlEvent::Settings(SettingsApplied {
            at: SystemTime::now(),
            face: caller.face,
            who: caller.who.clone(),
            report: report.clone(),
        })),
        None,
    );
    Ok(Done {
        report,
        held: after,
    })
}

/// The writes of `steps`, as `options` asks them to be checked.
fn requests(steps: &[Step], options: ApplyOptions) -> Vec<ControlRequest> {
    steps
        .iter()
        .map(|step| {
            let request = ControlRequest::drive(step.request).forced(options.force);
            if options.unattended {
                request.at_standstill(StillReason::Unattended)
            } else {
                request
            }
        })
        .collect()
}

/// Sends the writes of `steps`, one message at a time, until one fails:
/// what became of each setting goes into `outcomes`; the failure, if one
/// did, is returned (the later writes were not sent).
async fn write_steps(
    parts: &Arc<Parts>,
    caller: &Caller,
    target: Target,
    steps: &[Step],
    requests: Vec<ControlRequest>,
    outcomes: &mut [SettingOutcome],
) -> Option<Failure> {
    let mut failed: Option<Failure> = None;
    for (step, request) in steps.iter().zip(requests) {
        let result = match &failed {
            Some(earlier) => SettingResult::NotSent(format!(
                "not sent: an earlier write of the document failed ({earlier})"
            )),
            None => match super::write::write(parts, caller, target, request).await {
                Ok(_) => SettingResult::Written,
                Err(failure) => {
                    let words = failure.to_string();
                    failed = Some(failure);
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
    failed
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
    use crate::drive::wanted::Setting;

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
