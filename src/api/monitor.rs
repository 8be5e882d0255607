//! The bus monitor's routes: every frame on the wire of a bus, as JSON, CSV
//! or PCAP, and the per-attempt wire counters (live over a WebSocket:
//! [`super::monitor_live`]). Reading only: the viewer role.

use std::collections::VecDeque;

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::{Params, PathParams};
use super::problem_response::{Problem, ProblemDetails, ReadProblems};
use super::state::{ApiState, monitor_of};
use crate::control::Caller;
use crate::monitor::filter::{FilterText, FrameFilter};
use crate::monitor::record::FrameRecord;
use crate::monitor::view::{CSV_HEADER, FrameView};
use crate::monitor::{BusMonitor, pcap};
use crate::plant::Bus;

/// Frames a JSON answer holds when `limit` is not given.
const DEFAULT_LIMIT: usize = 1000;
/// Frames an answer may hold: the largest ring.
const MAX_LIMIT: usize = 1_000_000;

/// Which frames: every list is comma-separated; an absent one lets all
/// through.
#[derive(Debug, Clone, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct FrameQuery {
    /// Units of the transaction: `1,3-4`.
    pub unit: Option<String>,
    /// Function codes: `3,0x06,16`.
    pub function: Option<String>,
    /// Outcomes: `sent`, `broadcast`, `ok`, `exception`, `timeout`,
    /// `crc_error`, `bad_reply`, `stray`; and `retry` for the frames of a
    /// retry.
    pub outcome: Option<String>,
    /// Who caused it: `poller`, `scope`, `http`, `websocket`, `modbus-tcp`,
    /// `mqtt`, `lease-expiry`, `shutdown`, `internal`.
    pub source: Option<String>,
    /// The client: a token name (or client address), a Modbus TCP peer
    /// `address:port`, a lease's owner.
    pub who: Option<String>,
    /// Start at this sequence number (the `next` of a previous answer);
    /// without it, the last `limit` frames.
    #[param(minimum = 0, maximum = 9_223_372_036_854_775_807_i64)]
    pub from: Option<u64>,
    /// Frames at most (JSON: default 1000; downloads: the whole ring).
    #[param(minimum = 1, maximum = 1_000_000)]
    pub limit: Option<usize>,
}

impl FrameQuery {
    /// `limit` checked, or `default`.
    fn limit(&self, default: usize) -> Result<usize, Problem> {
        match self.limit.unwrap_or(default) {
            n @ 1..=MAX_LIMIT => Ok(n),
            n => Err(Problem::invalid(format!(
                "limit must be 1 to {MAX_LIMIT}, not {n}"
            ))),
        }
    }

    /// `from` checked (a JSON Schema int64).
    fn from(&self) -> Result<Option<u64>, Problem> {
        match self.from {
            Some(n) if n > i64::MAX as u64 => Err(Problem::invalid(format!(
                "from must be 0 to {}, not {n}",
                i64::MAX
            ))),
            other => Ok(other),
        }
    }

    fn filter(&self) -> Result<FrameFilter, Problem> {
        FrameFilter::parse(&FilterText {
            units: self.unit.as_deref(),
            functions: self.function.as_deref(),
            outcomes: self.outcome.as_deref(),
            sources: self.source.as_deref(),
            who: self.who.as_deref(),
        })
        .map_err(Problem::invalid)
    }
}

/// Per-attempt wire counters of one unit since start-up: every attempt
/// counts, so a fault that a retry hid still shows.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct UnitCounters {
    /// The unit.
    pub unit: u8,
    /// The configured drive at that unit, if any.
    pub drive: Option<String>,
    /// Requests sent (each attempt).
    pub attempts: u64,
    /// Replies with a wrong CRC.
    pub crc_errors: u64,
    /// Attempts without a reply.
    pub timeouts: u64,
    /// Replies that did not answer the request.
    pub bad_replies: u64,
    /// Exception replies.
    pub exceptions: u64,
    /// Stray bytes that followed a transaction with this unit.
    pub stray_bytes: u64,
}

/// The monitor of one bus.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct MonitorView {
    /// The bus.
    pub bus: String,
    /// False when `[monitor] enabled = false`: no frames are kept (the
    /// counters run anyway).
    pub enabled: bool,
    /// Frames the ring keeps (`[monitor] ring_frames`).
    pub ring_frames: usize,
    /// Memory the ring takes, bytes.
    pub memory_bytes: usize,
    /// Frames seen since start-up; the next frame's sequence number.
    pub frames_seen: u64,
    /// The oldest sequence number still in the ring.
    pub oldest: u64,
    /// Live clients connected now.
    pub live_clients: usize,
    /// Frames live clients lost by reading too slowly, since start-up.
    pub lost_frames: u64,
    /// Per-attempt counters of the configured units (and of any other unit
    /// seen on the wire).
    pub units: Vec<UnitCounters>,
}

/// Frames of the ring.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct FramesReply {
    /// The bus.
    pub bus: String,
    /// Pass as `from` to get the frames after these.
    pub next: u64,
    /// The oldest sequence number still in the ring.
    pub oldest: u64,
    /// Frames from `from` on that were overwritten before this read.
    pub missed: u64,
    /// The frames, oldest first.
    pub frames: Vec<FrameView>,
}

fn drive_name(bus: &Bus, unit: u8) -> Option<String> {
    bus.config
        .drives
        .iter()
        .find(|d| d.unit() == unit)
        .map(|d| d.name().to_string())
}

/// Reads the frames `query` selects: from `from`, or the last `limit`.
/// Returns them with the next sequence number and the frames missed.
fn select(
    monitor: &BusMonitor,
    filter: &FrameFilter,
    from: Option<u64>,
    limit: usize,
) -> (Vec<FrameRecord>, u64, u64) {
    let Some(ring) = monitor.ring() else {
        return (Vec::new(), 0, 0);
    };
    let mut cursor = from.unwrap_or_else(|| ring.oldest());
    let mut kept: VecDeque<FrameRecord> = VecDeque::new();
    let mut missed = 0;
    let mut batch = Vec::with_capacity(1024);
    let head = ring.head();
    while cursor < head {
        batch.clear();
        let report = ring.read(&mut cursor, 1024, &mut batch);
        missed += report.lost;
        for record in batch.drain(..).filter(|r| filter.accepts(r)) {
            if from.is_some() && kept.len() == limit {
                // From a point on: stop once full, `next` says where.
                cursor = record.seq;
                return (kept.into(), cursor, missed);
            }
            kept.push_back(record);
            if kept.len() > limit {
                kept.pop_front();
            }
        }
        if report.read == 0 && report.lost == 0 {
            break;
        }
    }
    (kept.into(), cursor, if from.is_some() { missed } else { 0 })
}

/// The monitor of a bus: its ring, its live clients, and the per-attempt
/// wire counters of every unit.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/monitor",
    tag = "monitor",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name")),
    responses(
        (status = 200, description = "The monitor", body = MonitorView),
        ReadProblems,
    )
)]
pub async fn get_monitor(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
) -> Result<Json<MonitorView>, Problem> {
    let bus = &*state.bus(&name)?;
    let monitor = bus.monitor();
    let units = monitor
        .counters()
        .snapshot(&monitor.units())
        .into_iter()
        .map(|(unit, c)| UnitCounters {
            unit,
            drive: drive_name(bus, unit),
            attempts: c.attempts,
            crc_errors: c.crc_errors,
            timeouts: c.timeouts,
            bad_replies: c.bad_replies,
            exceptions: c.exceptions,
            stray_bytes: c.stray_bytes,
        })
        .collect();
    Ok(Json(MonitorView {
        bus: bus.handle.name().to_string(),
        enabled: monitor.enabled(),
        ring_frames: monitor.capacity(),
        memory_bytes: monitor.memory_bytes(),
        frames_seen: monitor.frames(),
        oldest: monitor.ring().map_or(0, |r| r.oldest()),
        live_clients: monitor.clients(),
        lost_frames: monitor.lost(),
        units,
    }))
}

/// Frames of the ring, decoded, filtered: the last `limit`, or from `from`
/// on (to page through, pass each answer's `next`).
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/monitor/frames",
    tag = "monitor",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name"), FrameQuery),
    responses(
        (status = 200, description = "The frames, oldest first", body = FramesReply),
        (status = 409, description = "`monitor-off`: `[monitor] enabled = false`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_frames(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
    Params(query): Params<FrameQuery>,
) -> Result<Json<FramesReply>, Problem> {
    let bus = &*state.bus(&name)?;
    let monitor = monitor_of(bus)?;
    let filter = query.filter()?;
    let limit = query.limit(DEFAULT_LIMIT)?;
    let (records, next, missed) = select(monitor, &filter, query.from()?, limit);
    let clock = monitor.clock();
    Ok(Json(FramesReply {
        bus: bus.handle.name().to_string(),
        next,
        oldest: monitor.ring().map_or(0, |r| r.oldest()),
        missed,
        frames: records.iter().map(|r| FrameView::new(r, clock)).collect(),
    }))
}

fn download(body: Vec<u8>, content_type: &'static str, file: String) -> Response {
    let mut response = body.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{file}\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    response
}

/// The frames of the ring as CSV, one line per frame, the columns of the
/// JSON frames (filters as for `frames`).
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/monitor/frames.csv",
    tag = "monitor",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name"), FrameQuery),
    responses(
        (status = 200, description = "CSV with a header line: seq,time,time_us,direction,unit,function,bytes,length,meaning,decoded_as,crc,outcome,detail,attempt,turnaround_us,wire_us,source,source_who,source_ref,silence_us", content_type = "text/csv", body = String),
        (status = 409, description = "`monitor-off`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_frames_csv(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
    Params(query): Params<FrameQuery>,
) -> Result<Response, Problem> {
    let bus = &*state.bus(&name)?;
    let monitor = monitor_of(bus)?;
    let filter = query.filter()?;
    let limit = query.limit(monitor.capacity())?;
    let (records, _, _) = select(monitor, &filter, query.from()?, limit);
    let clock = monitor.clock();
    let mut text = String::with_capacity(160 * (records.len() + 1));
    text.push_str(CSV_HEADER);
    text.push('\n');
    for r in &records {
        text.push_str(&FrameView::new(r, clock).csv_line());
        text.push('\n');
    }
    Ok(download(
        text.into_bytes(),
        "text/csv; charset=utf-8",
        format!("{}-frames.csv", bus.handle.name()),
    ))
}

/// The frames of the ring as a PCAP file that Wireshark and tshark decode as
/// Modbus RTU: `tshark -r FILE -o mbrtu.udp.port:502` (each RTU frame is
/// the payload of a UDP datagram to or from port 502; unit N is 127.0.1.N;
/// timeouts, having no bytes, are left out). Filters as for `frames`.
#[utoipa::path(
    get,
    path = "/api/v1/buses/{bus}/monitor/frames.pcap",
    tag = "monitor",
    security(("bearer" = ["viewer"])),
    params(("bus" = String, Path, description = "Bus name"), FrameQuery),
    responses(
        (status = 200, description = "A PCAP file (link type 101, raw IPv4)", content_type = "application/vnd.tcpdump.pcap", body = Vec<u8>),
        (status = 409, description = "`monitor-off`", body = ProblemDetails, content_type = "application/problem+json"),
        ReadProblems,
    )
)]
pub async fn get_frames_pcap(
    State(state): State<ApiState>,
    _caller: Caller,
    PathParams(name): PathParams<String>,
    Params(query): Params<FrameQuery>,
) -> Result<Response, Problem> {
    let bus = &*state.bus(&name)?;
    let monitor = monitor_of(bus)?;
    let filter = query.filter()?;
    let limit = query.limit(monitor.capacity())?;
    let (records, _, _) = select(monitor, &filter, query.from()?, limit);
    Ok(download(
        pcap::file(&records, monitor.clock()),
        "application/vnd.tcpdump.pcap",
        format!("{}-frames.pcap", bus.handle.name()),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::timing::LineTiming;
    use crate::monitor::MonitorSettings;

    #[test]
    fn selects_the_last_frames_or_pages_from_a_point() {
        let monitor = BusMonitor::new(
            MonitorSettings {
                enabled: true,
                ring_frames: 16,
            },
            LineTiming::new_8n1(115_200),
            vec![1, 2],
        );
        let ring = monitor.ring().unwrap();
        for i in 0..40u8 {
            ring.push(|r| r.unit = 1 + i % 2);
        }
        let all = FrameFilter::default();
        let (last, next, _) = select(&monitor, &all, None, 5);
        assert_eq!(
            last.iter().map(|r| r.seq).collect::<Vec<_>>(),
            [35, 36, 37, 38, 39]
        );
        assert_eq!(next, 40);
        let units2 = FrameFilter {
            units: vec![2],
            ..FrameFilter::default()
        };
        // From 10: 14 were overwritten (the ring keeps 24..39).
        let (page, next, missed) = select(&monitor, &units2, Some(10), 3);
        assert_eq!(missed, 14);
        assert_eq!(page.iter().map(|r| r.seq).collect::<Vec<_>>(), [25, 27, 29]);
        let (page, next, missed) = select(&monitor, &units2, Some(next), 100);
        assert_eq!(missed, 0);
        assert_eq!(
            page.iter().map(|r| r.seq).collect::<Vec<_>>(),
            [31, 33, 35, 37, 39]
        );
        assert_eq!(next, 40);
    }
}
