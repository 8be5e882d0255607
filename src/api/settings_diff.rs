//! What a drive's settings were and are, as the API shows them: the diff
//! a settings document made (`PUT .../settings`, and the stream's
//! `settings-applied`), and how a drive stands to its declared settings
//! (a drive's `declared_settings`, and the stream's `settings-drift`).

use serde::Serialize;
use utoipa::ToSchema;

use crate::config::Declared;
use crate::control::Control;
use crate::control::drift::DriftView;
use crate::control::settings::{SettingOutcome, SettingsReport};
use crate::drive::wanted::{self, Difference};
use crate::faces_shared::target::Target;
use crate::timestamp::rfc3339;

/// A setting's value in engineering units: a number, or on/off.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, ToSchema)]
#[serde(untagged)]
pub enum SettingValue {
    /// A number in the setting's `unit`.
    Number(f64),
    /// On or off (`rs485_control`).
    Flag(bool),
}

impl From<wanted::Value> for SettingValue {
    fn from(v: wanted::Value) -> Self {
        match v {
            wanted::Value::Number(n) => SettingValue::Number(n),
            wanted::Value::Flag(f) => SettingValue::Flag(f),
        }
    }
}

/// One setting of a document: before, after, and what was done.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SettingChange {
    /// Its path in the document: `protection.limit_a`,
    /// `protection.stall_ms`, `speed_ramp.alpha`, `position_ramp.alpha`,
    /// `inertia_ratio` or `rs485_control`.
    pub setting: String,
    /// What it is, in words.
    pub quantity: String,
    /// Unit of `before` and `after` (`A`, `ms`, `x rotor`; empty for
    /// plain numbers and on/off).
    pub unit: String,
    /// What the drive held before, in engineering units.
    pub before: SettingValue,
    /// What it holds after (read back), or would hold after a dry run.
    pub after: SettingValue,
    /// `before`, raw (register value; alpha as 32 bits).
    pub raw_before: u32,
    /// `after`, raw.
    pub raw_after: u32,
    /// True when the value changes (or would).
    pub changed: bool,
    /// `unchanged` (held already, not written), `would-write` (dry run),
    /// `written` (confirmed by the drive), `failed` (its write failed:
    /// `detail` says whether it may have been carried out), `not-sent`
    /// (an earlier write failed).
    pub result: String,
    /// Why it failed or was not sent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

impl From<&SettingOutcome> for SettingChange {
    fn from(o: &SettingOutcome) -> Self {
        let after = o.after();
        SettingChange {
            setting: o.setting.key().to_string(),
            quantity: o.setting.quantity().to_string(),
            unit: o.setting.unit().to_string(),
            before: o.setting.value(o.before).into(),
            after: o.setting.value(after).into(),
            raw_before: o.before,
            raw_after: after,
            changed: o.changed(),
            result: o.result.name().to_string(),
            detail: o.result.detail().map(str::to_string),
        }
    }
}

/// What a settings document did to a drive (or would, in a dry run).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SettingsDiff {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// True for `?dry_run=true`: nothing was written.
    pub dry_run: bool,
    /// True when saving to flash was asked for.
    pub save: bool,
    /// True when every write the document needed was confirmed.
    pub complete: bool,
    /// Settings whose value changed (or would).
    pub changed: usize,
    /// Every setting the document names, in document order.
    pub settings: Vec<SettingChange>,
    /// Why reading the drive back after the writes failed, if it did
    /// (`after` is then the value written).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub read_back_error: Option<String>,
}

impl SettingsDiff {
    /// The diff of `report`, on drive `target`.
    pub fn new(target: &Target, report: &SettingsReport) -> Self {
        Self::of(
            target.drive.name.clone(),
            target.bus.name().to_string(),
            target.drive.unit,
            report,
        )
    }

    /// The diff of `report`, on drive `drive` at `unit` of `bus`.
    pub fn of(drive: String, bus: String, unit: u8, report: &SettingsReport) -> Self {
        SettingsDiff {
            drive,
            bus,
            unit,
            dry_run: report.dry_run,
            save: report.save,
            complete: report.complete(),
            changed: report.changed(),
            settings: report.settings.iter().map(SettingChange::from).collect(),
            read_back_error: report.read_back_error.clone(),
        }
    }
}

/// A declared setting the drive does not hold.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SettingDifference {
    /// Its path in the document (`speed_ramp.alpha`).
    pub setting: String,
    /// What it is, in words.
    pub quantity: String,
    /// Unit of the values.
    pub unit: String,
    /// What the drive holds, in engineering units.
    pub drive: SettingValue,
    /// What the configuration declares.
    pub declared: SettingValue,
    /// `drive`, raw.
    pub raw_drive: u32,
    /// `declared`, raw.
    pub raw_declared: u32,
}

impl From<&Difference> for SettingDifference {
    fn from(d: &Difference) -> Self {
        SettingDifference {
            setting: d.setting.key().to_string(),
            quantity: d.setting.quantity().to_string(),
            unit: d.setting.unit().to_string(),
            drive: d.setting.value(d.before).into(),
            declared: d.setting.value(d.after).into(),
            raw_drive: d.before,
            raw_declared: d.after,
        }
    }
}

/// A drive's declared settings and whether it holds them: the console's
/// drift badge.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct DeclaredState {
    /// `never` (report only) or `on-drift` (drivegate writes them).
    pub apply_settings: String,
    /// Whether drivegate's writes of them also save to flash.
    pub save: bool,
    /// `unchecked` (not compared yet: the drive has not come online),
    /// `match`, `drift`, `waiting-for-standstill` (`on-drift`: written
    /// once the motor stands still), `apply-failed` or `read-failed`.
    pub state: String,
    /// True when the drive is known not to hold them.
    pub drift: bool,
    /// The declared settings it does not hold.
    pub differences: Vec<SettingDifference>,
    /// When it was compared (RFC 3339, UTC).
    pub checked_at: Option<String>,
    /// Why, for `apply-failed` and `read-failed`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

impl DeclaredState {
    /// The state of a drive with `declared` settings, compared as `view`.
    pub fn new(declared: &Declared, view: Option<&DriftView>) -> Self {
        DeclaredState {
            apply_settings: declared.apply.name().to_string(),
            save: declared.save,
            state: view.map_or("unchecked", |v| v.state.name()).to_string(),
            drift: view.is_some_and(DriftView::drifted),
            differences: view
                .map(|v| v.drift.iter().map(SettingDifference::from).collect())
                .unwrap_or_default(),
            checked_at: view.map(|v| rfc3339(v.checked_at)),
            detail: view.and_then(|v| v.state.detail()).map(str::to_string),
        }
    }
}

/// The state of drive `target`'s declared settings, if it has any.
pub fn declared_state(control: &Control, target: &Target) -> Option<DeclaredState> {
    let declared = target.drive.declared.as_ref()?;
    let view = control.drift().view(&target.drive.name);
    Some(DeclaredState::new(declared, view.as_ref()))
}
