//! Settings as a document: `GET /api/v1/drives/{drive}/settings` (see
//! [`super::readback`]) is also what `PUT` takes, so a drive's settings
//! can be saved to a file (`?download=1`), put on another drive, or
//! compared with it (`?dry_run=true`). The core applies it whole or
//! refuses it whole ([`crate::control::settings`]); this module only
//! translates the document and renders the diff.
//!
//! Read-only fields of the document (`drive`, `bus`, `unit`,
//! `gear_ratio`, `read_at`) are ignored, so a file saved from one drive
//! can be put on another; so are `setpoints`, which are commands to the
//! motor, not settings.

use axum::Json;
use axum::extract::State;
use serde::de::IgnoredAny;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::auth::Caller;
use super::control;
use super::extract::{JsonBody, Params, PathParams};
use super::integers;
use super::openapi::WriteProblems;
use super::problem::{BusContext, InvalidSetting, Kind, Problem, ValidRange};
use super::state::{ApiState, Target};
use crate::config::Declared;
use crate::control::drift::DriftView;
use crate::control::settings::{ApplyOptions, SettingOutcome, SettingsError, SettingsReport};
use crate::drive::wanted::{self, Difference, Document, Setting, Wanted};
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
    fn new(target: &Target, report: &SettingsReport) -> Self {
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

/// Over-current protection in a document; give `limit_a` or
/// `limit_counts` (both: they must agree).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ProtectionDoc {
    /// Current limit, amps (0..15.99; what rounds to a count in 0..2047).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(minimum = -0.00390625, maximum = 15.99609375)]
    pub limit_a: Option<f64>,
    /// Current limit, counts (0..2047; 1 A = 128).
    #[serde(
        default,
        deserialize_with = "integers::optional",
        skip_serializing_if = "Option::is_none"
    )]
    #[schema(minimum = 0, maximum = 2047)]
    pub limit_counts: Option<i64>,
    /// Stall time, ms (0..60000).
    #[serde(
        default,
        deserialize_with = "integers::optional",
        skip_serializing_if = "Option::is_none"
    )]
    #[schema(minimum = 0, maximum = 60000)]
    pub stall_ms: Option<i64>,
}

/// A ramp in a document.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RampDoc {
    /// Alpha (0 = ramp off; 0..4294967295).
    #[serde(
        default,
        deserialize_with = "integers::optional",
        skip_serializing_if = "Option::is_none"
    )]
    #[schema(minimum = 0, maximum = 4294967295_i64)]
    pub alpha: Option<i64>,
}

/// `PUT .../settings`: the document `GET .../settings` returns (or a
/// part of it). Settings left out are neither compared nor written.
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SettingsDocument {
    /// Read-only: ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub drive: Option<IgnoredAny>,
    /// Read-only: ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub bus: Option<IgnoredAny>,
    /// Read-only: ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub unit: Option<IgnoredAny>,
    /// Read-only (configuration): ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub gear_ratio: Option<IgnoredAny>,
    /// Read-only: ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub read_at: Option<IgnoredAny>,
    /// Read-only (of a declaration, `GET .../settings/declared`): ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub apply_settings: Option<IgnoredAny>,
    /// The setpoint registers are commands, not settings: ignored.
    #[serde(default)]
    #[schema(value_type = Option<Value>)]
    pub setpoints: Option<IgnoredAny>,
    /// Over-current protection.
    #[serde(default, deserialize_with = "object")]
    pub protection: Option<ProtectionDoc>,
    /// Speed ramp.
    #[serde(default, deserialize_with = "object")]
    pub speed_ramp: Option<RampDoc>,
    /// Position ramp.
    #[serde(default, deserialize_with = "object")]
    pub position_ramp: Option<RampDoc>,
    /// Load inertia, times the rotor's (1..65535).
    #[serde(default, deserialize_with = "integers::optional")]
    #[schema(minimum = 1, maximum = 65535)]
    pub inertia_ratio: Option<i64>,
    /// True: RS-485 controls the motor; false: CAN.
    #[serde(default)]
    pub rs485_control: Option<bool>,
    /// Also write to flash: every message of 1.8 to 1.11 the document
    /// names is written with its save flag (flash cannot be read back),
    /// and only while the motor stands still.
    #[serde(default)]
    pub save: bool,
    /// Save even while the motor turns (audited).
    #[serde(default)]
    pub force: bool,
    /// Only compare and check, as `?dry_run=true` (the way to ask for it
    /// on the stream, whose `settings` op takes this body).
    #[serde(default)]
    pub dry_run: bool,
}

/// A part of a document that must be a JSON object (or null): serde would
/// read a struct from an array too, field by field.
fn object<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned,
{
    let Some(map) = Option::<serde_json::Map<String, serde_json::Value>>::deserialize(d)? else {
        return Ok(None);
    };
    serde_json::from_value(serde_json::Value::Object(map))
        .map(Some)
        .map_err(serde::de::Error::custom)
}

impl SettingsDocument {
    fn document(&self) -> Document {
        let p = self.protection.clone().unwrap_or_default();
        Document {
            limit_a: p.limit_a,
            limit_counts: p.limit_counts,
            stall_ms: p.stall_ms,
            speed_alpha: self.speed_ramp.as_ref().and_then(|r| r.alpha),
            position_alpha: self.position_ramp.as_ref().and_then(|r| r.alpha),
            inertia_ratio: self.inertia_ratio,
            rs485_control: self.rs485_control,
        }
    }
}

/// `?dry_run=`.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct ApplyQuery {
    /// Only compare and check (role, ranges, standstill for a save):
    /// the answer is the diff, nothing is written.
    #[serde(default)]
    pub dry_run: bool,
}

/// The problem of a document refused whole: every value named, with
/// its valid range.
fn invalid(refused: &[crate::drive::wanted::Refused]) -> Problem {
    let all_ranges = refused.iter().all(|r| r.range.is_some());
    let words: Vec<String> = refused
        .iter()
        .map(|r| format!("{}: {}", r.setting.key(), r.detail))
        .collect();
    let mut p = Problem::new(
        if all_ranges {
            Kind::OutOfRange
        } else {
            Kind::InvalidRequest
        },
        format!(
            "nothing was written: {} of the document {} refused: {}",
            plural(refused.len(), "value", "values"),
            if refused.len() == 1 { "is" } else { "are" },
            words.join("; ")
        ),
    );
    let range = |r: &crate::drive::wanted::Refused| {
        r.range.as_ref().map(|e| ValidRange {
            min: e.min,
            max: e.max,
            unit: e.unit.to_string(),
        })
    };
    p.valid_range = refused.first().and_then(range);
    p.invalid_settings = refused
        .iter()
        .map(|r| InvalidSetting {
            setting: r.setting.key().to_string(),
            detail: r.detail.clone(),
            valid_range: range(r),
        })
        .collect();
    p
}

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// Puts `body` on drive `key` (or, `dry_run`, shows what it would do).
pub async fn apply(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &SettingsDocument,
    dry_run: bool,
) -> Result<SettingsDiff, Problem> {
    let dry_run = dry_run || body.dry_run;
    let target = state.target(key)?;
    let offline = control::is_offline(&target);
    let options = ApplyOptions {
        save: body.save,
        force: body.force,
        dry_run,
        unattended: false,
    };
    let report = state
        .control
        .apply_settings(caller, target.control(), &body.document(), options)
        .await
        .map_err(|e| match e {
            SettingsError::Invalid(refused) => invalid(&refused).for_drive(&target.drive.name),
            SettingsError::Failed(failure) => control::problem(
                caller,
                &failure,
                BusContext {
                    drive: Some(&target.drive.name),
                    offline,
                    setpoint: false,
                },
            ),
        })?;
    let diff = SettingsDiff::new(&target, &report);
    if let Some(failure) = &report.failure {
        let mut p = control::problem(
            caller,
            failure,
            BusContext {
                drive: Some(&target.drive.name),
                offline,
                setpoint: false,
            },
        );
        p.detail = format!(
            "the settings document was applied only in part (settings_report says what became of each setting): {}",
            p.detail
        );
        p.settings_report = serde_json::to_value(&diff).ok();
        return Err(p);
    }
    Ok(diff)
}

/// Applies a settings document (the format of `GET .../settings`) to the
/// drive (admin); the answer is the diff.
///
/// The document is checked whole before anything is written: every value
/// against its range (all refusals in one problem, each with its range),
/// then the role and, with `"save": true`, that the motor stands still.
/// Only the messages whose settings change are written (with a save,
/// every message of 1.8 to 1.11 the document names), one at a time; the
/// drive is then read back. `?dry_run=true` only answers the diff.
/// A write that fails part-way ends it: the problem carries
/// `settings_report`, what became of each setting.
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/settings",
    tag = "settings",
    security(("bearer" = ["admin"])),
    params(
        ("drive" = String, Path, description = "Drive name, or its unit number on a single bus"),
        ApplyQuery,
    ),
    request_body(content = SettingsDocument, example = json!({
        "protection": {"limit_a": 12.0, "stall_ms": 3000},
        "speed_ramp": {"alpha": 5000},
        "position_ramp": {"alpha": 200},
        "inertia_ratio": 5,
        "rs485_control": true,
        "save": false
    })),
    responses(
        (status = 200, description = "What each setting was and is (or would be, in a dry run)", body = SettingsDiff),
        WriteProblems,
    )
)]
pub async fn put_settings(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    Params(query): Params<ApplyQuery>,
    JsonBody(body): JsonBody<SettingsDocument>,
) -> Result<Json<SettingsDiff>, Problem> {
    apply(&state, &caller, &key, &body, query.dry_run)
        .await
        .map(Json)
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
pub fn declared_state(state: &ApiState, target: &Target) -> Option<DeclaredState> {
    let declared = target.drive.declared.as_ref()?;
    let view = state.control.drift().view(&target.drive.name);
    Some(DeclaredState::new(declared, view.as_ref()))
}

/// A drive's declared settings as a document: `PUT .../settings` takes it
/// as it is (`save` then saves to flash, as drivegate's own writes of
/// them do). Whether the drive holds them is its `declared_settings`
/// (`GET /api/v1/drives/{drive}`).
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct DeclaredDocument {
    /// Drive name.
    pub drive: String,
    /// `never` or `on-drift`.
    pub apply_settings: String,
    /// Whether drivegate's own writes of them save to flash.
    pub save: bool,
    /// Over-current protection, if declared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub protection: Option<ProtectionDoc>,
    /// Speed ramp, if declared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_ramp: Option<RampDoc>,
    /// Position ramp, if declared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position_ramp: Option<RampDoc>,
    /// Load inertia ratio, if declared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub inertia_ratio: Option<i64>,
    /// RS-485 control, if declared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rs485_control: Option<bool>,
}

fn declared_document(name: &str, declared: &Declared) -> DeclaredDocument {
    let w: &Wanted = &declared.wanted;
    let int = |s: Setting| w.get(s).map(i64::from);
    let protection = (w.limit_counts.is_some() || w.stall_ms.is_some()).then(|| ProtectionDoc {
        limit_a: w
            .limit_counts
            .map(|c| f64::from(c) / crate::drive::units::COUNTS_PER_AMP),
        limit_counts: int(Setting::CurrentLimit),
        stall_ms: int(Setting::StallTime),
    });
    DeclaredDocument {
        drive: name.to_string(),
        apply_settings: declared.apply.name().to_string(),
        save: declared.save,
        protection,
        speed_ramp: w.speed_alpha.map(|a| RampDoc {
            alpha: Some(i64::from(a)),
        }),
        position_ramp: w.position_alpha.map(|a| RampDoc {
            alpha: Some(i64::from(a)),
        }),
        inertia_ratio: int(Setting::InertiaRatio),
        rs485_control: w.rs485_control,
    }
}

/// The drive's declared settings (`[bus.drive.settings]`) as a document
/// `PUT .../settings` takes as it is; 404 when none are declared.
#[utoipa::path(
    get,
    path = "/api/v1/drives/{drive}/settings/declared",
    tag = "settings",
    security(("bearer" = ["viewer"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    responses(
        (status = 200, description = "The declaration, in the keys PUT .../settings takes", body = DeclaredDocument),
        super::openapi::ReadProblems,
    )
)]
pub async fn get_declared(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(key): PathParams<String>,
) -> Result<Json<DeclaredDocument>, Problem> {
    let target = state.target(&key)?;
    let Some(declared) = target.drive.declared.as_ref() else {
        return Err(Problem::new(
            Kind::NotFound,
            format!(
                "drive \"{}\" has no declared settings: add a [bus.drive.settings] table to its section of the configuration",
                target.drive.name
            ),
        )
        .for_drive(&target.drive.name));
    };
    Ok(Json(declared_document(&target.drive.name, declared)))
}
