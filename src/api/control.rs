//! The API's side of the control core: the REST routes and the stream's
//! commands hand their writes to [`crate::control`] through
//! [`crate::ops::writes`], which words what comes back as a reply or a
//! problem the same for every face. No rule lives here.

use super::auth::{Caller, forbidden};
use super::problem::{Kind, Problem};
use super::state::{ApiState, Target};
use crate::control::{ControlRequest, Operation, Rule};
use crate::drive::{DriveReply, Status};

pub use crate::control::written::{Written, describe, written};
pub use crate::ops::writes::{is_offline, lease_problem, problem};

/// Writes `request` to the drive through the core for `caller`, and
/// returns once the drive confirmed it (or the problem saying why not).
pub async fn send(
    state: &ApiState,
    caller: &Caller,
    target: Target,
    request: ControlRequest,
) -> Result<DriveReply, Problem> {
    crate::ops::writes::send(&state.control, caller, target, request).await
}

/// Refuses `caller` (403) unless the core's policy lets its role do
/// `operation` (what is not a write: scans, scope captures).
pub fn authorize(state: &ApiState, caller: &Caller, operation: Operation) -> Result<(), Problem> {
    state
        .control
        .authorize(caller, operation)
        .map_err(|refusal| match refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, needed),
            _ => Problem::new(Kind::Internal, refusal.detail),
        })
}

/// Reads the drive's status now (not from the poll cache).
pub async fn read_status(
    state: &ApiState,
    caller: &Caller,
    target: Target,
) -> Result<Status, Problem> {
    crate::ops::writes::read_status(&state.control, caller, target).await
}
