//! The plant: every configured bus (with its simulator, if simulated) and
//! the directory of drives by name. The faces resolve a drive here and then
//! talk to its bus through the bus's handle.
//!
//! A reload changes the plant bus by bus, touching only what changed
//! ([`Plant::apply`]): a bus whose port, baud rate or transport changed is
//! stopped and started again; any other change of a bus (timing, poll
//! rates, drives added, removed or renamed) is handed to its running
//! scheduler, which takes it between two transactions without closing the
//! port. A drive is the motor at a unit of a bus: it keeps its slot (its
//! lease, its subscriptions, its status, its trends, its alarms) through a
//! rename, and loses it only when it leaves, or when its bus moves to
//! another port (other motors are behind it).
//!
//! The built-in simulator's drives belong to the simulated plant, not to a
//! port: the plant keeps each simulated bus's [`SimDrives`] by bus name
//! for as long as the bus is configured, so a bus reopened finds them as
//! real drives would be (turning, in their mode, at their position); they
//! go when the bus is removed, or stops being simulated.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::bus::{BusHandle, Observers};
use crate::config::{BusConfig, Config, Declared, DriveConfig};
use crate::monitor::BusMonitor;
use crate::scope::Scope;
use crate::sim::{SimDrives, SimHandle, Simulator};

#[cfg(test)]
mod served;
#[cfg(test)]
pub(crate) use served::served;

/// How long a running bus may take to reach a transaction boundary and
/// take its new settings before the reload goes on without it (they are
/// taken when the transaction under way ends).
const RETUNE_LIMIT: Duration = Duration::from_secs(15);

/// One running bus, as configured now. A reload that changes the bus in
/// place makes a new `Bus` with the new section around the same running
/// parts (handle, thread, simulator, monitor, scope): compare running
/// buses with [`Bus::is`], not by address.
pub struct Bus {
    /// Its configuration.
    pub config: BusConfig,
    /// Its handle.
    pub handle: BusHandle,
    /// The built-in simulator behind it, for `port = "sim"` (it stops when
    /// the last holder of a bus a reload removed lets it go; its drives
    /// are the plant's).
    pub sim: Option<Arc<SimHandle>>,
    monitor: Arc<BusMonitor>,
    scope: Arc<Scope>,
    thread: Arc<Mutex<Option<JoinHandle<()>>>>,
}

impl Bus {
    /// Starts the bus of `bus_config` (and its simulator, serving `drives`),
    /// with its monitor and scope sized by `config`.
    fn start(
        config: &Config,
        bus_config: &BusConfig,
        drives: Option<&SimDrives>,
    ) -> Result<Bus, PlantError> {
        let name = bus_config.name().to_string();
        let sim = match drives {
            Some(drives) if bus_config.is_simulated() => {
                let sim =
                    Simulator::start_on(bus_config.sim_config(), drives).map_err(|source| {
                        PlantError::Simulator {
                            bus: name.clone(),
                            source,
                        }
                    })?;
                info!(bus = %name, pty = %sim.port_path().display(), "built-in simulator running");
                Some(Arc::new(sim))
            }
            _ => None,
        };
        let port = match &sim {
            Some(sim) => sim.port_path().display().to_string(),
            None => bus_config.port.get_ref().clone(),
        };
        let mut settings = bus_config.settings(&port);
        let units: Vec<u8> = bus_config.drives.iter().map(|d| d.unit()).collect();
        let line = settings.master.line;
        let monitor = Arc::new(BusMonitor::new(
            config.monitor.settings(),
            line,
            units.clone(),
        ));
        let scope = Arc::new(Scope::new(config.scope.settings(), line, units));
        settings.observers = Observers {
            wire: vec![monitor.clone(), scope.clone()],
            steering: Some(scope.clone()),
        };
        let (handle, thread) =
            crate::bus::scheduler::spawn(settings).map_err(|source| PlantError::Bus {
                bus: name.clone(),
                source,
            })?;
        Ok(Bus {
            config: bus_config.clone(),
            handle,
            sim,
            monitor,
            scope,
            thread: Arc::new(Mutex::new(Some(thread))),
        })
    }

    /// True when `self` and `other` are the same running bus (the same
    /// thread and port), whatever section each was configured with.
    pub fn is(&self, other: &Bus) -> bool {
        self.handle.is(&other.handle)
    }

    /// The same running bus, configured with `config` (its changes taken
    /// in place).
    fn configured(&self, config: BusConfig) -> Bus {
        Bus {
            config,
            handle: self.handle.clone(),
            sim: self.sim.clone(),
            monitor: self.monitor.clone(),
            scope: self.scope.clone(),
            thread: self.thread.clone(),
        }
    }

    /// The scheduler's settings for `bus_config`, on this bus's port (its
    /// simulator's pty for a simulated bus), watched by its observers.
    fn settings(&self, bus_config: &BusConfig) -> crate::bus::scheduler::BusSettings {
        let port = match &self.sim {
            Some(sim) => sim.port_path().display().to_string(),
            None => bus_config.port.get_ref().clone(),
        };
        let mut settings = bus_config.settings(&port);
        settings.observers = Observers {
            wire: vec![self.monitor.clone(), self.scope.clone()],
            steering: Some(self.scope.clone()),
        };
        settings
    }

    /// Waits (at most 5 s) for the bus's thread after a stop.
    async fn join(&self) {
        let thread = self.thread.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(thread) = thread {
            let name = self.handle.name().to_string();
            let joined = tokio::task::spawn_blocking(move || thread.join());
            match tokio::time::timeout(Duration::from_secs(5), joined).await {
                Ok(Ok(Ok(()))) => {}
                _ => warn!(bus = %name, "bus thread did not stop cleanly"),
            }
        }
    }

    /// Its monitor: the last frames on the wire, the per-attempt counters.
    pub fn monitor(&self) -> &Arc<BusMonitor> {
        &self.monitor
    }

    /// Its scope's capture slot. After arming a capture,
    /// [`wake`](BusHandle::wake) the bus so its polling follows at once.
    pub fn scope(&self) -> &Arc<Scope> {
        &self.scope
    }
}

/// A bus's simulator, held: a reload may take the bus out of the plant,
/// and the simulator stops only when the last holder lets go. Its drives
/// are the plant's: a reopened bus's new simulator serves the same ones.
pub struct SimRef(Arc<SimHandle>);

impl SimRef {
    /// The simulator of `bus`, if it is simulated.
    pub fn of(bus: Arc<Bus>) -> Option<SimRef> {
        bus.sim.clone().map(SimRef)
    }
}

impl std::ops::Deref for SimRef {
    type Target = SimHandle;

    fn deref(&self) -> &SimHandle {
        &self.0
    }
}

/// One configured drive.
#[derive(Debug, Clone, PartialEq)]
pub struct Drive {
    /// Its unique name.
    pub name: String,
    /// Index of its bus in [`Plant::buses`].
    pub bus: usize,
    /// Its unit address.
    pub unit: u8,
    /// Its gearbox ratio.
    pub gear_ratio: f64,
    /// The settings it must hold (`[bus.drive.settings]`), if declared.
    pub declared: Option<Declared>,
}

impl Drive {
    /// The drive `d` configures on the bus at `bus` in the directory.
    fn configured(bus: usize, d: &DriveConfig) -> Self {
        Self {
            name: d.name().to_string(),
            bus,
            unit: d.unit(),
            gear_ratio: d.gear_ratio,
            declared: d.declared(),
        }
    }
}

/// Why the plant could not start.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    /// The simulator of a bus did not start.
    #[error("bus {bus}: cannot start the simulator: {source}")]
    Simulator {
        /// Bus name.
        bus: String,
        /// Cause.
        source: std::io::Error,
    },
    /// The bus thread did not start.
    #[error("bus {bus}: cannot start: {source}")]
    Bus {
        /// Bus name.
        bus: String,
        /// Cause.
        source: std::io::Error,
    },
}

/// Why a drive could not be found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LookupError {
    /// No drive has that name (or unit): said with the closest name and
    /// the list of those that exist.
    #[error("{}", unknown_drive(.name, .known))]
    Unknown {
        /// What was asked for.
        name: String,
        /// The configured drives' names.
        known: Vec<String>,
    },
    /// A unit number was given but several buses are configured.
    #[error("\"{0}\" is a unit number, but several buses are configured: use the drive's name")]
    Ambiguous(String),
}

/// "no drive named \"conveyr\" is configured: did you mean \"conveyor\"? The
/// drives are conveyor, lift, ...": the refusal of every face.
pub fn unknown_drive(name: &str, known: &[String]) -> String {
    let mut text = format!("no drive named \"{name}\" is configured");
    if let Some(close) = crate::suggest::closest(name, known.iter().map(String::as_str)) {
        text.push_str(&format!(": did you mean \"{close}\"?"));
    }
    if known.is_empty() {
        text.push_str(" (no drive is configured)");
    } else {
        text.push_str(&format!(" (the drives are {})", known.join(", ")));
    }
    text
}

/// The plant as it is at one moment: every bus and every drive, each in
/// its slot. A slot's index never changes and is never reused: it is the
/// key of leases, stream subscriptions and Modbus TCP routes, so a drive
/// removed by a reload leaves its slot empty rather than shifting the
/// others, and one added takes a new slot.
pub struct Directory {
    buses: Vec<Option<Arc<Bus>>>,
    drives: Vec<Option<Drive>>,
    /// Counts the changes since start-up (0: as started).
    version: u64,
}

impl Directory {
    /// Every running bus, in slot order.
    pub fn buses(&self) -> impl Iterator<Item = &Arc<Bus>> {
        self.buses.iter().flatten()
    }

    /// Every running bus with its slot index.
    pub fn indexed_buses(&self) -> impl Iterator<Item = (usize, &Arc<Bus>)> {
        self.buses
            .iter()
            .enumerate()
            .filter_map(|(i, b)| Some((i, b.as_ref()?)))
    }

    /// The bus in slot `index`, if it is still configured.
    pub fn bus_at(&self, index: usize) -> Option<&Arc<Bus>> {
        self.buses.get(index)?.as_ref()
    }

    /// The bus with this name.
    pub fn bus(&self, name: &str) -> Option<&Arc<Bus>> {
        self.buses().find(|b| b.handle.name() == name)
    }

    /// Running buses.
    pub fn bus_count(&self) -> usize {
        self.buses().count()
    }

    /// Slots of buses, past ones included (an upper bound of bus indices).
    pub fn bus_slots(&self) -> usize {
        self.buses.len()
    }

    /// Every configured drive, in slot order.
    pub fn drives(&self) -> impl Iterator<Item = &Drive> {
        self.drives.iter().flatten()
    }

    /// Every configured drive with its slot index.
    pub fn indexed_drives(&self) -> impl Iterator<Item = (usize, &Drive)> {
        self.drives
            .iter()
            .enumerate()
            .filter_map(|(i, d)| Some((i, d.as_ref()?)))
    }

    /// The drive in slot `index`, if it is still configured.
    pub fn drive_at(&self, index: usize) -> Option<&Drive> {
        self.drives.get(index)?.as_ref()
    }

    /// Configured drives.
    pub fn drive_count(&self) -> usize {
        self.drives().count()
    }

    /// Slots of drives, past ones included (an upper bound of drive indices).
    pub fn drive_slots(&self) -> usize {
        self.drives.len()
    }

    /// How many times the plant changed since start-up.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// A drive by name or, with a single bus, by unit number.
    pub fn drive(&self, key: &str) -> Result<(&Drive, &BusHandle), LookupError> {
        let found = match self.drives().find(|d| d.name == key) {
            Some(d) => Some(d),
            None => match key.parse::<u8>() {
                Ok(unit) => {
                    if self.bus_count() > 1 {
                        return Err(LookupError::Ambiguous(key.to_string()));
                    }
                    self.drives().find(|d| d.unit == unit)
                }
                Err(_) => None,
            },
        };
        let drive = found.ok_or_else(|| self.unknown(key))?;
        let bus = self.bus_at(drive.bus).ok_or_else(|| self.unknown(key))?;
        Ok((drive, &bus.handle))
    }

    /// The refusal of `key`, with the names of the drives there are.
    fn unknown(&self, key: &str) -> LookupError {
        LookupError::Unknown {
            name: key.to_string(),
            known: self.drives().map(|d| d.name.clone()).collect(),
        }
    }

    /// The handle of a drive's bus (a drive's bus is always running: the
    /// two change together).
    pub fn handle_of(&self, drive: &Drive) -> Option<&BusHandle> {
        self.bus_at(drive.bus).map(|b| &b.handle)
    }

    /// The configured drive at `unit` on bus `bus`.
    pub fn drive_on(&self, bus: usize, unit: u8) -> Option<&Drive> {
        self.drives().find(|d| d.bus == bus && d.unit == unit)
    }
}

/// All buses and drives of the daemon. What it holds changes only by a
/// reload ([`Plant::apply`]); who needs to follow it (a face's list of
/// drives, a per-drive task) [`follow`](Plant::follow)s it.
pub struct Plant {
    directory: watch::Sender<Arc<Directory>>,
    /// One change at a time.
    changing: tokio::sync::Mutex<()>,
    /// The drives of each simulated bus, by bus name: the simulated plant,
    /// kept while the bus is configured, whatever becomes of its port.
    sims: Mutex<BTreeMap<String, SimDrives>>,
}

/// A bus a part follows: its slot, the running bus (its handle), the token
/// that ends what was started for it.
type Running = (usize, BusHandle, CancellationToken);

/// What a reload asks of the plant, bus by bus; every other bus whose
/// section changed takes it in place.
#[derive(Debug, Default)]
pub struct Rebuild {
    /// Buses to stop and start again with their new section, by name.
    pub reopen: Vec<String>,
    /// Of those, buses moved to another port: other motors are behind it,
    /// so their drives take new slots (they were stopped before, as
    /// drives removed are).
    pub moved: Vec<String>,
}

impl Plant {
    /// Starts every bus of `config` (and its simulator).
    pub fn start(config: &Config) -> Result<Plant, PlantError> {
        let mut buses = Vec::new();
        let mut drives = Vec::new();
        let mut sims = BTreeMap::new();
        for (index, bus_config) in config.buses.iter().enumerate() {
            let sim = bus_config.is_simulated().then(|| {
                let drives = SimDrives::new(&bus_config.sim_config());
                sims.insert(bus_config.name().to_string(), drives.clone());
                drives
            });
            buses.push(Some(Arc::new(Bus::start(
                config,
                bus_config,
                sim.as_ref(),
            )?)));
            drives.extend(
                bus_config
                    .drives
                    .iter()
                    .map(|d| Some(Drive::configured(index, d))),
            );
        }
        let (directory, _) = watch::channel(Arc::new(Directory {
            buses,
            drives,
            version: 0,
        }));
        Ok(Plant {
            directory,
            changing: tokio::sync::Mutex::new(()),
            sims: Mutex::new(sims),
        })
    }

    /// The plant as it is now; hold it for the length of one answer, not
    /// forever (a reload may change it).
    pub fn now(&self) -> Arc<Directory> {
        self.directory.borrow().clone()
    }

    /// Follows the plant: the receiver sees each new directory as a reload
    /// applies it (`changed().await`, then `borrow_and_update()`).
    pub fn follow(&self) -> watch::Receiver<Arc<Directory>> {
        self.directory.subscribe()
    }

    /// The running buses now, in slot order (a copy: for a quick look; a
    /// bus's index in the plant is its slot, [`Directory::indexed_buses`]).
    pub fn buses(&self) -> Vec<Arc<Bus>> {
        self.now().buses().cloned().collect()
    }

    /// The configured drives now, in slot order (a copy: for a quick look;
    /// a drive's index is its slot, [`Directory::indexed_drives`]).
    pub fn drives(&self) -> Vec<Drive> {
        self.now().drives().cloned().collect()
    }

    /// Calls `start` for every running bus (its slot, the bus, a token)
    /// and, from a task, for each bus a reload adds or reopens later; a
    /// bus's token is cancelled when it leaves the plant (removed, or
    /// reopened: the new one is another call) or `shutdown` fires. What a
    /// part keeps per bus (a subscription to its events) starts there.
    pub fn for_each_bus(
        self: &Arc<Self>,
        shutdown: &CancellationToken,
        start: impl Fn(usize, &Arc<Bus>, CancellationToken) + Send + 'static,
    ) {
        let mut follow = self.follow();
        let ended = shutdown.clone();
        let shutdown = shutdown.clone();
        let mut running: Vec<Running> = Vec::new();
        let step = move |now: &Directory, running: &mut Vec<Running>| {
            running.retain(|(i, handle, stop)| {
                let same = now.bus_at(*i).is_some_and(|b| b.handle.is(handle));
                if !same {
                    stop.cancel();
                }
                same
            });
            for (index, bus) in now.indexed_buses() {
                if running.iter().any(|(i, _, _)| *i == index) {
                    continue;
                }
                let stop = shutdown.child_token();
                running.push((index, bus.handle.clone(), stop.clone()));
                start(index, bus, stop);
            }
        };
        let now = follow.borrow_and_update().clone();
        step(&now, &mut running);
        if tokio::runtime::Handle::try_current().is_err() {
            return;
        }
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    () = ended.cancelled() => return,
                    changed = follow.changed() => if changed.is_err() { return },
                }
                let now = follow.borrow_and_update().clone();
                step(&now, &mut running);
            }
        });
    }

    /// A drive by name or, with a single bus, by unit number, with its bus.
    pub fn drive(&self, key: &str) -> Result<(Drive, BusHandle), LookupError> {
        self.find(key).map(|(_, drive, bus)| (drive, bus))
    }

    /// A drive by name or, with a single bus, by unit number, with its
    /// slot index and its bus.
    pub fn find(&self, key: &str) -> Result<(usize, Drive, BusHandle), LookupError> {
        let now = self.now();
        let (drive, bus) = now.drive(key)?;
        let index = now
            .drives
            .iter()
            .position(|d| d.as_ref() == Some(drive))
            .ok_or_else(|| now.unknown(key))?;
        Ok((index, drive.clone(), bus.clone()))
    }

    /// The bus with this name.
    pub fn bus(&self, name: &str) -> Option<Arc<Bus>> {
        self.now().bus(name).cloned()
    }

    /// Applies `config` to the running plant: buses gone are stopped,
    /// buses in `rebuild.reopen` stopped and started again (a simulated
    /// one on the same simulated drives), new buses started; every other
    /// bus whose section changed takes it in place, its port kept open
    /// (its simulated drives follow it: one added is wired in). A drive keeps its
    /// slot while its bus and its unit stay the same, whatever its name,
    /// unless its bus is in `rebuild.moved`. Every drive that leaves must
    /// have been stopped before (the control core's `retire`). Buses that
    /// do not change are not touched. Returns the problems: buses that did
    /// not start (their slot stays empty, their drives unconfigured until
    /// the next reload), new settings a bus did not take in time.
    pub async fn apply(&self, config: &Config, rebuild: &Rebuild) -> Vec<String> {
        let _one = self.changing.lock().await;
        let old = self.now();
        let mut buses = old.buses.clone();
        let mut failed = Vec::new();
        // Stop what goes or reopens, first: a reopened port must be free.
        let mut stopping = Vec::new();
        for (slot, bus) in old.buses.iter().enumerate() {
            let Some(bus) = bus else { continue };
            let name = bus.handle.name();
            let gone = !config.buses.iter().any(|b| b.name() == name);
            if gone || rebuild.reopen.iter().any(|r| r == name) {
                stopping.push(bus.clone());
                buses[slot] = None;
            }
        }
        for bus in &stopping {
            bus.handle.stop();
        }
        for bus in stopping {
            bus.join().await;
        }
        // The simulated plant follows the file: a bus removed, or no
        // longer simulated, takes its drives with it.
        lock(&self.sims).retain(|name, _| {
            config
                .buses
                .iter()
                .any(|b| b.name() == name && b.is_simulated())
        });
        // Change in place what stays, start what is new or reopens, each
        // in its slot.
        for bus_config in &config.buses {
            let name = bus_config.name();
            let slot = old
                .buses
                .iter()
                .position(|b| b.as_ref().is_some_and(|b| b.handle.name() == name));
            if let Some(s) = slot
                && let Some(running) = buses[s].clone()
            {
                if running.config != *bus_config {
                    if let Err(problem) = self.retune(&running, bus_config).await {
                        warn!("{problem}");
                        failed.push(problem);
                    }
                    buses[s] = Some(Arc::new(running.configured(bus_config.clone())));
                }
                continue;
            }
            let sim = bus_config.is_simulated().then(|| {
                lock(&self.sims)
                    .entry(name.to_string())
                    .or_insert_with(|| SimDrives::new(&bus_config.sim_config()))
                    .clone()
            });
            let bus = match Bus::start(config, bus_config, sim.as_ref()) {
                Ok(bus) => Some(Arc::new(bus)),
                Err(e) => {
                    warn!("{e}");
                    failed.push(e.to_string());
                    None
                }
            };
            match slot {
                Some(s) => buses[s] = bus,
                None => buses.push(bus),
            }
        }
        let drives = slots(&old, &buses, config, rebuild);
        let version = old.version + 1;
        self.directory.send_replace(Arc::new(Directory {
            buses,
            drives,
            version,
        }));
        failed
    }

    /// Hands `new` to the running `bus` and waits until its scheduler took
    /// it (at its next transaction boundary); a simulated bus's drives
    /// follow it first, so that a drive added is on the line for its first
    /// poll.
    async fn retune(&self, bus: &Bus, new: &BusConfig) -> Result<(), String> {
        let name = new.name();
        if bus.sim.is_some()
            && let Some(sim) = lock(&self.sims).get(name)
        {
            sim.follow(&new.sim_config());
        }
        let units: Vec<u8> = new.drives.iter().map(|d| d.unit()).collect();
        bus.monitor.set_units(units.clone());
        bus.scope.set_units(units);
        let taken = bus.handle.retune(bus.settings(new));
        match tokio::time::timeout(RETUNE_LIMIT, taken).await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(_)) => Err(format!(
                "bus {name}: its new settings were not taken: the bus has stopped"
            )),
            Err(_) => Err(format!(
                "bus {name}: its new settings wait for the transaction under way, longer than {} s",
                RETUNE_LIMIT.as_secs()
            )),
        }
    }

    /// Takes no new work on any bus (the first step of the shutdown stop,
    /// `crate::control::shutdown`).
    pub fn close(&self) {
        for bus in self.now().buses() {
            bus.handle.close();
        }
    }

    /// Stops every bus once it finished the frame on the wire, and waits
    /// (at most 5 s a bus) for its thread.
    pub async fn stop(&self) {
        let _one = self.changing.lock().await;
        let now = self.now();
        for bus in now.buses() {
            bus.handle.stop();
        }
        for bus in now.buses() {
            bus.join().await;
        }
    }
}

/// The drive slots of `config` on `buses` after a reload from `old`: a
/// drive keeps its slot while its bus (by name) and its unit stay the same,
/// whatever its name, unless its bus moved to another port
/// (`rebuild.moved`); a drive new to the plant takes a new slot; a slot
/// left is never reused.
fn slots(
    old: &Directory,
    buses: &[Option<Arc<Bus>>],
    config: &Config,
    rebuild: &Rebuild,
) -> Vec<Option<Drive>> {
    let slot_of_bus = |name: &str| {
        buses
            .iter()
            .position(|b| b.as_ref().is_some_and(|b| b.handle.name() == name))
    };
    let mut drives: Vec<Option<Drive>> = vec![None; old.drives.len()];
    for bus_config in &config.buses {
        let Some(bus) = slot_of_bus(bus_config.name()) else {
            continue;
        };
        let moved = rebuild.moved.iter().any(|m| m == bus_config.name());
        for d in &bus_config.drives {
            let drive = Drive::configured(bus, d);
            let kept = old
                .drives
                .iter()
                .position(|o| {
                    o.as_ref()
                        .is_some_and(|o| o.bus == bus && o.unit == drive.unit)
                })
                .filter(|_| !moved);
            match kept {
                Some(i) => drives[i] = Some(drive),
                None => drives.push(Some(drive)),
            }
        }
    }
    drives
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::unknown_drive;

    #[test]
    fn an_unknown_drive_is_refused_with_the_closest_name_and_the_list() {
        let known = ["conveyor", "lift", "turntable", "feeder"].map(String::from);
        assert_eq!(
            unknown_drive("conveyr", &known),
            "no drive named \"conveyr\" is configured: did you mean \"conveyor\"? \
             (the drives are conveyor, lift, turntable, feeder)"
        );
        assert_eq!(
            unknown_drive("press", &known),
            "no drive named \"press\" is configured (the drives are conveyor, lift, turntable, feeder)"
        );
        assert_eq!(
            unknown_drive("press", &[]),
            "no drive named \"press\" is configured (no drive is configured)"
        );
    }
}
