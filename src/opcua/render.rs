//! The plant in the address space: one task that adds and removes the
//! drives and buses a reload adds and removes; each drive's values put in
//! at every poll (its status event, with the poll's source timestamp, as
//! one of the bus's followers), at every change of its freshness (the
//! core's news: a value that turns stale is not announced by any poll)
//! and, every second, each bus's state and counters. Subscriptions are told at once; they sample
//! at the poll rate.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use opcua::server::SubscriptionCache;
use opcua::types::{DataValue, NodeId, StatusCode, Variant};
use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;

use super::address::{DriveNodes, Nodes, Space, plant_of, set_values};
use super::spec::{self, BusVariable, Source, VARIABLES};
use super::values::{data_value, drive_value};
use crate::bus::freshness::Freshness;
use crate::bus::handle::PortState;
use crate::bus::stats::Outcome;
use crate::bus::{BusEvent, BusFollower};
use crate::control::{Control, ControlEvent};
use crate::metrics::Metrics;
use crate::plant::Directory;

/// What the task works with.
pub struct Render {
    /// The namespace.
    pub nodes: Nodes,
    /// The address space.
    pub space: Space,
    /// The server's subscriptions.
    pub subscriptions: Arc<SubscriptionCache>,
    /// The core (its plant and its news).
    pub control: Control,
    /// The metrics (values published, bus utilisation).
    pub metrics: Arc<Metrics>,
}

/// What is in the address space now.
#[derive(Default)]
pub struct Shown {
    drives: BTreeSet<(String, u64)>,
    buses: BTreeSet<String>,
}

impl Render {
    /// Puts the plant as it is into the address space (before the server
    /// takes its first client).
    pub fn begin(&self) -> Shown {
        let mut shown = Shown::default();
        let directory = self.control.plant().now();
        self.follow_plant(&directory, &mut shown);
        self.all_values(&directory);
        shown
    }

    /// Follows the plant from what [`begin`](Self::begin) showed, until
    /// `stop`.
    pub async fn run(self: Arc<Self>, mut shown: Shown, stop: CancellationToken) {
        let plant = self.control.plant().clone();
        let mut follow = plant.follow();
        let directory = follow.borrow_and_update().clone();
        self.follow_plant(&directory, &mut shown);
        let me = self.clone();
        plant.for_each_bus(&stop, move |slot, bus, bus_stop| {
            let follower = Follower {
                render: me.clone(),
                slot,
            };
            bus.handle.follow(Arc::new(follower), bus_stop);
        });
        let mut news = self.control.subscribe();
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = stop.cancelled() => return,
                changed = follow.changed() => {
                    if changed.is_err() {
                        return;
                    }
                    let directory = follow.borrow_and_update().clone();
                    self.follow_plant(&directory, &mut shown);
                    self.all_values(&directory);
                }
                n = news.recv() => match n {
                    Ok(p) => {
                        if let ControlEvent::Freshness(news) = &*p.event {
                            self.drive_values(&plant.now(), news.drive);
                        }
                    }
                    Err(RecvError::Lagged(_)) => self.all_values(&plant.now()),
                    Err(RecvError::Closed) => return,
                },
                _ = tick.tick() => self.bus_values(&plant.now()),
            }
        }
    }

    /// Adds what `directory` has that is not shown, removes what it lost,
    /// and gives a drive whose poll rate changed its new sampling interval.
    fn follow_plant(&self, directory: &Directory, shown: &mut Shown) {
        let (drives, buses) = plant_of(directory);
        if drives == shown.drives && buses == shown.buses {
            return;
        }
        let mut space = self.space.write();
        // A drive shown under the same name at another poll rate keeps its
        // nodes (and the monitored items on them).
        let named = |set: &BTreeSet<(String, u64)>, name: &str| {
            set.iter().find(|(n, _)| n == name).map(|(_, p)| *p)
        };
        for (name, period) in drives.difference(&shown.drives) {
            if named(&shown.drives, name).is_some() {
                let period = Duration::from_micros(*period);
                self.nodes.set_period(&mut space, name, period);
            }
        }
        for (name, _) in shown.drives.difference(&drives) {
            if named(&drives, name).is_none() {
                self.nodes.remove_drive(&mut space, name);
            }
        }
        for bus in shown.buses.difference(&buses) {
            self.nodes.remove_bus(&mut space, bus);
        }
        for bus in buses.difference(&shown.buses) {
            self.nodes.add_bus(&mut space, bus);
        }
        for (name, period) in drives.difference(&shown.drives) {
            if named(&shown.drives, name).is_some() {
                continue;
            }
            let drive = DriveNodes {
                name,
                period: Duration::from_micros(*period),
            };
            self.nodes.add_drive(&mut space, &drive);
        }
        shown.drives = drives;
        shown.buses = buses;
    }

    fn push(&self, values: Vec<(NodeId, DataValue)>) {
        if values.is_empty() {
            return;
        }
        let n = set_values(&self.space, &self.subscriptions, values);
        self.metrics.opcua().values_published(n);
    }

    fn bus_event(&self, slot: usize, event: &BusEvent) {
        let directory = self.control.plant().now();
        match event {
            BusEvent::Status { unit, .. }
            | BusEvent::Online { unit, .. }
            | BusEvent::Offline { unit, .. } => {
                if let Some((index, _)) = directory
                    .indexed_drives()
                    .find(|(_, d)| d.bus == slot && d.unit == *unit)
                {
                    self.drive_values(&directory, index);
                }
            }
            BusEvent::BusUp { .. } | BusEvent::BusDown { .. } => self.bus_values(&directory),
        }
    }

    /// Every drive's values, and every bus's.
    fn all_values(&self, directory: &Directory) {
        let mut values = Vec::new();
        for (index, _) in directory.indexed_drives() {
            values.extend(self.values_of(directory, index));
        }
        self.push(values);
        self.bus_values(directory);
    }

    fn drive_values(&self, directory: &Directory, drive: usize) {
        self.push(self.values_of(directory, drive));
    }

    /// The status and `Online` values of drive `drive` now.
    fn values_of(&self, directory: &Directory, drive: usize) -> Vec<(NodeId, DataValue)> {
        let Some(d) = directory.drive_at(drive) else {
            return Vec::new();
        };
        let Some(handle) = directory.handle_of(d) else {
            return Vec::new();
        };
        let Some(verdict) = handle.freshness(d.unit) else {
            return Vec::new();
        };
        let snapshot = handle.drive(d.unit);
        let last = snapshot
            .as_ref()
            .and_then(|s| s.status.as_ref().zip(s.seen_at));
        let now = SystemTime::now();
        VARIABLES
            .iter()
            .filter(|v| matches!(v.source, Source::Status(_) | Source::Online))
            .filter_map(|v| {
                let value = drive_value(v, last, &verdict, now)?;
                Some((self.nodes.id(&spec::variable_path(&d.name, v)), value))
            })
            .collect()
    }

    /// Every bus's state and counters.
    fn bus_values(&self, directory: &Directory) {
        let now = SystemTime::now();
        let mut values = Vec::new();
        for (slot, bus) in directory.indexed_buses() {
            let handle = &bus.handle;
            let stats = handle.stats();
            let count = |o: Outcome| -> u64 {
                stats
                    .transactions
                    .iter()
                    .filter(|((_, outcome), _)| *outcome == o)
                    .map(|(_, n)| *n)
                    .sum()
            };
            let (state, reason) = match handle.port_state() {
                PortState::Opening => ("opening", String::new()),
                PortState::Up { .. } => ("up", String::new()),
                PortState::Down { reason, .. } => ("down", reason),
            };
            let live = handle
                .freshness_all(std::time::Instant::now())
                .iter()
                .filter(|(_, v)| v.freshness == Freshness::Live)
                .count();
            let u32_of = |n: u64| Variant::UInt32(u32::try_from(n).unwrap_or(u32::MAX));
            for v in BusVariable::ALL {
                let value = match v {
                    BusVariable::State => Variant::from(state),
                    BusVariable::Reason => Variant::from(reason.as_str()),
                    BusVariable::Utilisation => match self.metrics.bus_utilisation(slot) {
                        Some(r) => Variant::Double(r * 100.0),
                        None => continue,
                    },
                    BusVariable::Timeouts => u32_of(count(Outcome::Timeout)),
                    BusVariable::CrcErrors => u32_of(count(Outcome::CrcError)),
                    BusVariable::BadReplies => u32_of(count(Outcome::BadReply)),
                    BusVariable::Retries => u32_of(stats.retries),
                    BusVariable::Reopens => u32_of(stats.reopens),
                    BusVariable::DrivesOnline => u32_of(live as u64),
                };
                let path = format!("{}/{}", spec::bus_path(handle.name()), v.name());
                values.push((
                    self.nodes.id(&path),
                    data_value(value, StatusCode::Good, now),
                ));
            }
        }
        self.push(values);
    }
}

/// The address space as a bus's follower: a drive's values put in at each
/// of its statuses and links, the bus's at its port's changes, in the task
/// every follower of the bus shares.
struct Follower {
    render: Arc<Render>,
    slot: usize,
}

impl BusFollower for Follower {
    fn event(&self, event: &BusEvent) {
        self.render.bus_event(self.slot, event);
    }

    // A lost status is made up for by the next one.
}
