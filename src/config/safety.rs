//! `[safety]` section: what the daemon does to moving motors nobody
//! controls any more (a lease ran out, the daemon stops), and the console's
//! jog lease. Plain data; `crate::control::stop_action` and the control core act on it.

use serde::Deserialize;

use super::values::int_in;

/// How to stop a motor nobody controls.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StopAction {
    /// Leave it as it is.
    None,
    /// Speed setpoint 0 in speed mode, current 0 in torque mode (ramped
    /// stop); both when the mode is unknown.
    #[default]
    ZeroSpeed,
    /// Emergency brake.
    Brake,
}

impl StopAction {
    /// Stable name for logs and the API.
    pub fn name(self) -> &'static str {
        match self {
            StopAction::None => "none",
            StopAction::ZeroSpeed => "zero-speed",
            StopAction::Brake => "brake",
        }
    }
}

/// `[safety]` section.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    /// Applied to every moving drive when the daemon stops.
    pub on_shutdown: StopAction,
    /// Applied when a client's setpoint lease runs out.
    pub on_lease_expiry: StopAction,
    /// The lease of a jog from the web console, ms: how long the motor runs
    /// on after the page's last renewal (it renews three times a lease).
    /// Longer rides out a tablet's Wi-Fi hiccups; shorter stops sooner.
    #[serde(deserialize_with = "int_in::<_, _, 100, 5000>")]
    pub jog_lease_ms: u64,
    /// Shortest lease a setpoint may ask for, ms, from any face: below it a
    /// client's ordinary network jitter would stop the motor.
    #[serde(deserialize_with = "int_in::<_, _, 10, 3_600_000>")]
    pub lease_min_ms: u64,
    /// Longest lease a setpoint may ask for, ms (at least
    /// `lease_min_ms`): how long a motor may run on for a client that went
    /// silent.
    #[serde(deserialize_with = "int_in::<_, _, 10, 86_400_000>")]
    pub lease_max_ms: u64,
    /// Where the safety journal is kept (leases, stops owed, brakes), so
    /// a restart keeps every promise made about a motor. `None`: systemd's
    /// `$STATE_DIRECTORY`, else none (nothing survives a restart).
    pub state_dir: Option<std::path::PathBuf>,
    /// Applied at start-up to every drive found moving when the safety
    /// journal could not be read: who asked for what is unknown.
    pub on_unknown_state: StopAction,
    /// Alarms kept (in memory and in `state_dir`'s `alarms.journal`): past
    /// it the oldest cleared and acknowledged ones go first.
    #[serde(deserialize_with = "int_in::<_, _, 10, 100_000>")]
    pub alarms_kept: usize,
}

impl SafetyConfig {
    /// The state directory: `state_dir`, else `$STATE_DIRECTORY` (the
    /// first, when systemd lists several).
    pub fn state_dir(&self) -> Option<std::path::PathBuf> {
        self.state_dir.clone().or_else(|| {
            let env = std::env::var_os("STATE_DIRECTORY")?;
            let first = env.to_string_lossy().split(':').next()?.to_string();
            (!first.is_empty()).then(|| first.into())
        })
    }
}

impl Default for SafetyConfig {
    fn default() -> Self {
        Self {
            on_shutdown: StopAction::ZeroSpeed,
            on_lease_expiry: StopAction::ZeroSpeed,
            jog_lease_ms: 300,
            lease_min_ms: 100,
            lease_max_ms: 60_000,
            state_dir: None,
            on_unknown_state: StopAction::ZeroSpeed,
            alarms_kept: 500,
        }
    }
}
