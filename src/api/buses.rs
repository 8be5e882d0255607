//! Bus level: health and counters of each bus, a scan for the units that
//! answer, and address setting (manual 1.2: a broadcast that every drive
//! on the bus obeys, so only with one drive connected).

use std::time::Duration;

use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::caller::authorize;
use super::extract::{JsonBody, OptionalJsonBody, PathParams};
use super::problem_response::{AdminBusProblems, ReadProblems};
use super::problem_response::{BusContext, Kind, Problem};
use super::state::ApiState;
use crate::bus::handle::{JobOptions, PortState};
use crate::bus::stats::Outcome;
use crate::bus::{BusError, BusHandle, Priority};
use crate::control::{Caller, ControlRequest, Operation};
use crate::drive::{DriveReply, DriveRequest, RangeError};
use crate::faces_shared::integers;
use crate::faces_shared::status::StatusView;
use crate::plant::Bus;
use crate::timestamp::rfc3339;

/// Jobs waiting on a bus, by priority.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct QueueDepths {
    /// Brake and safe-stop actions.
    pub emergency: usize,
    /// Commands, setpoints, fresh reads, scans.
    pub command: usize,
    /// Status polls.
    pub poll: usize,
}

/// A bus's counters since the daemon started.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct BusCounters {
    /// Status polls made.
    pub polls: u64,
    /// Status polls that failed.
    pub poll_failures: u64,
    /// Transactions with a valid reply.
    pub ok: u64,
    /// Transactions the drive answered with a Modbus exception.
    pub exceptions: u64,
    /// Transactions without a reply in time.
    pub timeouts: u64,
    /// Replies with a wrong CRC.
    pub crc_errors: u64,
    /// Replies that did not answer the request.
    pub bad_replies: u64,
    /// Jobs dropped unsent (caller gone or deadline passed).
    pub dropped: u64,
    /// Retries made.
    pub retries: u64,
    /// Submissions refused because a queue was full.
    pub busy_rejections: u64,
    /// Bytes that belonged to no reply (noise, late replies).
    pub stray_bytes: u64,
    /// Serial port errors.
    pub port_errors: u64,
    /// Times the port was reopened.
    pub reopens: u64,
    /// Seconds the wire was busy.
    pub busy_seconds: f64,
}

/// One drive's silence before its requests.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct DriveGapView {
    /// Its unit address.
    pub unit: u8,
    /// The silence its requests get now, µs: t3.5, the fixed value, or its
    /// learned gap.
    pub gap_us: u64,
    /// Times its learned gap was dropped for the spec after a fault.
    pub fallbacks: u64,
}

/// The silence before requests on a bus (`[bus] interframe`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct InterframeView {
    /// `spec`, `auto`, or the fixed silence in µs.
    pub setting: String,
    /// Each configured drive's, in configuration order.
    pub drives: Vec<DriveGapView>,
}

/// A bus: its port, health and counters.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct BusView {
    /// Its name.
    pub name: String,
    /// Its serial device (`sim` for the built-in simulator).
    pub port: String,
    /// Baud rate.
    pub baud: u32,
    /// `opening`, `up` or `down`.
    pub state: String,
    /// Since when (RFC 3339, UTC).
    pub since: Option<String>,
    /// Why it is down.
    pub reason: Option<String>,
    /// Configured drives.
    pub drives: usize,
    /// Drives whose data is live (answering within their poll period;
    /// none while the port is down).
    pub drives_online: usize,
    /// Jobs waiting.
    pub queue: QueueDepths,
    /// Counters.
    pub counters: BusCounters,
    /// True when a drive of the bus is polled as fast as the bus allows
    /// (`poll_interval_ms = 0`, the default): its wire is then in use all
    /// the time by design (commands still go ahead of polls), and a
    /// utilisation near 100 % is no fault.
    pub polled_flat_out: bool,
    /// The silence before each drive's requests.
    pub interframe: InterframeView,
}

fn bus_view(bus: &Bus) -> BusView {
    let handle = &bus.handle;
    let (state, since, reason) = match handle.port_state() {
        PortState::Opening => ("opening", None, None),
        PortState::Up { since } => ("up", Some(rfc3339(since)), None),
        PortState::Down { since, reason } => ("down", Some(rfc3339(since)), Some(reason)),
    };
    let stats = handle.stats();
    let [emergency, command, poll] = handle.queue_depths();
    let start = bus.config.starting_interframe();
    let interframe = InterframeView {
        setting: bus.config.interframe.describe(),
        drives: bus
            .config
            .drives
            .iter()
            .map(|d| {
                let timing = stats.drives.get(&d.unit());
                DriveGapView {
                    unit: d.unit(),
                    gap_us: timing.map_or(start, |t| t.interframe).as_micros() as u64,
                    fallbacks: timing.map_or(0, |t| t.interframe_fallbacks),
                }
            })
            .collect(),
    };
    let live = handle.freshness_all(std::time::Instant::now());
    BusView {
        name: handle.name().to_string(),
        port: bus.config.port.get_ref().clone(),
        baud: bus.config.baud,
        state: state.to_string(),
        since,
        reason,
        drives: bus.config.drives.len(),
        drives_online: bus
            .config
            .drives
            .iter()
            .filter(|d| {
                live.iter()
                    .any(|(unit, v)| *unit == d.unit() && v.freshness.is_live())
            })
            .count(),
        queue: QueueDepths {
            emergency,
            command,
            poll,
        },
        counters: BusCounters {
            polls: stats.polls,
            poll_failures: stats.poll_failures,
            ok: stats.count(Outcome::Ok),
            exceptions: stats.count(Outcome::Exception),
            timeouts: stats.count(Outcome::Timeout),
            crc_errors: stats.count(Outcome::CrcError),
            bad_replies: stats.count(Outcome::BadReply),
            dropped: stats.count(Outcome::Dropped),
            retries: stats.retries,
            busy_rejections: stats.busy_rejections,
            stray_bytes: stats.stray_bytes,
            port_errors: stats.port_errors,
            reopens: stats.reopens,
            busy_seconds: stats.busy_seconds,
        },
        polled_flat_out: bus
            .config
            .drives
            .iter()
            .any(|d| d.poll_interval_ms.unwrap_or(bus.config.poll_interval_ms) == 0),
        interframe,
    }
}

/// Every bus with its port state, queues and counters.
#[utoipa::path(
    get,
    path = "/api/v1/buses",
    tag = "buses",
    security(("bearer" = ["viewer"])),
    responses(
        (status = 200, description = "Every bus, in configuration order", body = [BusView]),
        ReadProblems,
    )
)]
pub async fn list_buses(
    State(state): State<ApiState>,
    _caller: Caller,
) -> Result<Json<Vec<BusView>>, Problem> {
    Ok(Json(
        state.plant.now().buses().map(|b| bus_view(b)).collect(),
    ))
}

/// One bus with its port state, queues and counters.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}",
    tag = "buses",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "The bus", body = BusView),
        ReadProblems,
    )
)]
pub async fn get_bus(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<BusView>, Problem> {
    state.bus(&name).map(|b| Json(bus_view(&b)))
}

/// `POST .../scan` body (optional).
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ScanBody {
    /// First unit to try (1..255).
    #[serde(default = "default_from", deserialize_with = "integers::integer")]
    #[schema(minimum = 1, maximum = 255)]
    pub from: i64,
    /// Last unit to try (1..255, not below `from`); each silent unit costs a
    /// response timeout.
    #[serde(default = "default_to", deserialize_with = "integers::integer")]
    #[schema(minimum = 1, maximum = 255)]
    pub to: i64,
}

fn default_from() -> i64 {
    1
}
fn default_to() -> i64 {
    32
}

impl Default for ScanBody {
    fn default() -> Self {
        ScanBody {
            from: default_from(),
            to: default_to(),
        }
    }
}

/// A unit that answered a scan.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ScanHit {
    /// Its address.
    pub unit: u8,
    /// The configured drive at that address on this bus, if any.
    pub configured_as: Option<String>,
    /// Its status, when it answered the status read.
    pub status: Option<StatusView>,
    /// The Modbus exception it answered with instead, if so.
    pub exception_code: Option<u8>,
}

/// A unit the scan could not read: the bus stayed busy, or went down.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct NotScanned {
    /// Its address.
    pub unit: u8,
    /// Why it was not read (nothing was sent to it).
    pub reason: String,
}

/// What a scan found.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ScanReply {
    /// The bus.
    pub bus: String,
    /// First unit tried.
    pub from: u8,
    /// Last unit tried.
    pub to: u8,
    /// Units that answered.
    pub answered: Vec<ScanHit>,
    /// Units whose replies were garbled: often two drives with one address.
    pub garbled: Vec<u8>,
    /// Configured drives in the range that did not answer.
    pub missing: Vec<String>,
    /// Units that stayed silent.
    pub silent: usize,
    /// Units not read: the queue stayed full (or the read waited its whole
    /// queue time) on every try, or the bus went down; scan them again.
    pub not_scanned: Vec<NotScanned>,
}

/// Tries a scan gives a unit the bus is too busy for.
const SCAN_TRIES: u32 = 3;
/// Wait before trying a unit again after a full queue (times the try).
const SCAN_BUSY_WAIT: Duration = Duration::from_millis(250);

/// Reads `unit`'s status for a scan. The scan shares the bus with the
/// commands and polls of everybody else, so a read refused because the
/// queue is full is tried again after a short wait, and one that waited its
/// whole queue time at once (it has waited already); neither was sent.
async fn scan_read(
    handle: &BusHandle,
    unit: u8,
    options: JobOptions,
) -> Result<DriveReply, BusError> {
    let mut tries = 1;
    loop {
        match handle
            .execute(unit, &DriveRequest::ReadStatus, options.clone())
            .await
        {
            Err(BusError::Busy { .. }) if tries < SCAN_TRIES => {
                tokio::time::sleep(SCAN_BUSY_WAIT * tries).await;
            }
            Err(BusError::Expired { .. }) if tries < SCAN_TRIES => {}
            other => return other,
        }
        tries += 1;
    }
}

fn unit_in(quantity: &'static str, v: i64) -> Result<u8, Problem> {
    let v = RangeError::check_int(quantity, v, 1, 255, "")?;
    u8::try_from(v).map_err(|_| Problem::invalid("unit out of range"))
}

/// Reads the status of every unit in a range, one attempt each with a short
/// queue wait, and reports which answered (admin). Polling goes on
/// meanwhile; each silent unit costs one response timeout of bus time. A
/// unit the bus is too busy for is tried again, then reported in
/// `not_scanned`; the rest of the range is scanned all the same.
#[utoipa::path(
    post,
    path = "/api/v1/buses/{bus}/scan",
    tag = "buses",
    security(("bearer" = ["admin"])),
    params(("bus" = String, Path, description = "Bus name")),
    request_body(content = Option<ScanBody>, description = "Optional: the unit range (default 1..32)"),
    responses(
        (status = 200, description = "What answered", body = ScanReply),
        AdminBusProblems,
    )
)]
pub async fn post_scan(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
    OptionalJsonBody(body): OptionalJsonBody<ScanBody>,
) -> Result<Json<ScanReply>, Problem> {
    scan(&state, &caller, &name, &body.unwrap_or_default())
        .await
        .map(Json)
}

/// Scans `name` for `caller`.
pub async fn scan(
    state: &ApiState,
    caller: &Caller,
    name: &str,
    body: &ScanBody,
) -> Result<ScanReply, Problem> {
    authorize(state, caller, Operation::Scan)?;
    let bus = &*state.bus(name)?;
    let from = unit_in("first unit", body.from)?;
    let to = unit_in("last unit", body.to)?;
    if from > to {
        return Err(Problem::invalid(format!(
            "the range is empty: from = {from} is after to = {to}"
        )));
    }
    let handle = &bus.handle;
    let options = JobOptions {
        priority: Priority::Command,
        source: caller.source,
        queue_timeout: Some(Duration::from_secs(2)),
        max_attempts: Some(1),
        origin: caller.origin.clone(),
    };
    let mut reply = ScanReply {
        bus: handle.name().to_string(),
        from,
        to,
        answered: Vec::new(),
        garbled: Vec::new(),
        missing: Vec::new(),
        silent: 0,
        not_scanned: Vec::new(),
    };
    tracing::info!(who = %caller.who, bus = %handle.name(), from, to, "bus scan");
    let mut units = from..=to;
    while let Some(unit) = units.next() {
        let configured_as = bus
            .config
            .drives
            .iter()
            .find(|d| d.unit() == unit)
            .map(|d| d.name().to_string());
        match scan_read(handle, unit, options.clone()).await {
            Ok(DriveReply::Status(s)) => reply.answered.push(ScanHit {
                unit,
                configured_as,
                status: Some(StatusView::from(&s)),
                exception_code: None,
            }),
            Ok(_) => reply.garbled.push(unit),
            Err(BusError::Exception { code, .. }) => reply.answered.push(ScanHit {
                unit,
                configured_as,
                status: None,
                exception_code: Some(code.0),
            }),
            Err(BusError::Timeout { .. }) => {
                reply.silent += 1;
                if let Some(name) = configured_as {
                    reply.missing.push(name);
                }
            }
            Err(BusError::BadReply { .. } | BusError::Unconfirmed { .. }) => {
                reply.garbled.push(unit);
            }
            Err(e @ (BusError::Busy { .. } | BusError::Expired { .. })) => {
                reply.not_scanned.push(NotScanned {
                    unit,
                    reason: format!("tried {SCAN_TRIES} times: {e}"),
                });
            }
            Err(e @ (BusError::BusDown { .. } | BusError::ShuttingDown)) => {
                // Nothing found yet: the bus's state is the answer.
                let found_nothing = reply.answered.is_empty()
                    && reply.garbled.is_empty()
                    && reply.silent == 0
                    && reply.not_scanned.is_empty();
                if found_nothing {
                    return Err(Problem::bus(&e, BusContext::default()));
                }
                // The rest would fail alike: keep what was found.
                let reason = e.to_string();
                for unit in std::iter::once(unit).chain(units.by_ref()) {
                    reply.not_scanned.push(NotScanned {
                        unit,
                        reason: reason.clone(),
                    });
                }
            }
            Err(e) => return Err(Problem::bus(&e, BusContext::default())),
        }
    }
    Ok(reply)
}

/// `POST .../address` body.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AddressBody {
    /// The new address, 1..255.
    #[serde(deserialize_with = "integers::integer")]
    #[schema(minimum = 1, maximum = 255)]
    pub address: i64,
    /// Must be true: the broadcast sets the address of every drive that
    /// hears it, so only one drive may be connected to the bus.
    #[serde(default)]
    pub only_drive_on_bus: bool,
    /// Set the address even while a drive of the bus turns (a drive that
    /// takes a new address stops answering at the old one mid-motion).
    #[serde(default)]
    pub force: bool,
}

/// What an address setting did.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct AddressReply {
    /// The bus.
    pub bus: String,
    /// The new address.
    pub address: u8,
    /// True: a status read at the new address was answered.
    pub verified: bool,
    /// The status read at the new address.
    pub status: StatusView,
    /// The configured drive at that address on this bus, if any.
    pub configured_as: Option<String>,
    /// What to do next.
    pub note: String,
}

/// Sets the address of the only drive on the bus with a broadcast (admin),
/// then verifies it by reading status at the new address.
///
/// drivegate polls the units in its configuration: afterwards set `unit`
/// of that drive's `[[bus.drive]]` to the new address and restart.
#[utoipa::path(
    post,
    path = "/api/v1/buses/{bus}/address",
    tag = "buses",
    security(("bearer" = ["admin"])),
    params(("bus" = String, Path, description = "Bus name")),
    request_body(content = AddressBody, example = json!({"address": 5, "only_drive_on_bus": true})),
    responses(
        (status = 200, description = "The drive answers at the new address", body = AddressReply),
        AdminBusProblems,
    )
)]
pub async fn post_address(
    State(state): State<ApiState>,
    caller: Caller,
    PathParams(name): PathParams<String>,
    JsonBody(body): JsonBody<AddressBody>,
) -> Result<Json<AddressReply>, Problem> {
    set_address(&state, &caller, &name, &body).await.map(Json)
}

/// Sets the address on bus `name` for `caller`.
pub async fn set_address(
    state: &ApiState,
    caller: &Caller,
    name: &str,
    body: &AddressBody,
) -> Result<AddressReply, Problem> {
    let bus = &*state.bus(name)?;
    let address = unit_in("drive address", body.address)?;
    let handle: &BusHandle = &bus.handle;
    let index = state
        .plant
        .now()
        .indexed_buses()
        .find(|(_, b)| b.handle.name() == handle.name())
        .map(|(i, _)| i)
        .ok_or_else(|| Problem::new(Kind::Internal, "bus directory inconsistent"))?;
    let request = ControlRequest::drive(DriveRequest::SetAddress { address })
        .single_drive(body.only_drive_on_bus)
        .forced(body.force);
    let target = state.control.unit_target(index, 0);
    state
        .control
        .write(caller, target, request)
        .await
        .map_err(|f| crate::faces_shared::writes::problem(caller, &f, BusContext::default()))?;
    let options = JobOptions {
        priority: Priority::Command,
        source: caller.source,
        queue_timeout: None,
        max_attempts: None,
        origin: caller.origin.clone(),
    };
    let verified = handle
        .execute(address, &DriveRequest::ReadStatus, options)
        .await;
    let status = match verified {
        Ok(DriveReply::Status(s)) => s,
        Ok(_) => {
            return Err(Problem::new(
                Kind::DriveUnconfirmed,
                format!(
                    "the broadcast was sent, but the reply at unit {address} carried no status"
                ),
            ));
        }
        Err(e) => {
            let mut p = Problem::bus(&e, BusContext::default());
            p.detail = format!(
                "the address broadcast was sent, but no drive confirms it at unit {address}: {}",
                p.detail
            );
            return Err(p);
        }
    };
    let configured_as = bus
        .config
        .drives
        .iter()
        .find(|d| d.unit() == address)
        .map(|d| d.name().to_string());
    crate::control::audit::address_verified(
        caller.face.name(),
        &caller.who,
        handle.name(),
        address,
    );
    Ok(AddressReply {
        bus: handle.name().to_string(),
        address,
        verified: true,
        status: StatusView::from(&status),
        note: match &configured_as {
            Some(name) => format!(
                "drive \"{name}\" is configured at unit {address}: drivegate polls it there"
            ),
            None => format!(
                "set unit = {address} in this drive's [[bus.drive]] section and restart drivegate: it polls only the configured units"
            ),
        },
        configured_as,
    })
}
