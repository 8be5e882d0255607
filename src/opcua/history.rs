//! `HistoryRead` (raw) of a drive's trend, from the daemon's history
//! (`crate::history`): the status as polled where the full-rate ring still
//! holds it, and before that one value per second (the second's mean,
//! marked `Calculated` in its status code's historian bits, Part 11). At
//! most [`PAGE`] values per answer (or the client's `numValuesPerNode`);
//! the rest follows with a continuation point.

use opcua::server::ContinuationPoint;
use opcua::server::node_manager::HistoryNode;
use opcua::types::{
    DataValue, DateTime, HistoryData, ReadRawModifiedDetails, StatusCode, StatusCodeValueType,
    Variant,
};

use super::values::unix_ms;
use crate::drive::StatusField;
use crate::history::History;
use crate::history::store::Point;

/// The most values one answer carries.
pub const PAGE: usize = 1000;

/// Where the next page of a read starts, Unix ms.
struct Cursor {
    from_ms: i64,
}

/// Answers `node` with the raw history of `field` of `unit` on `bus`.
pub fn read_raw(
    history: &History,
    (bus, unit, field): (&str, u8, StatusField),
    details: &ReadRawModifiedDetails,
    node: &mut HistoryNode,
) {
    let (mut start, mut end) = (
        bound(&details.start_time, i64::MIN),
        bound(&details.end_time, i64::MAX),
    );
    let reverse = start > end;
    if reverse {
        std::mem::swap(&mut start, &mut end);
    }
    if let Some(cursor) = node.continuation_point().and_then(|c| c.get::<Cursor>()) {
        if reverse {
            end = cursor.from_ms;
        } else {
            start = cursor.from_ms;
        }
    }
    let wanted = match usize::try_from(details.num_values_per_node) {
        Ok(0) | Err(_) => PAGE,
        Ok(n) => n.min(PAGE),
    };
    let mut points = history.query(bus, unit, start, end, usize::MAX);
    if reverse {
        points.reverse();
    }
    let more = points.len() > wanted;
    points.truncate(wanted);
    let next = match (more, points.last()) {
        (true, Some(last)) if reverse => Some(last.t_ms - 1),
        (true, Some(last)) => Some(last.t_ms + 1),
        _ => None,
    };
    let data_values = points.iter().map(|p| value_of(p, field)).collect();
    node.set_next_continuation_point(
        next.map(|from_ms| ContinuationPoint::new(Box::new(Cursor { from_ms }))),
    );
    node.set_result(HistoryData {
        data_values: Some(data_values),
    });
    node.set_status(StatusCode::Good);
}

/// A time bound of a request, Unix ms; a null time is open.
fn bound(t: &DateTime, open: i64) -> i64 {
    if t.is_null() { open } else { unix_ms(t) }
}

/// A point of the history as a data value of `field`.
fn value_of(point: &Point, field: StatusField) -> DataValue {
    let value = point.mean_of(field).unwrap_or(0.0);
    let status = if point.span_ms == 0 {
        StatusCode::Good
    } else {
        StatusCode::Good.set_value_type(StatusCodeValueType::Calculated)
    };
    let at = DateTime::from(
        super::values::date_time(std::time::UNIX_EPOCH)
            .ticks()
            .saturating_add(point.t_ms.saturating_mul(10_000)),
    );
    DataValue {
        value: Some(Variant::Double(value)),
        status: Some(status),
        source_timestamp: Some(at),
        source_picoseconds: None,
        server_timestamp: Some(at),
        server_picoseconds: None,
    }
}
