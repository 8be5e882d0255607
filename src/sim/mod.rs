//! The drive simulator: a timing-accurate bus of drives behind real RTU bytes
//! on a pty (or on TCP, as a serial device server serves a line).
//!
//! The daemon runs it in-process for a bus configured with `port = "sim"`;
//! `drivegate sim` serves it to third-party tools. A master opens
//! [`SimHandle::port_path`] as it would a serial port and cannot tell the
//! difference from the wire: the bytes, their pacing, the silences and the
//! drives' behaviour follow the manual.
//!
//! The parts, each pure except the last three:
//! - `ramp`: the setpoint ramp (bang-bang, manual 1.9/1.10);
//! - `physics`: the motor, its supply and its heat;
//! - `control`: the drive's speed and position loops;
//! - [`model`]: one drive: registers, flash, commands, protections, faults;
//! - `device`: a plain register device (meter, I/O) on the same bus;
//! - `slave`: the Modbus slave (PDU in, PDU out, exceptions);
//! - `faults`: seeded fault injection on the wire;
//! - `delivery`: when the master receives each reply byte (a UART, or a
//!   USB adapter's late chunks);
//! - [`bus`]: the drives on one line, who answers what;
//! - `uart`: what a receiver at one baud rate reads of bytes sent at
//!   another (a master at the wrong rate);
//! - `wire`: framing and the line's timing on the pty or TCP, and an
//!   adapter's echo;
//! - [`pty`]: the pseudo-terminal;
//! - `tcp`: the line served on TCP;
//! - `handle`: control of a running simulator.
//!
//! The simulator runs on its own thread (`sim-bus`) with a current-thread
//! runtime, so its timing does not depend on the load of the caller's
//! runtime; the handle and the thread share the bus behind a mutex that is
//! never held across an await.
//!
//! The drives belong to the simulated plant, not to the port they are
//! reached through: [`SimDrives`] holds them, and a simulator started on
//! it ([`Simulator::start_on`]) serves them on a new pty. The daemon keeps
//! one `SimDrives` per simulated bus for as long as the bus is configured
//! (`crate::plant`), so a bus reopened (another baud rate, new `[bus.sim]`
//! settings) finds its drives as real ones would be: turning, in their
//! mode, at their position.

pub mod bus;
pub mod cli;
pub(crate) mod closed_loop;
pub(crate) mod config;
pub(crate) mod config_error;
pub(crate) mod delivery;
pub(crate) mod device;
pub(crate) mod faults;
pub(crate) mod handle;
pub mod model;
pub(crate) mod physics;
pub mod pty;
pub(crate) mod ramp;
pub(crate) mod slave;
pub(crate) mod stats;
pub(crate) mod tcp;
pub(crate) mod uart;
pub(crate) mod wire;

use std::io;
use std::path::PathBuf;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio_util::sync::CancellationToken;

pub use config::{SimConfig, SimDriveConfig};
pub use config_error::ConfigError;
pub use delivery::Delivery;
pub use faults::FaultRates;
pub use handle::{SimError, SimHandle};
pub use model::SimDriveView;
pub use stats::{GapHistogram, SimStats};

use bus::Bus;
use tcp::Disconnects;
use wire::Wire;

/// The drives (and devices) of one simulated line, apart from any port:
/// what a simulator started on them serves, kept while its port is closed
/// and opened again. Cheap to clone: the clones share the drives.
#[derive(Clone)]
pub struct SimDrives(Arc<Mutex<Bus>>);

impl SimDrives {
    /// The drives of `config`, powered on now.
    pub fn new(config: &SimConfig) -> Self {
        SimDrives(Arc::new(Mutex::new(Bus::new(config, Instant::now()))))
    }

    /// Follows `config` (a reload): the drives on the line stay as they
    /// are, those it adds are wired in fresh from the factory, those it
    /// no longer names stay wired (not polled, as a real drive taken out
    /// of the configuration); a simulator serving them sees the change
    /// from its next request.
    pub fn follow(&self, config: &SimConfig) {
        bus::lock(&self.0).follow(config, Instant::now());
    }

    /// Snapshots of every drive, in configuration order.
    pub fn views(&self) -> Vec<SimDriveView> {
        bus::lock(&self.0).views(Instant::now())
    }
}

impl std::fmt::Debug for SimDrives {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("SimDrives").finish_non_exhaustive()
    }
}

/// Starts simulated buses.
pub struct Simulator;

impl Simulator {
    /// Starts a simulator on its own thread behind a new pty (or listening
    /// on `config.listen`); returns once masters can open it.
    pub fn start(config: SimConfig) -> io::Result<SimHandle> {
        config
            .validate()
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        let drives = SimDrives::new(&config);
        Self::start_on(config, &drives)
    }

    /// Starts a simulator serving `drives` (made to follow `config` first)
    /// on a new pty (or listening on `config.listen`): the line reopened,
    /// its drives as they were. Returns once masters can open it.
    pub fn start_on(config: SimConfig, drives: &SimDrives) -> io::Result<SimHandle> {
        config
            .validate()
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        drives.follow(&config);
        let bus = Arc::clone(&drives.0);
        let cancel = CancellationToken::new();
        let (ready_tx, ready_rx) = mpsc::sync_channel(1);
        let thread = std::thread::Builder::new().name("sim-bus".into()).spawn({
            let bus = Arc::clone(&bus);
            let cancel = cancel.clone();
            move || run(config, bus, cancel, ready_tx)
        })?;
        match ready_rx.recv() {
            Ok(Ok((path, disconnects))) => {
                Ok(SimHandle::new(path, disconnects, bus, cancel, thread))
            }
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => {
                let _ = thread.join();
                Err(io::Error::other(
                    "the simulator stopped before its port was ready",
                ))
            }
        }
    }
}

/// The simulator thread: its own runtime, the pty, the wire until cancelled.
fn run(
    config: SimConfig,
    bus: Arc<Mutex<Bus>>,
    cancel: CancellationToken,
    ready: mpsc::SyncSender<io::Result<(PathBuf, Option<Arc<Disconnects>>)>>,
) {
    crate::clock::tighten_timer_slack();
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            let _ = ready.send(Err(e));
            return;
        }
    };
    runtime.block_on(async move {
        let wire = match Wire::new(&config, bus) {
            Ok(wire) => wire,
            Err(e) => {
                let _ = ready.send(Err(e));
                return;
            }
        };
        let _ = ready.send(Ok((wire.path().to_path_buf(), wire.disconnects())));
        tokio::select! {
            () = cancel.cancelled() => {}
            result = wire.serve() => {
                if let Err(e) = result {
                    tracing::error!("the simulated bus stopped: {e}");
                }
            }
        }
    });
}
