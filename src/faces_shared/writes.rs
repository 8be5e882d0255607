//! The faces' side of the control core, worded once: a write handed to
//! [`crate::control`] for a caller, and what it decided as a reply or a
//! problem. No rule lives here: the core decides, this module only words
//! the decision (where an override is `"force": true`, where a
//! confirmation is `only_drive_on_bus`), the same for every face.

use super::problem::{BusContext, Kind, Problem};
use super::target::Target;
use crate::bus::BusError;
use crate::bus::cache::Link;
use crate::control::{
    Caller, Control, ControlRequest, Face, Failure, Outcome, Refusal, Role, Rule,
};
use crate::drive::{DriveReply, RangeError, Status};

/// True when the drive's polls have stopped getting answers.
pub(crate) fn is_offline(target: &Target) -> bool {
    target
        .bus
        .drive(target.drive.unit)
        .is_some_and(|s| s.link == Link::Offline)
}

/// Writes `request` to the drive through the core for `caller`, and
/// returns once the drive confirmed it (or the problem saying why not).
pub(crate) async fn send(
    control: &Control,
    caller: &Caller,
    target: Target,
    request: ControlRequest,
) -> Result<DriveReply, Problem> {
    let offline = is_offline(&target);
    let setpoint = request.write.meaning().setpoint.is_some();
    match control.write(caller, target.control(), request).await {
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

/// Audits, through the core, a write `caller` asked of `target` that its
/// face refused before it became a request: `what` was asked, `why` it
/// cannot be (a value out of the drive's range, a mode it does not have).
pub(crate) fn refused(
    control: &Control,
    caller: &Caller,
    target: &Target,
    what: String,
    why: &str,
) {
    control.refused(caller, target.control(), what, format!("refused: {why}"));
}

/// The 403 for `caller`, whose role is not `needed`: what it has, in the
/// terms of its face (a token's name, or MQTT's `[mqtt] commands`).
pub(crate) fn forbidden(caller: &Caller, needed: Role) -> Problem {
    let detail = match caller.face {
        Face::Mqtt => format!(
            "this needs the {} role; commands over MQTT have the {} role ([mqtt] commands)",
            needed.name(),
            caller.role.name()
        ),
        _ => format!(
            "this needs the {} role; the token \"{}\" has the {} role",
            needed.name(),
            caller.who,
            caller.role.name()
        ),
    };
    Problem::new(Kind::Forbidden, detail)
}

/// The problem document of a failed write.
pub(crate) fn problem(caller: &Caller, failure: &Failure, ctx: BusContext<'_>) -> Problem {
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
            // Only a passthrough face sends what the core cannot decode.
            Rule::NotDecoded => Problem::new(Kind::InvalidRequest, refusal.detail.clone()),
            Rule::NotLive => Problem::new(Kind::NotLive, refusal.detail.clone()),
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

/// The problem of a lease length the core refused: out of range, with
/// the valid range.
pub(crate) fn lease_problem(refusal: &Refusal) -> Problem {
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
pub(crate) async fn read_status(
    control: &Control,
    caller: &Caller,
    target: Target,
) -> Result<Status, Problem> {
    let offline = is_offline(&target);
    control
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
