//! Control of a running simulator: the truth about its drives for tests and
//! metrics, the knobs of the fault suite, and its lifetime.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use super::bus::Bus;
use super::bus::lock;
use super::config_error::ConfigError;
use super::faults::FaultRates;
use super::model::{DriveModel, SimDriveView};
use super::physics::Environment;
use super::stats::{GapHistogram, SimStats};
use super::tcp::Disconnects;
use crate::drive::{Fault, RangeError};

/// Why a handle operation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// No simulated drive has that address now.
    #[error("no simulated drive has address {0}")]
    UnknownUnit(u8),
    /// A value outside what the simulation accepts.
    #[error(transparent)]
    Range(#[from] RangeError),
    /// Invalid fault rates.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

/// Control of a running simulator. Dropping it stops the simulator, closes
/// its pty (masters then read EIO or EOF: the bus is "unplugged") and removes
/// the link made with [`link_at`](Self::link_at).
pub struct SimHandle {
    path: PathBuf,
    disconnects: Option<Arc<Disconnects>>,
    link: Option<PathBuf>,
    bus: Arc<Mutex<Bus>>,
    cancel: CancellationToken,
    thread: Option<JoinHandle<()>>,
}

impl SimHandle {
    pub(super) fn new(
        path: PathBuf,
        disconnects: Option<Arc<Disconnects>>,
        bus: Arc<Mutex<Bus>>,
        cancel: CancellationToken,
        thread: JoinHandle<()>,
    ) -> Self {
        SimHandle {
            path,
            disconnects,
            link: None,
            bus,
            cancel,
            thread: Some(thread),
        }
    }

    /// Where a master connects: the pty path (e.g. `/dev/pts/3`), or
    /// `tcp://ip:port` for a simulator served on TCP; what a bus's `port`
    /// is set to.
    pub fn port_path(&self) -> &Path {
        &self.path
    }

    /// Closes the TCP connection of the master (a device server's reboot, a
    /// network cut); the simulator takes the next one. False behind a pty.
    pub fn disconnect(&self) -> bool {
        self.disconnects.as_ref().map(|d| d.disconnect()).is_some()
    }

    /// The symlink made by [`link_at`](Self::link_at), if any.
    pub fn link_path(&self) -> Option<&Path> {
        self.link.as_deref()
    }

    /// Makes `link` a symlink to the pty (replacing an existing symlink, never
    /// a real file); it is removed when the simulator stops.
    pub fn link_at(&mut self, link: impl AsRef<Path>) -> io::Result<()> {
        let link = link.as_ref();
        if self.disconnects.is_some() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "a simulator served on TCP has no pty to link to",
            ));
        }
        match fs::symlink_metadata(link) {
            Ok(meta) if meta.file_type().is_symlink() => fs::remove_file(link)?,
            Ok(_) => {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "{} exists and is not a symlink: not replacing it",
                        link.display()
                    ),
                ));
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(e),
        }
        std::os::unix::fs::symlink(&self.path, link)?;
        if let Some(old) = self.link.replace(link.to_path_buf())
            && old != link
        {
            remove_link(&old, &self.path);
        }
        Ok(())
    }

    /// The wire's counters.
    pub fn stats(&self) -> SimStats {
        lock(&self.bus).stats()
    }

    /// Keeps the simulator from running for `time`, as a starved machine
    /// would; blocks the calling thread that long. A request that arrives
    /// meanwhile is answered late, or not at all once the master has given
    /// up on it (see `SimConfig::max_lag`).
    pub fn stall(&self, time: Duration) {
        let _bus = lock(&self.bus);
        std::thread::sleep(time);
    }

    /// The silences the wire saw before each request (the master's idle
    /// time between frames, as the drives see it).
    pub fn gaps(&self) -> GapHistogram {
        lock(&self.bus).gaps().clone()
    }

    /// The fault rates in force.
    pub fn fault_rates(&self) -> FaultRates {
        lock(&self.bus).fault_rates().clone()
    }

    /// Changes the fault rates from the next request on.
    pub fn set_fault_rates(&self, rates: FaultRates) -> Result<(), SimError> {
        rates.validate()?;
        lock(&self.bus).set_fault_rates(rates);
        Ok(())
    }

    /// Makes `unit` never answer, or answer again.
    pub fn set_silent(&self, unit: u8, silent: bool) {
        lock(&self.bus).set_silent(unit, silent);
    }

    /// Makes `unit` stop answering once it has carried out `writes` more
    /// writes (reads do not count): a drive that stops answering part-way
    /// through a sequence of writes. [`set_silent`](Self::set_silent)
    /// lets it answer again.
    pub fn silence_after_writes(&self, unit: u8, writes: u32) {
        lock(&self.bus).silence_after_writes(unit, writes);
    }

    /// A snapshot of the drive at `unit` (its address now).
    pub fn drive(&self, unit: u8) -> Option<SimDriveView> {
        self.with_drive(unit, |d| d.view()).ok()
    }

    /// Snapshots of every drive, in configuration order.
    pub fn drives(&self) -> Vec<SimDriveView> {
        lock(&self.bus).views(Instant::now())
    }

    /// Injects a hardware fault into the drive at `unit`; it stays until
    /// [`clear_fault`](Self::clear_fault) and a fault reset.
    pub fn inject_fault(&self, unit: u8, fault: Fault) -> Result<(), SimError> {
        self.with_drive(unit, |d| d.inject_fault(fault))
    }

    /// Removes an injected fault's cause (the drive still needs a fault reset).
    pub fn clear_fault(&self, unit: u8) -> Result<(), SimError> {
        self.with_drive(unit, DriveModel::clear_injected_fault)
    }

    /// Cuts the power of the drive at `unit`: it is silent for the reboot
    /// time, then comes back with what its flash holds.
    pub fn power_cycle(&self, unit: u8) -> Result<(), SimError> {
        self.with_drive(unit, DriveModel::power_cycle)
    }

    /// Sets the silence after which the drive at `unit` parts frames
    /// (`None`: by length, as at start without a frame gap): a drive
    /// replaced by a stricter one.
    pub fn set_frame_gap(&self, unit: u8, gap: Option<Duration>) -> Result<(), SimError> {
        if lock(&self.bus).set_frame_gap(unit, gap) {
            Ok(())
        } else {
            Err(SimError::UnknownUnit(unit))
        }
    }

    /// Replaces the drive at `unit` with a new one at the same address,
    /// fresh from the factory (factory settings, inactive): silent for the
    /// reboot time, then back. Keep it silent meanwhile
    /// ([`set_silent`](Self::set_silent)) for a replacement the poller
    /// sees as offline, then online.
    pub fn replace(&self, unit: u8) -> Result<(), SimError> {
        self.with_drive(unit, DriveModel::replace)
    }

    /// Load torque at the gearbox output of the drive at `unit`, N·m
    /// (positive opposes forward motion).
    pub fn set_load_torque(&self, unit: u8, newton_metres: f64) -> Result<(), SimError> {
        let v = RangeError::check("load torque", newton_metres, -1000.0, 1000.0, "N·m")?;
        self.set_environment(unit, |e| e.load_torque = v)
    }

    /// Open-circuit supply voltage of the drive at `unit`, V.
    pub fn set_supply_voltage(&self, unit: u8, volts: f64) -> Result<(), SimError> {
        let v = RangeError::check("supply voltage", volts, 0.0, 100.0, "V")?;
        self.set_environment(unit, |e| e.supply_voltage = v)
    }

    /// Ambient temperature around the drive at `unit`, °C.
    pub fn set_ambient_temperature(&self, unit: u8, celsius: f64) -> Result<(), SimError> {
        let v = RangeError::check("ambient temperature", celsius, -40.0, 125.0, "°C")?;
        self.set_environment(unit, |e| e.ambient = v)
    }

    /// True while the simulator's thread runs.
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Stops the simulator (as dropping the handle does).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn set_environment(
        &self,
        unit: u8,
        change: impl FnOnce(&mut Environment),
    ) -> Result<(), SimError> {
        self.with_drive(unit, |d| {
            let mut env = d.environment();
            change(&mut env);
            d.set_environment(env);
        })
    }

    fn with_drive<T>(&self, unit: u8, f: impl FnOnce(&mut DriveModel) -> T) -> Result<T, SimError> {
        let mut bus = lock(&self.bus);
        bus.drive(unit, Instant::now())
            .map(f)
            .ok_or(SimError::UnknownUnit(unit))
    }

    fn shutdown(&mut self) {
        self.cancel.cancel();
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!("the simulator thread panicked");
        }
        if let Some(link) = self.link.take() {
            remove_link(&link, &self.path);
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

impl std::fmt::Debug for SimHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimHandle")
            .field("path", &self.path)
            .field("link", &self.link)
            .finish_non_exhaustive()
    }
}

/// Removes `link` if it is still our symlink to `target`.
fn remove_link(link: &Path, target: &Path) {
    if fs::read_link(link).is_ok_and(|t| t == target)
        && let Err(e) = fs::remove_file(link)
    {
        tracing::warn!("could not remove the link {}: {e}", link.display());
    }
}
