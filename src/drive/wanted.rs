//! What a drive's settings should be, and how that differs from what it
//! holds: the document of `PUT /api/v1/drives/{drive}/settings` and of a
//! drive's declared settings (`[bus.drive.settings]`), checked against the
//! manual's ranges, compared with a read-back, and turned into the
//! messages of sections 1.8 to 1.12 that make the drive hold it. Pure.
//!
//! Every setting is optional: one a document leaves out is neither
//! compared nor written.

use super::message::DriveRequest;
use super::range::RangeError;
use super::settings::DriveSettings;
use super::units::{self, COUNTS_PER_AMP};
use crate::listed::listed_enum;

listed_enum! {
    /// One writable setting of the drive (manual 1.8 to 1.12).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
    pub enum Setting {
        /// STALLED_CURR: the over-current limit (1.8).
        CurrentLimit,
        /// STALLED_DURATION_MS: how long the current may exceed it (1.8).
        StallTime,
        /// The speed ramp's alpha (1.9).
        SpeedRamp,
        /// The position ramp's alpha (1.10).
        PositionRamp,
        /// INERTIA_RATIO (1.11).
        InertiaRatio,
        /// USE_485_CONTROL (1.12).
        Rs485Control,
    }
}

impl Setting {
    /// Its path in the settings document (`protection.limit_a`).
    pub fn key(self) -> &'static str {
        match self {
            Setting::CurrentLimit => "protection.limit_a",
            Setting::StallTime => "protection.stall_ms",
            Setting::SpeedRamp => "speed_ramp.alpha",
            Setting::PositionRamp => "position_ramp.alpha",
            Setting::InertiaRatio => "inertia_ratio",
            Setting::Rs485Control => "rs485_control",
        }
    }

    /// What it is, in words.
    pub fn quantity(self) -> &'static str {
        match self {
            Setting::CurrentLimit => "over-current limit",
            Setting::StallTime => "stall time",
            Setting::SpeedRamp => "speed ramp alpha",
            Setting::PositionRamp => "position ramp alpha",
            Setting::InertiaRatio => "load inertia ratio",
            Setting::Rs485Control => "RS-485 control",
        }
    }

    /// The engineering unit of [`value`](Self::value) (may be empty).
    pub fn unit(self) -> &'static str {
        match self {
            Setting::CurrentLimit => "A",
            Setting::StallTime => "ms",
            Setting::InertiaRatio => "x rotor",
            Setting::SpeedRamp | Setting::PositionRamp | Setting::Rs485Control => "",
        }
    }

    /// A raw value in engineering units.
    pub fn value(self, raw: u32) -> Value {
        match self {
            Setting::CurrentLimit => Value::Number(f64::from(raw) / COUNTS_PER_AMP),
            Setting::Rs485Control => Value::Flag(raw != 0),
            _ => Value::Number(f64::from(raw)),
        }
    }

    /// What the drive holds for this setting, raw.
    pub fn held(self, s: &DriveSettings) -> u32 {
        match self {
            Setting::CurrentLimit => u32::from(s.limit_counts),
            Setting::StallTime => u32::from(s.stall_ms),
            Setting::SpeedRamp => s.speed_alpha,
            Setting::PositionRamp => s.position_alpha,
            Setting::InertiaRatio => u32::from(s.inertia_ratio),
            Setting::Rs485Control => u32::from(s.rs485_control),
        }
    }

    /// The value in words, with its unit ("12 A", "on").
    pub fn words(self, raw: u32) -> String {
        match self.value(raw) {
            Value::Flag(true) => "on".to_string(),
            Value::Flag(false) => "off (CAN controls)".to_string(),
            Value::Number(v) if self.unit().is_empty() => format!("{v}"),
            Value::Number(v) => format!("{v} {}", self.unit()),
        }
    }
}

/// A setting's value in engineering units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Value {
    /// A number in the setting's unit.
    Number(f64),
    /// On or off.
    Flag(bool),
}

/// A settings document as a client or the configuration gives it, in
/// engineering units, before its ranges are checked.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Document {
    /// Over-current limit, amps.
    pub limit_a: Option<f64>,
    /// Over-current limit, counts (1 A = 128); if given with `limit_a`,
    /// both must say the same.
    pub limit_counts: Option<i64>,
    /// Stall time, ms.
    pub stall_ms: Option<i64>,
    /// Speed ramp alpha.
    pub speed_alpha: Option<i64>,
    /// Position ramp alpha.
    pub position_alpha: Option<i64>,
    /// Load inertia ratio.
    pub inertia_ratio: Option<i64>,
    /// RS-485 control.
    pub rs485_control: Option<bool>,
}

/// A value of a document that cannot be taken.
#[derive(Debug, Clone, PartialEq)]
pub struct Refused {
    /// The setting.
    pub setting: Setting,
    /// Out of range: the range.
    pub range: Option<RangeError>,
    /// What is wrong, in words.
    pub detail: String,
}

/// The settings asked for, in the drive's units, each within its range.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Wanted {
    /// STALLED_CURR, counts.
    pub limit_counts: Option<u16>,
    /// STALLED_DURATION_MS.
    pub stall_ms: Option<u16>,
    /// Speed ramp alpha.
    pub speed_alpha: Option<u32>,
    /// Position ramp alpha.
    pub position_alpha: Option<u32>,
    /// INERTIA_RATIO.
    pub inertia_ratio: Option<u16>,
    /// USE_485_CONTROL.
    pub rs485_control: Option<bool>,
}

impl Document {
    /// The document in the drive's units, or every value that cannot be
    /// taken (all of them, not only the first).
    pub fn check(&self) -> Result<Wanted, Vec<Refused>> {
        let mut refused = Vec::new();
        let mut range = |setting: Setting, r: Result<u32, RangeError>| match r {
            Ok(v) => Some(v),
            Err(e) => {
                refused.push(Refused {
                    setting,
                    detail: e.to_string(),
                    range: Some(e),
                });
                None
            }
        };
        let by_amps = self.limit_a.map(|a| units::current_limit(a).map(u32::from));
        let by_counts = self
            .limit_counts
            .map(|c| units::current_limit_counts(c).map(u32::from));
        let limit_a = by_amps.and_then(|r| range(Setting::CurrentLimit, r));
        let limit_c = by_counts.and_then(|r| range(Setting::CurrentLimit, r));
        let stall = self
            .stall_ms
            .and_then(|v| range(Setting::StallTime, units::stall_time_ms(v).map(u32::from)));
        let speed = self
            .speed_alpha
            .and_then(|v| range(Setting::SpeedRamp, alpha("speed ramp alpha", v)));
        let position = self
            .position_alpha
            .and_then(|v| range(Setting::PositionRamp, alpha("position ramp alpha", v)));
        let inertia = self.inertia_ratio.and_then(|v| {
            range(
                Setting::InertiaRatio,
                units::inertia_ratio(v).map(u32::from),
            )
        });
        if let (Some(a), Some(c)) = (limit_a, limit_c)
            && a != c
        {
            refused.push(Refused {
                setting: Setting::CurrentLimit,
                range: None,
                detail: format!(
                    "protection.limit_a ({} A = {a} counts) and protection.limit_counts ({c}) disagree: give one, or both for the same limit",
                    f64::from(a) / COUNTS_PER_AMP
                ),
            });
        }
        if !refused.is_empty() {
            return Err(refused);
        }
        let narrow16 = |v: Option<u32>| v.and_then(|v| u16::try_from(v).ok());
        Ok(Wanted {
            limit_counts: narrow16(limit_c.or(limit_a)),
            stall_ms: narrow16(stall),
            speed_alpha: speed,
            position_alpha: position,
            inertia_ratio: narrow16(inertia),
            rs485_control: self.rs485_control,
        })
    }
}

fn alpha(quantity: &'static str, v: i64) -> Result<u32, RangeError> {
    let v = RangeError::check_int(quantity, v, 0, i64::from(u32::MAX), "")?;
    Ok(u32::try_from(v).unwrap_or(u32::MAX))
}

impl Wanted {
    /// Every setting a drive holding `s` has.
    pub fn of(s: &DriveSettings) -> Wanted {
        Wanted {
            limit_counts: Some(s.limit_counts),
            stall_ms: Some(s.stall_ms),
            speed_alpha: Some(s.speed_alpha),
            position_alpha: Some(s.position_alpha),
            inertia_ratio: Some(s.inertia_ratio),
            rs485_control: Some(s.rs485_control),
        }
    }

    /// The raw value asked for `setting`, if it is asked for.
    pub fn get(&self, setting: Setting) -> Option<u32> {
        match setting {
            Setting::CurrentLimit => self.limit_counts.map(u32::from),
            Setting::StallTime => self.stall_ms.map(u32::from),
            Setting::SpeedRamp => self.speed_alpha,
            Setting::PositionRamp => self.position_alpha,
            Setting::InertiaRatio => self.inertia_ratio.map(u32::from),
            Setting::Rs485Control => self.rs485_control.map(u32::from),
        }
    }

    /// True when it names no setting.
    pub fn is_empty(&self) -> bool {
        Setting::ALL.iter().all(|&s| self.get(s).is_none())
    }

    /// The settings it names, in document order.
    pub fn settings(&self) -> impl Iterator<Item = Setting> + '_ {
        Setting::ALL.into_iter().filter(|&s| self.get(s).is_some())
    }
}

/// One setting a document names, with what the drive held and what the
/// document asks for (raw).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Difference {
    /// The setting.
    pub setting: Setting,
    /// What the drive holds.
    pub before: u32,
    /// What the document asks for.
    pub after: u32,
}

impl Difference {
    /// True when the drive holds something else.
    pub fn changed(&self) -> bool {
        self.before != self.after
    }

    /// "speed ramp alpha 500000 -> 1000".
    pub fn words(&self) -> String {
        format!(
            "{} {} -> {}",
            self.setting.key(),
            self.setting.words(self.before),
            self.setting.words(self.after)
        )
    }
}

/// Every setting `wanted` names, beside what a drive holding `held` has.
pub fn compare(wanted: &Wanted, held: &DriveSettings) -> Vec<Difference> {
    wanted
        .settings()
        .filter_map(|setting| {
            Some(Difference {
                setting,
                before: setting.held(held),
                after: wanted.get(setting)?,
            })
        })
        .collect()
}

/// The settings `wanted` names that a drive holding `held` does not hold:
/// its drift from the document (empty: none).
pub fn drift(wanted: &Wanted, held: &DriveSettings) -> Vec<Difference> {
    compare(wanted, held)
        .into_iter()
        .filter(Difference::changed)
        .collect()
}

/// One message that puts part of a document on the drive, and the
/// settings it carries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Step {
    /// The message.
    pub request: DriveRequest,
    /// The settings of the document it writes.
    pub settings: Vec<Setting>,
}

/// The messages that make a drive holding `held` hold `wanted`, in the
/// manual's order: one per message whose settings change; with `save`,
/// every message of 1.8 to 1.11 the document names, with its save flag,
/// since flash cannot be read back to tell whether it already holds them.
/// A message that carries two settings (1.8) keeps the drive's value of
/// the one the document leaves out.
pub fn steps(wanted: &Wanted, held: &DriveSettings, save: bool) -> Vec<Step> {
    let differs = |s: Setting| wanted.get(s).is_some_and(|v| v != s.held(held));
    let named = |s: Setting| wanted.get(s).is_some();
    let due = |group: &[Setting], saves: bool| {
        group.iter().any(|&s| differs(s)) || (saves && save && group.iter().any(|&s| named(s)))
    };
    let mut out = Vec::new();
    let mut push = |request, group: &[Setting]| {
        out.push(Step {
            request,
            settings: group.iter().copied().filter(|&s| named(s)).collect(),
        });
    };
    let protection = [Setting::CurrentLimit, Setting::StallTime];
    if due(&protection, true) {
        push(
            DriveRequest::OverCurrent {
                limit_counts: wanted.limit_counts.unwrap_or(held.limit_counts),
                stall_ms: wanted.stall_ms.unwrap_or(held.stall_ms),
                save,
            },
            &protection,
        );
    }
    if let Some(alpha) = wanted.speed_alpha
        && due(&[Setting::SpeedRamp], true)
    {
        push(
            DriveRequest::SpeedRamp { alpha, save },
            &[Setting::SpeedRamp],
        );
    }
    if let Some(alpha) = wanted.position_alpha
        && due(&[Setting::PositionRamp], true)
    {
        push(
            DriveRequest::PositionRamp { alpha, save },
            &[Setting::PositionRamp],
        );
    }
    if let Some(ratio) = wanted.inertia_ratio
        && due(&[Setting::InertiaRatio], true)
    {
        push(
            DriveRequest::LoadInertia { ratio, save },
            &[Setting::InertiaRatio],
        );
    }
    // 1.12 has no save flag: written only when it changes.
    if let Some(enabled) = wanted.rs485_control
        && due(&[Setting::Rs485Control], false)
    {
        push(
            DriveRequest::Rs485Control { enabled },
            &[Setting::Rs485Control],
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A drive at its factory settings (the simulator's, the manual's
    /// power-on ramps).
    fn factory() -> DriveSettings {
        DriveSettings {
            speed_rpm: 0,
            position_centideg: 0,
            torque_counts: 0,
            limit_counts: 1536,
            stall_ms: 3000,
            speed_alpha: 500_000,
            position_alpha: 500_000,
            inertia_ratio: 1,
            rs485_control: true,
        }
    }

    #[test]
    fn a_document_is_checked_whole_and_every_refusal_named() {
        let doc = Document {
            limit_a: Some(20.0),
            stall_ms: Some(70_000),
            inertia_ratio: Some(5),
            speed_alpha: Some(-1),
            ..Document::default()
        };
        let refused = doc.check().unwrap_err();
        let names: Vec<_> = refused.iter().map(|r| r.setting).collect();
        assert_eq!(
            names,
            [
                Setting::CurrentLimit,
                Setting::StallTime,
                Setting::SpeedRamp
            ]
        );
        assert_eq!(
            refused[1].detail,
            "stall time 70000 ms is out of range: valid 0 to 60000 ms"
        );
        let range = refused[0].range.clone().unwrap();
        assert_eq!(
            (range.min, range.max, range.unit),
            (0.0, 2047.0 / 128.0, "A")
        );
        // Both forms of the limit must agree.
        let both = Document {
            limit_a: Some(12.0),
            limit_counts: Some(1536),
            ..Document::default()
        };
        assert_eq!(both.check().unwrap().limit_counts, Some(1536));
        let contradiction = Document {
            limit_a: Some(10.0),
            limit_counts: Some(1536),
            ..Document::default()
        };
        let r = contradiction.check().unwrap_err();
        assert!(
            r[0].range.is_none() && r[0].detail.contains("disagree"),
            "{r:?}"
        );
    }

    #[test]
    fn a_document_is_compared_only_where_it_speaks() {
        let wanted = Document {
            limit_a: Some(12.0),
            inertia_ratio: Some(5),
            rs485_control: Some(true),
            ..Document::default()
        }
        .check()
        .unwrap();
        let all = compare(&wanted, &factory());
        assert_eq!(
            all.iter().map(|d| d.setting).collect::<Vec<_>>(),
            [
                Setting::CurrentLimit,
                Setting::InertiaRatio,
                Setting::Rs485Control
            ]
        );
        assert_eq!(
            drift(&wanted, &factory()),
            [Difference {
                setting: Setting::InertiaRatio,
                before: 1,
                after: 5
            }]
        );
        assert_eq!(
            drift(&wanted, &factory())[0].words(),
            "inertia_ratio 1 x rotor -> 5 x rotor"
        );
        // A drive read whole matches its own document.
        assert!(drift(&Wanted::of(&factory()), &factory()).is_empty());
        assert!(Wanted::default().is_empty());
    }

    #[test]
    fn only_changed_messages_are_written_unless_saving() {
        let mut wanted = Wanted::of(&factory());
        wanted.stall_ms = Some(500);
        wanted.position_alpha = Some(200);
        let steps_ = steps(&wanted, &factory(), false);
        assert_eq!(
            steps_.iter().map(|s| s.request).collect::<Vec<_>>(),
            [
                DriveRequest::OverCurrent {
                    limit_counts: 1536,
                    stall_ms: 500,
                    save: false
                },
                DriveRequest::PositionRamp {
                    alpha: 200,
                    save: false
                },
            ]
        );
        assert_eq!(
            steps_[0].settings,
            [Setting::CurrentLimit, Setting::StallTime]
        );
        // Saving writes every message with a save flag the document names;
        // RS-485 control has none and is unchanged.
        let saved = steps(&wanted, &factory(), true);
        assert_eq!(saved.len(), 4);
        assert!(saved.iter().all(|s| s.request.saves_to_flash()));
        // Nothing to change, nothing to save: nothing at all.
        assert!(steps(&Wanted::of(&factory()), &factory(), false).is_empty());
        // 1.8 carries both values: the one left out keeps the drive's.
        let only_stall = Wanted {
            stall_ms: Some(100),
            ..Wanted::default()
        };
        assert_eq!(
            steps(&only_stall, &factory(), false)[0].request,
            DriveRequest::OverCurrent {
                limit_counts: 1536,
                stall_ms: 100,
                save: false
            }
        );
        assert_eq!(
            steps(&only_stall, &factory(), false)[0].settings,
            [Setting::StallTime]
        );
    }

    #[test]
    fn values_read_in_engineering_units() {
        assert_eq!(Setting::CurrentLimit.value(1536), Value::Number(12.0));
        assert_eq!(Setting::Rs485Control.value(0), Value::Flag(false));
        assert_eq!(Setting::StallTime.words(3000), "3000 ms");
        assert_eq!(Setting::SpeedRamp.words(500_000), "500000");
        let keys: std::collections::BTreeSet<_> = Setting::ALL.iter().map(|s| s.key()).collect();
        assert_eq!(keys.len(), Setting::ALL.len());
    }
}
