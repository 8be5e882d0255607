//! `[bus.drive.settings]`: the settings a drive must hold for the line it
//! runs, in the keys of the settings document (`GET
//! /api/v1/drives/{drive}/settings`), and what drivegate does when the
//! drive comes online holding something else.

use serde::Deserialize;

use crate::drive::wanted::{Document, Wanted};

/// What drivegate does about a drive that holds other settings than its
/// declaration when it comes online.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ApplySettings {
    /// Report the drift (stream event, metric, the drive's status, the
    /// audit log); change nothing.
    #[default]
    Never,
    /// Report it, then write the declared settings through the control
    /// core, once the motor stands still.
    OnDrift,
}

impl ApplySettings {
    /// The configuration's spelling.
    pub fn name(self) -> &'static str {
        match self {
            ApplySettings::Never => "never",
            ApplySettings::OnDrift => "on-drift",
        }
    }
}

/// `[bus.drive.settings.protection]`.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProtectionKeys {
    /// Over-current limit, amps (0 to 15.99).
    pub limit_a: Option<f64>,
    /// Over-current limit, counts (0 to 2047; 1 A = 128).
    pub limit_counts: Option<i64>,
    /// Stall time, ms (0 to 60000).
    pub stall_ms: Option<i64>,
}

/// `[bus.drive.settings.speed_ramp]` and `.position_ramp`.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RampKeys {
    /// Ramp alpha (0 = off; 0 to 4294967295).
    pub alpha: Option<i64>,
}

/// `[bus.drive.settings]` as written.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeclaredKeys {
    /// What to do on drift (default `never`: report only).
    #[serde(default)]
    pub apply_settings: ApplySettings,
    /// With `on-drift`: also write the settings to flash (default false).
    #[serde(default)]
    pub save: bool,
    /// Over-current protection.
    pub protection: Option<ProtectionKeys>,
    /// Speed ramp.
    pub speed_ramp: Option<RampKeys>,
    /// Position ramp.
    pub position_ramp: Option<RampKeys>,
    /// Load inertia, times the rotor's (1 to 65535).
    pub inertia_ratio: Option<i64>,
    /// True: RS-485 controls the motor; false: CAN.
    pub rs485_control: Option<bool>,
}

/// A drive's declared settings, checked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Declared {
    /// The settings, in the drive's units.
    pub wanted: Wanted,
    /// What to do on drift.
    pub apply: ApplySettings,
    /// Whether applying them also writes flash.
    pub save: bool,
}

impl DeclaredKeys {
    /// The document these keys make.
    pub fn document(&self) -> Document {
        let protection = self.protection.clone().unwrap_or_default();
        Document {
            limit_a: protection.limit_a,
            limit_counts: protection.limit_counts,
            stall_ms: protection.stall_ms,
            speed_alpha: self.speed_ramp.as_ref().and_then(|r| r.alpha),
            position_alpha: self.position_ramp.as_ref().and_then(|r| r.alpha),
            inertia_ratio: self.inertia_ratio,
            rs485_control: self.rs485_control,
        }
    }

    /// Checked against the manual's ranges: the declaration, or every
    /// refusal in words.
    pub fn declared(&self) -> Result<Declared, String> {
        let wanted = self.document().check().map_err(|refused| {
            refused
                .iter()
                .map(|r| format!("{}: {}", r.setting.key(), r.detail))
                .collect::<Vec<_>>()
                .join("; ")
        })?;
        if wanted.is_empty() {
            return Err(
                "[bus.drive.settings] declares no setting: give protection, speed_ramp, position_ramp, inertia_ratio or rs485_control, or remove the table".to_string(),
            );
        }
        Ok(Declared {
            wanted,
            apply: self.apply_settings,
            save: self.save,
        })
    }
}
