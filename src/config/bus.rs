//! `[[bus]]` and `[[bus.drive]]` sections.

use std::time::Duration;

use serde::{Deserialize, Deserializer};
use toml::Spanned;

use super::declared::{Declared, DeclaredKeys};
use super::values::{self, Name, UnitAddress};
use crate::bus::interframe::Interframe;
use crate::bus::master::{Guard, MasterSettings};
use crate::bus::port::Rs485Settings;
use crate::bus::queue::QueueLimits;
use crate::bus::scheduler::BusSettings;
use crate::sim::{Delivery, FaultRates, SimConfig, SimDriveConfig};

/// One serial adapter and the drives on it.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BusConfig {
    /// Name in logs, metrics and the API.
    pub name: Spanned<Name>,
    /// Serial device (prefer a stable `/dev/serial/by-id/...` path),
    /// `tcp://host:port` for a serial device server, or `"sim"` for the
    /// built-in simulator.
    pub port: Spanned<String>,
    /// Baud rate (the drives speak 115200).
    #[serde(
        default = "default_baud",
        deserialize_with = "values::int_in::<_, _, 1200, 4000000>"
    )]
    pub baud: u32,
    /// How long to wait for a reply, after the request has left the wire.
    #[serde(
        default = "default_timeout",
        deserialize_with = "values::int_in::<_, _, 1, 10000>"
    )]
    pub response_timeout_ms: u64,
    /// The least wait for a reply's first byte once a drive's own wait is
    /// learned (it is never more than `response_timeout_ms`).
    #[serde(
        default = "default_reply_timeout_floor",
        deserialize_with = "values::int_in::<_, _, 1, 10000>"
    )]
    pub reply_timeout_floor_ms: u64,
    /// Attempts after the first on a timeout or a corrupted reply.
    #[serde(
        default = "default_retries",
        deserialize_with = "values::int_in::<_, _, 0, 10>"
    )]
    pub retries: u8,
    /// Default poll interval of each drive; 0 = as fast as the bus allows.
    #[serde(default, deserialize_with = "values::int_in::<_, _, 0, 3600000>")]
    pub poll_interval_ms: u64,
    /// Silence kept after a timeout or bad reply, discarding late bytes
    /// (default: sized by the wire, with each drive's reply timeout learned;
    /// set, the full response timeout for every reply and this guard after
    /// every fault, nothing learned).
    #[serde(default, deserialize_with = "values::opt_int_in::<_, _, 0, 10000>")]
    pub guard_ms: Option<u64>,
    /// The silence before each request: `"spec"` (t3.5, 1.75 ms above
    /// 19200 baud), `"auto"` (each drive's own, learned), or microseconds.
    #[serde(default, deserialize_with = "interframe")]
    pub interframe: Interframe,
    /// Time the drives get after a broadcast before the next request.
    #[serde(
        default = "default_broadcast_delay",
        deserialize_with = "values::int_in::<_, _, 0, 10000>"
    )]
    pub broadcast_delay_ms: u64,
    /// Failed polls in a row before a drive is reported offline.
    #[serde(
        default = "default_offline_after",
        deserialize_with = "values::int_in::<_, _, 1, 1000>"
    )]
    pub offline_after: u32,
    /// First retry delay of an offline drive (doubles up to the max).
    #[serde(
        default = "default_backoff",
        deserialize_with = "values::int_in::<_, _, 10, 3600000>"
    )]
    pub offline_backoff_ms: u64,
    /// Longest retry delay of an offline drive.
    #[serde(
        default = "default_backoff_max",
        deserialize_with = "values::int_in::<_, _, 10, 3600000>"
    )]
    pub offline_backoff_max_ms: u64,
    /// Jobs that may wait per priority class.
    #[serde(
        default = "default_queue",
        deserialize_with = "values::int_in::<_, _, 1, 100000>"
    )]
    pub queue_capacity: usize,
    /// Jobs one client (connection) may have waiting.
    #[serde(
        default = "default_queue_per_client",
        deserialize_with = "values::int_in::<_, _, 1, 100000>"
    )]
    pub queue_per_client: usize,
    /// How long a job may wait for the bus before it is dropped unsent.
    #[serde(
        default = "default_queue_timeout",
        deserialize_with = "values::int_in::<_, _, 1, 600000>"
    )]
    pub queue_timeout_ms: u64,
    /// While polls are due, at most this many commands run before one poll.
    #[serde(
        default = "default_poll_share",
        deserialize_with = "values::int_in::<_, _, 1, 1000>"
    )]
    pub poll_share: u32,
    /// RS-485 direction control.
    #[serde(default, deserialize_with = "rs485")]
    pub rs485: Rs485Settings,
    /// Simulator options (only with `port = "sim"`).
    #[serde(default)]
    pub sim: Option<SimSection>,
    /// The drives on this bus.
    #[serde(rename = "drive", default)]
    pub drives: Vec<DriveConfig>,
}

/// `[bus.sim]`: the built-in simulator's options.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimSection {
    /// Drive processing time before replying, ms.
    #[serde(default = "default_turnaround")]
    pub turnaround_ms: f64,
    /// Seed of the fault injection.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// How long a drive stays silent after a power cycle or soft reset, ms.
    #[serde(default = "default_reboot")]
    pub reboot_ms: f64,
    /// Whether the simulated drives start calibrated.
    #[serde(default = "default_calibrated")]
    pub calibrated: bool,
    /// Units of plain register devices (meters, I/O) simulated beside the
    /// drives: 65536 holding registers each, for long reads.
    #[serde(default)]
    pub devices: Vec<u8>,
    /// Fault injection rates.
    #[serde(default)]
    pub faults: FaultRates,
    /// How reply bytes reach the daemon: `[bus.sim.delivery] chunk_bytes`,
    /// `jitter_us` model a USB adapter's late chunks (default: a UART's
    /// exact timing).
    #[serde(default, deserialize_with = "delivery")]
    pub delivery: Delivery,
    /// The silence after which the simulated drives part frames, µs: a
    /// request that follows the last frame sooner is garbled to them and
    /// not answered; they answer this long (and the turnaround) after a
    /// request. Default: none, the drives frame requests by their length
    /// and answer t3.5 after them.
    #[serde(default, deserialize_with = "values::opt_int_in::<_, _, 50, 100000>")]
    pub frame_gap_us: Option<u32>,
    /// Drives that part frames only after the spec's t3.5.
    #[serde(default)]
    pub strict_units: Vec<u8>,
}

impl Default for SimSection {
    fn default() -> Self {
        Self {
            turnaround_ms: default_turnaround(),
            seed: default_seed(),
            reboot_ms: default_reboot(),
            calibrated: default_calibrated(),
            devices: Vec::new(),
            faults: FaultRates::default(),
            delivery: Delivery::default(),
            frame_gap_us: None,
            strict_units: Vec::new(),
        }
    }
}

/// One drive on a bus.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    /// Its address on the bus, 1 to 255.
    pub unit: Spanned<UnitAddress>,
    /// Its name in the API and metrics, unique over all buses.
    pub name: Spanned<Name>,
    /// Gearbox ratio (motor turns per output turn), used by the ramp formulas.
    #[serde(
        default = "default_gear_ratio",
        deserialize_with = "values::gear_ratio"
    )]
    pub gear_ratio: f64,
    /// Poll interval of this drive, overriding the bus's.
    #[serde(default, deserialize_with = "values::opt_int_in::<_, _, 0, 3600000>")]
    pub poll_interval_ms: Option<u64>,
    /// `[bus.drive.settings]`: the settings the drive must hold, compared
    /// with it whenever it comes online.
    #[serde(default)]
    pub settings: Option<Spanned<DeclaredKeys>>,
}

impl DriveConfig {
    /// The unit address.
    pub fn unit(&self) -> u8 {
        self.unit.get_ref().0
    }

    /// The drive's name.
    pub fn name(&self) -> &str {
        self.name.get_ref().as_str()
    }

    /// Its declared settings, if it has any that hold (checked when the
    /// configuration is loaded).
    pub fn declared(&self) -> Option<Declared> {
        self.settings.as_ref()?.get_ref().declared().ok()
    }
}

impl BusConfig {
    /// The bus's name.
    pub fn name(&self) -> &str {
        self.name.get_ref().as_str()
    }

    /// True for the built-in simulator.
    pub fn is_simulated(&self) -> bool {
        self.port.get_ref() == "sim"
    }

    /// The simulator for this bus: its drives, at this baud, with `[bus.sim]`.
    pub fn sim_config(&self) -> SimConfig {
        let section = self.sim.clone().unwrap_or_default();
        SimConfig {
            baud: self.baud,
            turnaround_ms: section.turnaround_ms,
            seed: section.seed,
            drives: self
                .drives
                .iter()
                .map(|d| SimDriveConfig {
                    unit: d.unit(),
                    gear_ratio: d.gear_ratio,
                    frame_gap: sim_frame_gap(&section, d.unit(), self.baud),
                })
                .collect(),
            devices: section.devices,
            faults: section.faults,
            reboot_ms: section.reboot_ms,
            calibrated: section.calibrated,
            delivery: section.delivery,
            listen: None,
            // Later than the master waits, a reply only crosses its next
            // request.
            max_lag: Some(Duration::from_millis(self.response_timeout_ms)),
            echo: false,
            check_master_baud: false,
        }
    }

    /// The silence every drive's requests get at start: t3.5, or the
    /// fixed `interframe`.
    pub fn starting_interframe(&self) -> Duration {
        match self.interframe {
            Interframe::Fixed(gap) => gap,
            Interframe::Spec | Interframe::Auto => {
                crate::modbus::timing::LineTiming::new_8n1(self.baud).t3_5()
            }
        }
    }

    /// The scheduler's settings, with the serial device at `port_path` (the
    /// simulator's pty for a simulated bus).
    pub fn settings(&self, port_path: &str) -> BusSettings {
        let timeout = Duration::from_millis(self.response_timeout_ms);
        let mut master = MasterSettings::new(self.baud, timeout, self.retries);
        master.guard = self
            .guard_ms
            .map_or(Guard::Auto, |ms| Guard::Fixed(Duration::from_millis(ms)));
        master.reply_timeout_floor = Duration::from_millis(self.reply_timeout_floor_ms);
        master.broadcast_delay = Duration::from_millis(self.broadcast_delay_ms);
        master.interframe = self.interframe;
        master.rs485 = self.rs485;
        let mut settings = BusSettings::new(
            self.name(),
            port_path,
            self.baud,
            self.drives
                .iter()
                .map(|d| {
                    let ms = d.poll_interval_ms.unwrap_or(self.poll_interval_ms);
                    (d.unit(), Duration::from_millis(ms))
                })
                .collect(),
        );
        settings.master = master;
        settings.offline_after = self.offline_after;
        settings.offline_backoff = (
            Duration::from_millis(self.offline_backoff_ms),
            Duration::from_millis(self.offline_backoff_max_ms.max(self.offline_backoff_ms)),
        );
        settings.queue = QueueLimits {
            per_class: self.queue_capacity,
            per_source: self.queue_per_client.min(self.queue_capacity),
        };
        settings.queue_timeout = Duration::from_millis(self.queue_timeout_ms);
        settings.poll_share = self.poll_share;
        settings
    }
}

/// The frame separation of the simulated drive at `unit` (see
/// [`SimSection::frame_gap_us`]).
fn sim_frame_gap(section: &SimSection, unit: u8, baud: u32) -> Option<Duration> {
    if section.strict_units.contains(&unit) {
        return Some(crate::modbus::timing::LineTiming::new_8n1(baud).t3_5());
    }
    section
        .frame_gap_us
        .map(|us| Duration::from_micros(u64::from(us)))
}

/// The least and most a fixed `interframe` may be, µs.
const INTERFRAME_US: (u64, u64) = (100, 100_000);

/// `interframe`: `"spec"`, `"auto"` or a number of microseconds.
/// `[bus.rs485]` as written: the delays within what the kernel's RS-485
/// mode takes (it caps them at 100 ms).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRs485 {
    #[serde(default)]
    direction: crate::bus::port::Direction,
    #[serde(default = "yes")]
    rts_active_high: bool,
    #[serde(default, deserialize_with = "values::int_in::<_, _, 0, 100_000>")]
    delay_before_send_us: u32,
    #[serde(default, deserialize_with = "values::int_in::<_, _, 0, 100_000>")]
    delay_after_send_us: u32,
}

fn yes() -> bool {
    true
}

fn rs485<'de, D: Deserializer<'de>>(d: D) -> Result<Rs485Settings, D::Error> {
    let raw = RawRs485::deserialize(d)?;
    Ok(Rs485Settings {
        direction: raw.direction,
        rts_active_high: raw.rts_active_high,
        delay_before_send_us: raw.delay_before_send_us,
        delay_after_send_us: raw.delay_after_send_us,
    })
}

/// `[bus.sim.delivery]` as written: chunks of 1 byte (a UART) to 256,
/// each up to 100 ms late (the simulator's own bounds).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDelivery {
    #[serde(default = "one", deserialize_with = "values::int_in::<_, _, 1, 256>")]
    chunk_bytes: u16,
    #[serde(default, deserialize_with = "values::int_in::<_, _, 0, 100_000>")]
    jitter_us: u32,
}

fn one() -> u16 {
    1
}

fn delivery<'de, D: Deserializer<'de>>(d: D) -> Result<Delivery, D::Error> {
    let raw = RawDelivery::deserialize(d)?;
    Ok(Delivery {
        chunk_bytes: raw.chunk_bytes,
        jitter_us: raw.jitter_us,
    })
}

fn interframe<'de, D: Deserializer<'de>>(d: D) -> Result<Interframe, D::Error> {
    struct Visitor;
    impl serde::de::Visitor<'_> for Visitor {
        type Value = Interframe;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(
                f,
                "\"spec\", \"auto\" or a number of microseconds ({} to {})",
                INTERFRAME_US.0, INTERFRAME_US.1
            )
        }

        fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Interframe, E> {
            match v {
                "spec" => Ok(Interframe::Spec),
                "auto" => Ok(Interframe::Auto),
                _ => Err(E::custom(format!(
                    "interframe \"{v}\" is not \"spec\", \"auto\" or a number of \
                     microseconds ({} to {})",
                    INTERFRAME_US.0, INTERFRAME_US.1
                ))),
            }
        }

        fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Interframe, E> {
            match u64::try_from(v) {
                Ok(us) if (INTERFRAME_US.0..=INTERFRAME_US.1).contains(&us) => {
                    Ok(Interframe::Fixed(Duration::from_micros(us)))
                }
                _ => Err(E::custom(format!(
                    "interframe {v} us is out of range: valid {} to {} (or \"spec\", \"auto\")",
                    INTERFRAME_US.0, INTERFRAME_US.1
                ))),
            }
        }
    }
    d.deserialize_any(Visitor)
}

fn default_baud() -> u32 {
    115_200
}
fn default_timeout() -> u64 {
    50
}
fn default_reply_timeout_floor() -> u64 {
    crate::bus::master::DEFAULT_REPLY_TIMEOUT_FLOOR.as_millis() as u64
}
fn default_retries() -> u8 {
    1
}
fn default_broadcast_delay() -> u64 {
    20
}
fn default_offline_after() -> u32 {
    3
}
fn default_backoff() -> u64 {
    2000
}
fn default_backoff_max() -> u64 {
    30_000
}
fn default_queue() -> usize {
    256
}
fn default_queue_per_client() -> usize {
    64
}
fn default_queue_timeout() -> u64 {
    5000
}
fn default_poll_share() -> u32 {
    4
}
fn default_turnaround() -> f64 {
    0.5
}
fn default_seed() -> u64 {
    1
}
fn default_reboot() -> f64 {
    300.0
}
fn default_calibrated() -> bool {
    true
}
fn default_gear_ratio() -> f64 {
    1.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    fn bus(keys: &str) -> Result<BusConfig, String> {
        let text = format!("[[bus]]\nname = \"line1\"\nport = \"sim\"\n{keys}\n");
        Config::parse(&text, "test")
            .map(|c| c.buses[0].clone())
            .map_err(|e| e.to_string())
    }

    #[test]
    fn interframe_is_spec_auto_or_microseconds() {
        assert_eq!(bus("").unwrap().interframe, Interframe::Spec);
        assert_eq!(
            bus("interframe = \"spec\"").unwrap().interframe,
            Interframe::Spec
        );
        assert_eq!(
            bus("interframe = \"auto\"").unwrap().interframe,
            Interframe::Auto
        );
        let fixed = bus("interframe = 400").unwrap();
        assert_eq!(
            fixed.interframe,
            Interframe::Fixed(Duration::from_micros(400))
        );
        assert_eq!(fixed.starting_interframe(), Duration::from_micros(400));
        assert_eq!(
            fixed.settings("/dev/ttyUSB0").master.interframe,
            fixed.interframe
        );
        assert_eq!(
            bus("").unwrap().starting_interframe(),
            Duration::from_micros(1750)
        );
        let e = bus("interframe = \"fast\"").unwrap_err();
        assert!(
            e.contains("test:4:14") && e.contains("\"spec\", \"auto\""),
            "{e}"
        );
        let e = bus("interframe = 50").unwrap_err();
        assert!(e.contains("out of range: valid 100 to 100000"), "{e}");
    }

    #[test]
    fn the_simulated_drives_frame_gaps() {
        let b = bus("[bus.sim]\nframe_gap_us = 350\nstrict_units = [2]\n[[bus.drive]]\nunit = 1\nname = \"a\"\n[[bus.drive]]\nunit = 2\nname = \"b\"").unwrap();
        let gaps: Vec<_> = b.sim_config().drives.iter().map(|d| d.frame_gap).collect();
        assert_eq!(
            gaps,
            [
                Some(Duration::from_micros(350)),
                Some(Duration::from_micros(1750))
            ]
        );
        assert_eq!(bus("").unwrap().sim_config().drives.len(), 0);
    }
}
