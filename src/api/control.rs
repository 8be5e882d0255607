//! The API's side of the control core: the REST routes and the stream's
//! commands hand their writes to [`crate::control`] and render what comes
//! back as a reply or a problem. No rule lives here: the core decides,
//! this module only words the decision for HTTP (where an override is
//! `"force": true`, where a confirmation is `only_drive_on_bus`).

use super::auth::{Caller, forbidden};
use super::problem::{BusContext, Kind, Problem};
use super::state::{ApiState, Target};
use crate::bus::BusError;
use crate::bus::cache::Link;
use crate::control::{ControlRequest, Failure, Operation, Outcome, Refusal, Rule};
use crate::drive::{DriveReply, RangeError, Status};

pub use crate::control::written::{Written, describe, written};

/// True when the drive's polls have stopped getting answers.
pub fn is_offline(target: &Target) -> bool {
    target
        .bus
        .drive(target.drive.unit)
        .is_some_and(|s| s.link == Link::Offline)
}

/// Writes `request` to the drive through the core for `caller`, and
/// returns once the drive confirmed it (or the problem saying why not).
pub async fn send(
    state: &ApiState,
    caller: &Caller,
    target: Target,
    request: ControlRequest,
) -> Result<DriveReply, Problem> {
    let offline = is_offline(&target);
    let setpoint = request.write.meaning().setpoint.is_some();
    match state.control.write(caller, target.control(), request).await {
        Ok(Outcome::Confirmed { typed, .. }) => Ok(typed.unwrap_or(DriveReply::Confirmed)),
        Ok(Outcome::Broadcast) => Ok(DriveReply::None),
        Err(failure) => Err(problem(
            caller,
            &failure,
            BusContext {
                drive: Some(&target.drive.name),
                offline,
                setpoint,
            },
        )),
    }
}

/// The problem document of a failed write.
pub fn problem(caller: &Caller, failure: &Failure, ctx: BusContext<'_>) -> Problem {
    let p = match failure {
        Failure::Refused(refusal) => match &refusal.rule {
            Rule::Role { needed, .. } => forbidden(caller, *needed),
            Rule::Moving { .. } => Problem::new(
                Kind::DriveMoving,
                format!("{}, or send \"force\": true", refusal.detail),
            ),
            Rule::NotActive => Problem::new(Kind::DriveNotActive, refusal.detail.clone()),
            Rule::SharedBusAddress => Problem::new(
                Kind::ConfirmationRequired,
                format!("{}: send \"only_drive_on_bus\": true", refusal.detail),
            ),
            Rule::LeaseLength { .. } => lease_problem(refusal),
        },
        other => match other.bus_error() {
            Some(e) => Problem::bus(&e, ctx),
            None => Problem::new(Kind::Internal, other.to_string()),
        },
    };
    match ctx.drive {
        Some(drive) => p.for_drive(drive),
        None => p,
    }
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

/// The problem of a lease length the core refused: out of range, with
/// the valid range.
pub fn lease_problem(refusal: &Refusal) -> Problem {
    match refusal.rule {
        Rule::LeaseLength { asked, min, max } => Problem::range(&RangeError {
            quantity: "lease",
            value: asked as f64,
            min: min as f64,
            max: max as f64,
            unit: "ms",
        }),
        _ => Problem::new(Kind::Internal, refusal.detail.clone()),
    }
}

/// Reads the drive's status now (not from the poll cache).
pub async fn read_status(
    state: &ApiState,
    caller: &Caller,
    target: Target,
) -> Result<Status, Problem> {
    let offline = is_offline(&target);
    state
        .control
        .read_status(caller, target.control())
        .await
        .map_err(|e: BusError| {
            Problem::bus(
                &e,
                BusContext {
                    drive: Some(&target.drive.name),
                    offline,
                    setpoint: false,
                },
            )
        })
}
