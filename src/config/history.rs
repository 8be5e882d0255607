//! `[history]`: how long each drive's status is kept for the trends, and
//! how much of it at full rate.

use serde::Deserialize;

use super::values;
use crate::history::HistorySettings;

/// `[history]` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HistoryConfig {
    /// Minutes of each drive's status kept, in one-second buckets (min,
    /// max and mean of each field): 48 bytes a second.
    #[serde(deserialize_with = "values::int_in::<_, _, 1, 1440>")]
    pub minutes: u64,
    /// The most recent seconds kept at full rate, each status as polled
    /// (room for 100 a second, 24 bytes each).
    #[serde(deserialize_with = "values::int_in::<_, _, 1, 600>")]
    pub full_rate_s: u64,
}

impl Default for HistoryConfig {
    fn default() -> Self {
        Self {
            minutes: 60,
            full_rate_s: 60,
        }
    }
}

impl HistoryConfig {
    /// The history's settings.
    pub fn settings(&self) -> HistorySettings {
        HistorySettings {
            minutes: self.minutes,
            full_rate_s: self.full_rate_s,
        }
    }
}
