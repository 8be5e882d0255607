//! The drive simulator: a bus of drives behind real RTU bytes on a pty.
//!
//! (Interface stub; the model lands with the simulator.)

pub mod cli;

use std::io;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// Per-request fault injection rates (0.0 to 1.0), reproducible by seed.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct FaultRates {
    /// Fraction of requests that get no reply at all.
    pub drop_rate: f64,
    /// Fraction of replies sent with a corrupted CRC.
    pub crc_error_rate: f64,
    /// Fraction of replies sent `late_ms` late.
    pub late_rate: f64,
    /// How late a late reply is, in ms.
    pub late_ms: f64,
    /// Fraction of idle moments with noise bytes on the line.
    pub noise_rate: f64,
    /// Units that never answer.
    pub silent_units: Vec<u8>,
}

/// One simulated drive.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimDriveConfig {
    /// Its bus address.
    pub unit: u8,
    /// Its gearbox ratio.
    pub gear_ratio: f64,
}

/// A simulated bus.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Baud rate the wire is modelled at.
    pub baud: u32,
    /// Drive processing time before a reply, in ms.
    pub turnaround_ms: f64,
    /// Seed of the fault injection.
    pub seed: u64,
    /// The drives on the bus.
    pub drives: Vec<SimDriveConfig>,
    /// Fault injection.
    pub faults: FaultRates,
}

/// Counters of what the simulated wire saw.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SimStats {
    /// Requests framed (any unit).
    pub requests: u64,
    /// Requests that arrived inside the silent interval.
    pub gap_violations: u64,
}

/// The running simulator.
pub struct Simulator;

impl Simulator {
    /// Starts a simulator on its own thread behind a new pty.
    pub fn start(_config: SimConfig) -> io::Result<SimHandle> {
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            "simulator not built yet",
        ))
    }
}

/// Control of a running simulator; dropping it stops the simulator.
pub struct SimHandle {
    path: PathBuf,
}

impl SimHandle {
    /// The pty path a master opens.
    pub fn port_path(&self) -> &Path {
        &self.path
    }

    /// Counters of the wire.
    pub fn stats(&self) -> SimStats {
        SimStats::default()
    }
}
