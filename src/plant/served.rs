//! A plant whose buses the test serves: no port, simulator or scheduler
//! (the model of the control core, `control/model/`).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use tokio::sync::watch;

use super::{Bus, BusHandle, BusMonitor, Config, Directory, Drive, Plant, Scope};

/// A plant of `config`'s drives whose buses have no port, simulator or
/// scheduler: each bus's handle is given, its jobs taken off its queue and
/// answered by the test.
pub(crate) fn served(config: &Config, handles: Vec<BusHandle>) -> Plant {
    let mut buses = Vec::new();
    let mut drives = Vec::new();
    for (index, (bus_config, handle)) in config.buses.iter().zip(handles).enumerate() {
        let units: Vec<u8> = bus_config.drives.iter().map(|d| d.unit()).collect();
        let line = handle.line();
        buses.push(Some(Arc::new(Bus {
            config: bus_config.clone(),
            handle,
            sim: None,
            monitor: Arc::new(BusMonitor::new(
                config.monitor.settings(),
                line,
                units.clone(),
            )),
            scope: Arc::new(Scope::new(config.scope.settings(), line, units)),
            thread: Arc::new(Mutex::new(None)),
        })));
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
    Plant {
        directory,
        changing: tokio::sync::Mutex::new(()),
        sims: Mutex::new(BTreeMap::new()),
    }
}
