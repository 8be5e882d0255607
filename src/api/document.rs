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

use super::extract::{JsonBody, Params, PathParams};
use super::problem_response::WriteProblems;
use super::problem_response::{BusContext, InvalidSetting, Kind, Problem, ValidRange};
use super::settings_diff::SettingsDiff;
use super::state::ApiState;
use crate::config::Declared;
use crate::control::Caller;
use crate::control::settings::{ApplyOptions, SettingsError};
use crate::drive::wanted::{Document, Setting, Wanted};
use crate::faces_shared::integers;
use crate::faces_shared::writes;

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
    let offline = writes::is_offline(&target);
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
            SettingsError::Failed(failure) => writes::problem(
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
        let mut p = writes::problem(
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
        super::problem_response::ReadProblems,
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
