//! Setpoints (manual 1.4 to 1.6) in engineering units, and the leases that
//! may come with them: renew, release.

use axum::Json;
use axum::extract::State;
use serde::Deserialize;
use utoipa::ToSchema;

use super::extract::{JsonBody, OptionalJsonBody, PathParams};
use super::problem_response::{Kind, Problem};
use super::problem_response::{LeaseProblems, WriteProblems};
use super::state::ApiState;
use crate::control::{Caller, LeaseError, Refusal, Rule};
use crate::faces_shared::command_messages::lease_length;
pub use crate::faces_shared::command_messages::{LeaseInfo, SetpointBody, SetpointReply};
use crate::faces_shared::integers;
use crate::faces_shared::writes::{self, forbidden};

/// Sends a setpoint to drive `key` for `caller`; a lease taken over the
/// stream ends with its session too.
pub async fn apply(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &SetpointBody,
) -> Result<SetpointReply, Problem> {
    let target = state.target(key)?;
    crate::faces_shared::command_messages::apply(
        &state.control,
        caller,
        &target,
        body,
        state.config.lease_default,
    )
    .await
}

/// The problem for a lease that cannot be renewed or released.
fn lease_problem(caller: &Caller, drive: &str, error: LeaseError, hint: &str) -> Problem {
    match error {
        LeaseError::Refused(Refusal {
            rule: Rule::Role { needed, .. },
            ..
        }) => forbidden(caller, needed),
        LeaseError::Refused(refusal) => writes::lease_problem(&refusal),
        LeaseError::NoLease(why) => {
            Problem::new(Kind::NoLease, format!("{}; {hint}", why.0)).for_drive(drive)
        }
    }
}

/// Sends a speed, position or torque setpoint (operator); it returns once
/// the drive echoed it.
///
/// With `lease_ms` the motor is stopped (`[safety] on_lease_expiry`) unless
/// the setpoint is repeated or `POST .../lease/renew` is called within that
/// time. The drive must be active (409 `drive-not-active` otherwise).
#[utoipa::path(
    put,
    path = "/api/v1/drives/{drive}/setpoint",
    tag = "setpoints",
    security(("bearer" = ["operator"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = SetpointBody, examples(
        ("speed" = (value = json!({"speed_rpm": 100}))),
        ("position with a lease" = (value = json!({"position_deg": 90.0, "lease_ms": 500}))),
        ("torque" = (value = json!({"torque_a": 1.0}))),
    )),
    responses(
        (status = 200, description = "The drive confirmed the setpoint", body = SetpointReply),
        WriteProblems,
    )
)]
pub async fn put_setpoint(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    JsonBody(body): JsonBody<SetpointBody>,
) -> Result<Json<SetpointReply>, Problem> {
    apply(&state, &caller, &key, &body).await.map(Json)
}

/// `POST .../lease/renew` body (optional).
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RenewBody {
    /// A new lease length, ms (default: the current one), between
    /// `[safety] lease_min_ms` and `lease_max_ms`.
    #[serde(default, deserialize_with = "integers::optional")]
    pub lease_ms: Option<i64>,
}

/// Renews drive `key`'s lease.
pub async fn renew(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &RenewBody,
) -> Result<LeaseInfo, Problem> {
    let target = state.target(key)?;
    let length = body.lease_ms.map(lease_length);
    state
        .control
        .renew(caller, target.index, length)
        .map(|view| LeaseInfo::new(&target.drive.name, &view))
        .map_err(|e| {
            lease_problem(
                caller,
                &target.drive.name,
                e,
                "to take a lease, send the setpoint again with lease_ms",
            )
        })
}

/// Pushes the lease's deadline ahead by its length (operator).
#[utoipa::path(
    post,
    path = "/api/v1/drives/{drive}/lease/renew",
    tag = "setpoints",
    security(("bearer" = ["operator"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    request_body(content = Option<RenewBody>, description = "Optional: a new lease length"),
    responses(
        (status = 200, description = "The lease, renewed", body = LeaseInfo),
        LeaseProblems,
    )
)]
pub async fn post_renew(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
    OptionalJsonBody(body): OptionalJsonBody<RenewBody>,
) -> Result<Json<LeaseInfo>, Problem> {
    renew(&state, &caller, &key, &body.unwrap_or_default())
        .await
        .map(Json)
}

/// Ends drive `key`'s lease without stopping the motor.
pub async fn release(state: &ApiState, caller: &Caller, key: &str) -> Result<LeaseInfo, Problem> {
    let target = state.target(key)?;
    let view = state
        .control
        .release(caller, target.index)
        .map_err(|e| lease_problem(caller, &target.drive.name, e, "there is nothing to release"))?;
    Ok(LeaseInfo::new(&target.drive.name, &view))
}

/// Ends the lease without stopping the motor (operator): the motor keeps
/// its setpoint, unguarded.
#[utoipa::path(
    delete,
    path = "/api/v1/drives/{drive}/lease",
    tag = "setpoints",
    security(("bearer" = ["operator"])),
    params(("drive" = String, Path, description = "Drive name, or its unit number on a single bus")),
    responses(
        (status = 200, description = "The lease that ended", body = LeaseInfo),
        LeaseProblems,
    )
)]
pub async fn delete_lease(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(key): PathParams<String>,
) -> Result<Json<LeaseInfo>, Problem> {
    release(&state, &caller, &key).await.map(Json)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::DriveRequest;

    #[test]
    fn exactly_one_setpoint() {
        let both = SetpointBody {
            speed_rpm: Some(1.0),
            torque_a: Some(1.0),
            ..SetpointBody::default()
        };
        let p = both.request().unwrap_err();
        assert_eq!(p.kind(), Kind::InvalidRequest);
        assert!(
            p.detail.contains("found speed_rpm and torque_a"),
            "{}",
            p.detail
        );
        let none = SetpointBody::default().request().unwrap_err();
        assert!(none.detail.contains("found none"));
        let far = SetpointBody {
            position_deg: Some(200.0),
            ..SetpointBody::default()
        };
        let p = far.request().unwrap_err();
        assert_eq!(p.kind(), Kind::OutOfRange);
        assert_eq!(p.valid_range.clone().unwrap().max, 180.0);
        let counts = SetpointBody {
            torque_counts: Some(-128),
            ..SetpointBody::default()
        };
        assert_eq!(
            counts.request().unwrap(),
            DriveRequest::Torque { counts: -128 }
        );
    }
}
