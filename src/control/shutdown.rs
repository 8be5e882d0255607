//! The shutdown stop: when the daemon stops, `[safety] on_shutdown` on
//! every drive that moves, each write audited like any other, then the
//! buses finish their frame on the wire and stop. A rule for the motor, so
//! it is the core's, not the plant's.

use std::time::Duration;

use tracing::{info, warn};

use super::audit;
use super::caller::Face;
use super::events::WriteEnd;
use crate::bus::Origin;
use crate::control::stop_action::{self, StopAction, StopOutcome};
use crate::plant::Plant;

/// Stops the plant: no new work, `action` on every moving drive (bounded
/// to 5 s), then the buses finish their frame on the wire and stop.
pub async fn shutdown(plant: &Plant, action: StopAction) {
    plant.close();
    // Every drive is asked, not only those the polled copy shows moving:
    // the copy may be older than the last command.
    let now = plant.now();
    let stops = now.drives().filter_map(|drive| {
        let handle = now.handle_of(drive)?.clone();
        let (name, unit) = (drive.name.clone(), drive.unit);
        Some(async move {
            match stop_action::stop_drive(&handle, unit, action, true, Origin::Shutdown).await {
                Ok(outcome @ StopOutcome { sent: Some(_), .. }) => {
                    // One line per write: with the mode unknown,
                    // zero-speed is two (speed and torque setpoint 0).
                    for request in outcome.requests() {
                        audit::write(
                            Face::Internal.name(),
                            "shutdown",
                            handle.name(),
                            unit,
                            request.name(),
                            &WriteEnd::Confirmed,
                        );
                    }
                    info!(drive = %name, action = action.name(), "stopped at shutdown")
                }
                Ok(_) => {}
                Err(e) => {
                    audit::write(
                        Face::Internal.name(),
                        "shutdown",
                        handle.name(),
                        unit,
                        action.name(),
                        &WriteEnd::bus_error(e.clone()),
                    );
                    warn!(drive = %name, action = action.name(), "safe stop failed: {e}")
                }
            }
        })
    });
    let all = futures_util::future::join_all(stops);
    if tokio::time::timeout(Duration::from_secs(5), all)
        .await
        .is_err()
    {
        warn!("safe-stop actions did not finish within 5 s");
    }
    plant.stop().await;
}
