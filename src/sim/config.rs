//! What a simulated bus is made of: its line, its drives, its faults.

use std::net::SocketAddr;
use std::time::Duration;

use serde::Deserialize;

use super::config_error::ConfigError;
use super::delivery::Delivery;
use super::faults::FaultRates;
use crate::drive::RangeError;
use crate::drive::units::GEAR_RATIO;

/// The gear ratio of the manual's examples, used when none is given.
pub(crate) const DEFAULT_GEAR_RATIO: f64 = 3.75;

/// One simulated drive.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimDriveConfig {
    /// Its bus address at power-on (1..=255).
    pub unit: u8,
    /// Its gearbox ratio (motor turns per output turn).
    pub gear_ratio: f64,
    /// The silence after which it parts frames: a request that follows the
    /// last frame on the line sooner is, to it, one garbled frame with that
    /// one, and it does not answer; it answers this long (and the
    /// turnaround) after a request. `None`: it frames requests by their
    /// length, answers t3.5 after them, and only counts a short silence.
    #[serde(skip)]
    pub frame_gap: Option<Duration>,
}

/// A simulated bus. Start from [`SimConfig::default`] (or
/// [`SimConfig::for_units`]) and change what matters.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Baud rate the wire is modelled at (8N1).
    pub baud: u32,
    /// Drive processing time between the end of the request's t3.5 and the
    /// first reply byte, in ms (0 allowed).
    pub turnaround_ms: f64,
    /// Seed of the fault injection.
    pub seed: u64,
    /// The drives on the bus.
    pub drives: Vec<SimDriveConfig>,
    /// Units of plain register devices (meters, I/O modules) on the same
    /// bus: 65536 holding registers each, register `a` holding `a`.
    pub devices: Vec<u8>,
    /// Fault injection.
    pub faults: FaultRates,
    /// How long a drive stays silent after a power cycle or a software
    /// reset, in ms.
    pub reboot_ms: f64,
    /// Whether the drives' flash says their encoders have been calibrated
    /// (false models drives that never were: fine-tuning is then refused).
    pub calibrated: bool,
    /// How the replies' bytes reach the master (a UART's exact timing, or a
    /// USB adapter's late chunks).
    pub delivery: Delivery,
    /// Serve the bus on TCP at this address, as a serial device server does,
    /// instead of behind a pty.
    pub listen: Option<SocketAddr>,
    /// A reply the simulator could only start this much later than its time
    /// (the machine kept its thread from running) is not sent: the master
    /// has given up on it, and it would cross the next request on the line.
    /// With a limit set, a reply is not sent either once the master has
    /// begun another frame before its first byte (the master's wait, learned
    /// per drive, can be far shorter than the limit); replies made late on
    /// purpose (`late_rate`) are the exception, sent as a late drive's are.
    /// `None`: sent however late. The daemon's own simulator uses the bus's
    /// response timeout.
    pub max_lag: Option<Duration>,
    /// Send every byte the master writes straight back, as an RS-485
    /// adapter without automatic direction control (or with echo on) makes
    /// its master hear its own request before any answer.
    pub echo: bool,
    /// On a pty, read the baud rate the master set on its end and, when it
    /// is not `baud`, pass the bytes each way through [`super::uart`] (the
    /// levels at the sender's rate, sampled at the receiver's): the drives
    /// then hear garbage, as real ones do from a master at the wrong rate.
    pub check_master_baud: bool,
}

impl Default for SimConfig {
    /// Eight drives (units 1 to 8) at 115200 baud with 0.5 ms turnaround,
    /// gear ratio 3.75, calibrated, no faults, seed 0, 300 ms reboot.
    fn default() -> Self {
        SimConfig::for_units(1..=8)
    }
}

impl SimConfig {
    /// The default bus with drives at `units`.
    pub fn for_units(units: impl IntoIterator<Item = u8>) -> Self {
        SimConfig {
            baud: 115_200,
            turnaround_ms: 0.5,
            seed: 0,
            drives: units
                .into_iter()
                .map(|unit| SimDriveConfig {
                    unit,
                    gear_ratio: DEFAULT_GEAR_RATIO,
                    frame_gap: None,
                })
                .collect(),
            devices: Vec::new(),
            faults: FaultRates::default(),
            reboot_ms: 300.0,
            calibrated: true,
            delivery: Delivery::default(),
            listen: None,
            max_lag: None,
            echo: false,
            check_master_baud: false,
        }
    }

    /// Checks the configuration, naming what is wrong.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(300..=4_000_000).contains(&self.baud) {
            return Err(ConfigError::Baud(self.baud));
        }
        RangeError::check("turnaround", self.turnaround_ms, 0.0, 1000.0, "ms")?;
        RangeError::check("reboot time", self.reboot_ms, 0.0, 60_000.0, "ms")?;
        for (i, drive) in self.drives.iter().enumerate() {
            if drive.unit == 0 {
                return Err(ConfigError::BroadcastUnit);
            }
            if self.drives[..i].iter().any(|d| d.unit == drive.unit) {
                return Err(ConfigError::DuplicateUnit(drive.unit));
            }
            RangeError::check(
                "gear ratio",
                drive.gear_ratio,
                GEAR_RATIO.0,
                GEAR_RATIO.1,
                "",
            )?;
            if let Some(gap) = drive.frame_gap {
                RangeError::check("frame gap", gap.as_secs_f64() * 1e6, 0.0, 100_000.0, "us")?;
            }
        }
        for (i, &unit) in self.devices.iter().enumerate() {
            if unit == 0 {
                return Err(ConfigError::BroadcastUnit);
            }
            if self.drives.iter().any(|d| d.unit == unit) || self.devices[..i].contains(&unit) {
                return Err(ConfigError::DuplicateUnit(unit));
            }
        }
        self.delivery.validate()?;
        self.faults.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_mistakes_are_named() {
        assert_eq!(SimConfig::default().validate(), Ok(()));
        assert_eq!(SimConfig::default().drives.len(), 8);
        let mut c = SimConfig::for_units([1, 2, 1]);
        assert_eq!(c.validate(), Err(ConfigError::DuplicateUnit(1)));
        c = SimConfig::for_units([0]);
        assert_eq!(c.validate(), Err(ConfigError::BroadcastUnit));
        // No drive: a silent line, as a bus with every drive off.
        c = SimConfig::for_units([]);
        assert_eq!(c.validate(), Ok(()));
        c = SimConfig::for_units([1]);
        c.turnaround_ms = -1.0;
        assert_eq!(
            c.validate().unwrap_err().to_string(),
            "turnaround -1 ms is out of range: valid 0 to 1000 ms"
        );
        c = SimConfig::for_units([1]);
        c.faults.drop_rate = 2.0;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .starts_with("drop rate 2")
        );
        c = SimConfig::for_units([1]);
        c.drives[0].gear_ratio = 0.0;
        assert!(c.validate().is_err());
        c = SimConfig::for_units([1]);
        c.devices = vec![100, 1];
        assert_eq!(c.validate(), Err(ConfigError::DuplicateUnit(1)));
    }
}
