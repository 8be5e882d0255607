//! `[monitor]` and `[scope]`: the bus monitor's ring and the scope's limits,
//! the same for every bus.

use std::time::Duration;

use serde::{Deserialize, Deserializer, de::Error};

use super::values;
use crate::monitor::MonitorSettings;
use crate::monitor::record::FrameRecord;
use crate::scope::ScopeSettings;
use crate::scope::capture::Sample;

/// `[monitor]`: every frame on the wire, kept in a ring per bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorConfig {
    /// Keep the frames (the per-attempt counters of `/metrics` run anyway).
    #[serde(default = "default_enabled")]
    pub enabled: bool,
    /// Frames kept per bus (each takes about 160 bytes, and 256 more in a
    /// slot that once held a frame longer than 32).
    #[serde(
        default = "default_ring_frames",
        deserialize_with = "values::int_in::<_, _, 16, 1000000>"
    )]
    pub ring_frames: usize,
}

impl Default for MonitorConfig {
    fn default() -> Self {
        Self {
            enabled: default_enabled(),
            ring_frames: default_ring_frames(),
        }
    }
}

impl MonitorConfig {
    /// The monitor settings of each bus.
    pub fn settings(&self) -> MonitorSettings {
        MonitorSettings {
            enabled: self.enabled,
            ring_frames: self.ring_frames,
        }
    }

    /// Memory the ring of one bus takes, bytes.
    pub fn memory_per_bus(&self) -> usize {
        if self.enabled {
            self.ring_frames * std::mem::size_of::<std::sync::Mutex<FrameRecord>>()
        } else {
            0
        }
    }
}

/// `[scope]`: one capture per bus at a time, bounded.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScopeConfig {
    /// Samples one capture may hold (each takes 32 bytes).
    #[serde(
        default = "default_max_samples",
        deserialize_with = "values::int_in::<_, _, 1000, 10000000>"
    )]
    pub max_samples: usize,
    /// Status reads per second that each drive not captured keeps while a
    /// capture runs, 0.1 to 100.
    #[serde(default = "default_floor", deserialize_with = "floor_rate")]
    pub floor_rate_hz: f64,
    /// Longest wait for a trigger, s.
    #[serde(
        default = "default_max_wait",
        deserialize_with = "values::int_in::<_, _, 1, 86400>"
    )]
    pub max_wait_s: u64,
}

impl Default for ScopeConfig {
    fn default() -> Self {
        Self {
            max_samples: default_max_samples(),
            floor_rate_hz: default_floor(),
            max_wait_s: default_max_wait(),
        }
    }
}

impl ScopeConfig {
    /// The scope settings of each bus.
    pub fn settings(&self) -> ScopeSettings {
        ScopeSettings {
            max_samples: self.max_samples,
            floor_rate_hz: self.floor_rate_hz,
            max_wait: Duration::from_secs(self.max_wait_s),
        }
    }

    /// Memory the largest capture takes, bytes.
    pub fn memory_per_capture(&self) -> usize {
        self.max_samples * std::mem::size_of::<Sample>()
    }
}

fn floor_rate<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    let v = f64::deserialize(d)?;
    if !(v.is_finite() && (0.1..=100.0).contains(&v)) {
        return Err(D::Error::custom(format!(
            "floor rate {v} Hz is out of range: valid 0.1 to 100"
        )));
    }
    Ok(v)
}

fn default_enabled() -> bool {
    true
}
fn default_ring_frames() -> usize {
    10_000
}
fn default_max_samples() -> usize {
    200_000
}
fn default_floor() -> f64 {
    10.0
}
fn default_max_wait() -> u64 {
    3600
}
