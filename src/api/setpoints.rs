//! Setpoints (manual 1.4 to 1.6) in engineering units, and the leases that
//! may come with them: renew, release.

use std::time::Duration;

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::auth::Caller;
use super::control::{self, Written};
use super::extract::{JsonBody, OptionalJsonBody, PathParams};
use super::integers;
use super::leases::LeaseInfo;
use super::openapi::{LeaseProblems, WriteProblems};
use super::problem::{Kind, Problem};
use super::roles::Role;
use super::state::{ApiState, Target};
use crate::drive::{DriveRequest, Mode, RangeError, units};

/// `PUT .../setpoint` body: exactly one setpoint, and optionally a lease.
/// Its OpenAPI schema is in [`super::body_schemas`].
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetpointBody {
    /// Speed at the gearbox output, rpm (-2048..2047, rounded to 1 rpm).
    pub speed_rpm: Option<f64>,
    /// Position at the gearbox output, degrees (-180..180, rounded to 0.01).
    pub position_deg: Option<f64>,
    /// Motor current, amps (-16..15.99, rounded to 1/128 A).
    pub torque_a: Option<f64>,
    /// Motor current, raw counts (-2048..2047; 1 A = 128).
    #[serde(default, deserialize_with = "integers::optional")]
    pub torque_counts: Option<i64>,
    /// Stop the motor (`[safety] on_lease_expiry`) unless the setpoint is
    /// repeated or the lease renewed within this many ms.
    #[serde(default, deserialize_with = "integers::optional")]
    pub lease_ms: Option<i64>,
}

impl SetpointBody {
    /// The drive request, with values checked against the manual's ranges.
    pub fn request(&self) -> Result<DriveRequest, Problem> {
        let given: Vec<&str> = [
            self.speed_rpm.map(|_| "speed_rpm"),
            self.position_deg.map(|_| "position_deg"),
            self.torque_a.map(|_| "torque_a"),
            self.torque_counts.map(|_| "torque_counts"),
        ]
        .into_iter()
        .flatten()
        .collect();
        if given.len() != 1 {
            return Err(Problem::invalid(format!(
                "give exactly one of speed_rpm, position_deg, torque_a or torque_counts (found {})",
                if given.is_empty() {
                    "none".to_string()
                } else {
                    given.join(" and ")
                }
            )));
        }
        Ok(match self {
            SetpointBody {
                speed_rpm: Some(rpm),
                ..
            } => DriveRequest::Speed {
                rpm: units::speed_setpoint(*rpm)?,
            },
            SetpointBody {
                position_deg: Some(deg),
                ..
            } => DriveRequest::Position {
                centideg: units::position_setpoint(*deg)?,
            },
            SetpointBody {
                torque_a: Some(a), ..
            } => DriveRequest::Torque {
                counts: units::torque_setpoint(*a)?,
            },
            SetpointBody {
                torque_counts: Some(c),
                ..
            } => DriveRequest::Torque {
                counts: units::torque_setpoint_counts(*c)?,
            },
            _ => return Err(Problem::invalid("no setpoint given")),
        })
    }
}

/// What a setpoint did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct SetpointReply {
    /// Drive name.
    pub drive: String,
    /// Its bus.
    pub bus: String,
    /// Its unit address.
    pub unit: u8,
    /// What was written (engineering units and raw); the drive echoed it.
    pub written: Vec<Written>,
    /// The lease now covering the motor, if any.
    pub lease: Option<LeaseInfo>,
}

/// The lease length asked for (or the configured default), checked.
fn lease_length(state: &ApiState, asked: Option<i64>) -> Result<Option<Duration>, Problem> {
    let Some(ms) = asked else {
        return Ok(state.config.lease_default);
    };
    let (min, max) = (
        millis(state.config.lease_min),
        millis(state.config.lease_max),
    );
    let ms = RangeError::check_int("lease", ms, min, max, "ms")?;
    Ok(Some(Duration::from_millis(ms.unsigned_abs())))
}

fn millis(d: Duration) -> i64 {
    i64::try_from(d.as_millis()).unwrap_or(i64::MAX)
}

/// How long a setpoint may take to be confirmed: the queue wait and every
/// attempt's timeout, with a margin.
fn pending_allowance(target: Target<'_>, state: &ApiState) -> Duration {
    state
        .plant
        .buses()
        .get(target.drive.bus)
        .map_or(Duration::from_secs(10), |b| {
            let c = &b.config;
            let per_attempt = c.response_timeout_ms + c.guard_ms.unwrap_or(c.response_timeout_ms);
            Duration::from_millis(c.queue_timeout_ms)
                + Duration::from_millis(per_attempt) * (u32::from(c.retries) + 1)
                + Duration::from_secs(1)
        })
}

/// The mode a setpoint drives the motor in.
fn setpoint_mode(request: &DriveRequest) -> Mode {
    match request {
        DriveRequest::Position { .. } => Mode::Position,
        DriveRequest::Torque { .. } => Mode::Torque,
        _ => Mode::Speed,
    }
}

/// Sends a setpoint to drive `key` for `caller`; `connection` ties its
/// lease to a WebSocket.
pub async fn apply(
    state: &ApiState,
    caller: &Caller,
    key: &str,
    body: &SetpointBody,
    connection: Option<u64>,
) -> Result<SetpointReply, Problem> {
    caller.require(Role::Operator)?;
    let target = state.target(key)?;
    let request = body.request()?;
    let lease = lease_length(state, body.lease_ms)?;
    control::ensure_active(caller, target).await?;
    let grant = lease.map(|d| {
        state.leases.grant(
            target.index,
            setpoint_mode(&request),
            &caller.who,
            connection,
            d,
            pending_allowance(target, state),
        )
    });
    let result = control::send(caller, target, &request).await;
    let lease = match (grant, &result) {
        (None, Ok(_)) => {
            let what = format!("a setpoint without a lease from {}", caller.who);
            state.leases.took_over(target.index, &what);
            state.leases.get(target.index)
        }
        (None, Err(_)) => state.leases.get(target.index),
        (Some(g), Err(problem)) if !g.replaced && surely_not_applied(problem) => {
            state.leases.withdraw(target.index, g.id);
            None
        }
        (Some(g), _) => state.leases.confirm(target.index, g.id, result.is_ok()),
    };
    result?;
    Ok(SetpointReply {
        drive: target.drive.name.clone(),
        bus: target.bus.name().to_string(),
        unit: target.drive.unit,
        written: control::written(&request),
        lease,
    })
}

/// True when the drive surely did not take the setpoint: it was never sent,
/// or the drive refused it.
fn surely_not_applied(problem: &Problem) -> bool {
    matches!(
        problem.kind(),
        Kind::BusBusy
            | Kind::BusDown
            | Kind::QueueTimeout
            | Kind::ShuttingDown
            | Kind::DriveNotActive
            | Kind::DriveBusy
            | Kind::DriveRefused
            | Kind::Internal
    )
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
    apply(&state, &caller, &key, &body, None).await.map(Json)
}

/// `POST .../lease/renew` body (optional).
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RenewBody {
    /// A new lease length, ms (default: the current one), between
    /// `[http] lease_min_ms` and `lease_max_ms`.
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
    caller.require(Role::Operator)?;
    let target = state.target(key)?;
    let length = match body.lease_ms {
        Some(ms) => lease_length(state, Some(ms))?,
        None => None,
    };
    state.leases.renew(target.index, length).map_err(|what| {
        Problem::new(
            Kind::NoLease,
            format!("{what}; to take a lease, send the setpoint again with lease_ms"),
        )
        .for_drive(&target.drive.name)
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
    caller.require(Role::Operator)?;
    let target = state.target(key)?;
    let info = state
        .leases
        .release(target.index, &caller.who)
        .map_err(|what| {
            Problem::new(
                Kind::NoLease,
                format!("{what}; there is nothing to release"),
            )
            .for_drive(&target.drive.name)
        })?;
    tracing::info!(
        target: "drivegate::audit",
        who = %caller.who,
        drive = %target.drive.name,
        "lease released: the motor keeps its setpoint without a lease"
    );
    Ok(info)
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
