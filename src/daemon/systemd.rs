//! What the daemon tells systemd (`Type=notify`): ready, its status line,
//! the watchdog's pings, stopping. Outside systemd every call does nothing.

use std::net::SocketAddr;

use tracing::warn;

use crate::plant::Plant;

/// Sends `states` to systemd; a failure is logged, never fatal.
pub(crate) fn notify(states: &[sd_notify::NotifyState<'_>]) {
    if let Err(e) = sd_notify::notify(states) {
        warn!("cannot notify systemd: {e}");
    }
}

/// The line `systemctl status` shows: what is served and where the API
/// is, or what to do first on a package as shipped.
pub(crate) fn status_line(plant: &Plant, http: Option<SocketAddr>) -> String {
    let http = http.map_or_else(|| "off".to_string(), |a| a.to_string());
    let now = plant.now();
    if now.bus_count() == 0 {
        format!("waiting to be configured: no bus (run drivegate probe); HTTP on {http}")
    } else {
        format!(
            "serving {} drive(s) on {} bus(es); HTTP on {http}",
            now.drive_count(),
            now.bus_count(),
        )
    }
}

/// Updates the status line, after a reload.
pub(crate) fn status(plant: &Plant, http: Option<SocketAddr>) {
    notify(&[sd_notify::NotifyState::Status(&status_line(plant, http))]);
}
