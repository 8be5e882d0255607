//! Working the bus through its handle, as every face does: for tests that
//! need the wire in a given state before a face acts.

use std::time::Duration;

use drivegate::bus::BusHandle;
use drivegate::bus::handle::JobOptions;
use drivegate::bus::job::JobResult;
use drivegate::bus::{Priority, SourceId};
use drivegate::drive::DriveRequest;
use tokio::sync::oneshot;

use crate::support::eventually;

/// Holds the wire with an emergency read of unit 30, which nobody answers,
/// and returns once it is on the wire: whatever is queued meanwhile waits
/// behind it for one response timeout and guard time of the bus. The
/// receiver yields the read's (failed) result once the wire is free again.
pub async fn hold_the_wire(bus: &BusHandle) -> oneshot::Receiver<JobResult> {
    let options = JobOptions {
        priority: Priority::Emergency,
        source: SourceId::new_unique(),
        queue_timeout: None,
        max_attempts: Some(1),
        origin: Default::default(),
    };
    let pdu = DriveRequest::ReadStatus.pdu().unwrap();
    let blocker = bus.submit(30, pdu, options).unwrap();
    eventually(Duration::from_secs(10), "the blocker on the wire", || {
        (bus.queue_depths()[0] == 0).then_some(())
    })
    .await;
    blocker
}
