//! A capture as the API shows it: its state (also sent on the WebSocket
//! stream as it fills), and its samples as JSON traces (one per drive,
//! columns ready to plot) or as CSV (one row per sample).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::{SystemTime, UNIX_EPOCH};

use serde::Serialize;
use utoipa::ToSchema;

use super::capture::{Capture, Fired};
use super::field;
use crate::timestamp::rfc3339_micros;

/// The trigger of a capture and, once it fired, when and why.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct TriggerView {
    /// `rising`, `falling`, `fault`, `stall`, `write`, `manual`, `immediate`.
    pub kind: &'static str,
    /// The drive it watches (or whose writes it waits for).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drive: Option<String>,
    /// True once it fired.
    pub fired: bool,
    /// When it fired: t = 0 of the samples (RFC 3339, UTC, µs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time: Option<String>,
    /// What happened, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub what: Option<String>,
    /// Who caused it: the write's source, or who triggered by hand.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
}

/// Where a capture is.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ScopeState {
    /// The capture's number (from 1 since start-up).
    pub id: u64,
    /// Its bus.
    pub bus: String,
    /// `armed` (waiting for the trigger), `triggered` (filling), then
    /// `complete`, `incomplete` (a drive stopped answering), `timed-out`
    /// (no trigger within the wait) or `cancelled`.
    pub state: &'static str,
    /// True while armed or triggered: the captured drives get the polls.
    pub running: bool,
    /// The captured drives.
    pub drives: Vec<String>,
    /// The fields kept.
    pub fields: Vec<String>,
    /// When it was armed (RFC 3339, UTC, µs).
    pub armed_at: String,
    /// Seconds since it was armed (until it ended).
    pub elapsed_s: f64,
    /// The trigger.
    pub trigger: TriggerView,
    /// Samples held from before the trigger.
    pub pre_trigger_samples: usize,
    /// Samples held from the trigger on.
    pub post_trigger_samples: usize,
    /// Post-trigger samples it waits for (a length in samples), else null.
    pub target_samples: Option<usize>,
    /// Samples it may hold at most (sized when armed).
    pub capacity_samples: usize,
    /// Memory its samples take at most, bytes.
    pub memory_bytes: usize,
    /// Samples per second so far, all captured drives together (from the
    /// first to the last sample held).
    pub rate_hz: f64,
}

/// One field of the result.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct FieldView {
    /// Its name (the CSV column): `speed_rpm`.
    pub name: &'static str,
    /// Its unit (empty for flags and codes).
    pub unit: &'static str,
}

/// The samples of one drive, as columns.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct Trace {
    /// The drive.
    pub drive: String,
    /// Its unit address.
    pub unit: u8,
    /// Samples held.
    pub samples: usize,
    /// Its samples per second (first to last sample).
    pub rate_hz: f64,
    /// Each sample's time relative to the trigger, s (negative before it):
    /// the end of the status request on the wire, when the drive read it.
    pub t_s: Vec<f64>,
    /// Each sample's wall-clock time, µs since 1970-01-01 UTC.
    pub time_us: Vec<u64>,
    /// Each field's values, in its unit, by field name.
    pub values: BTreeMap<&'static str, Vec<f64>>,
}

/// A capture's samples.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct ScopeResult {
    /// Where it is (it may still be filling).
    #[serde(flatten)]
    pub state: ScopeState,
    /// The fields, with their units.
    pub columns: Vec<FieldView>,
    /// One trace per captured drive.
    pub traces: Vec<Trace>,
}

fn micros(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX))
}

/// Rounds seconds to the µs.
fn round_us(s: f64) -> f64 {
    (s * 1e6).round() / 1e6
}

fn rate(count: usize, first: Option<std::time::Instant>, last: Option<std::time::Instant>) -> f64 {
    match (first, last) {
        (Some(a), Some(b)) if b > a && count > 1 => {
            ((count - 1) as f64 / (b - a).as_secs_f64() * 10.0).round() / 10.0
        }
        _ => 0.0,
    }
}

/// The state of `capture` on bus `bus`; `name` gives a unit's drive name.
pub fn state(capture: &Capture, bus: &str, name: &dyn Fn(u8) -> String) -> ScopeState {
    let spec = capture.spec();
    let (armed_at, armed_wall) = capture.armed_at();
    let end = capture.ended_at().unwrap_or_else(std::time::Instant::now);
    let (pre, post) = capture.counts();
    let fired: Option<&Fired> = capture.fired();
    let watched = match &spec.trigger {
        super::trigger::Trigger::Level { unit, .. }
        | super::trigger::Trigger::Fault { unit }
        | super::trigger::Trigger::Stall { unit }
        | super::trigger::Trigger::Write { unit } => Some(name(*unit)),
        _ => None,
    };
    ScopeState {
        id: capture.id(),
        bus: bus.to_string(),
        state: capture.phase().name(),
        running: capture.is_running(),
        drives: spec.units.iter().map(|&u| name(u)).collect(),
        fields: spec.fields.iter().map(|f| f.name().to_string()).collect(),
        armed_at: rfc3339_micros(armed_wall),
        elapsed_s: round_us(end.saturating_duration_since(armed_at).as_secs_f64()),
        trigger: TriggerView {
            kind: spec.trigger.kind(),
            drive: watched,
            fired: fired.is_some(),
            time: fired.map(|f| rfc3339_micros(capture.wall(f.at))),
            what: fired.map(|f| f.what.clone()),
            source: fired.and_then(|f| f.by.as_ref()).map(|o| o.to_string()),
        },
        pre_trigger_samples: pre,
        post_trigger_samples: post,
        target_samples: capture.target(),
        capacity_samples: capture.capacity(),
        memory_bytes: capture.capacity() * std::mem::size_of::<super::capture::Sample>(),
        rate_hz: {
            let (first, last) = capture.first_last();
            rate(pre + post, first, last)
        },
    }
}

/// The samples of `capture` as traces.
pub fn result(capture: &Capture, bus: &str, name: &dyn Fn(u8) -> String) -> ScopeResult {
    let spec = capture.spec();
    let traces = spec
        .units
        .iter()
        .map(|&unit| {
            let samples: Vec<_> = capture.samples().filter(|s| s.unit == unit).collect();
            let values = spec
                .fields
                .iter()
                .map(|f| {
                    (
                        f.name(),
                        samples
                            .iter()
                            .map(|s| field::value(*f, &s.status))
                            .collect(),
                    )
                })
                .collect();
            Trace {
                drive: name(unit),
                unit,
                samples: samples.len(),
                rate_hz: rate(
                    samples.len(),
                    samples.first().map(|s| s.at),
                    samples.last().map(|s| s.at),
                ),
                t_s: samples
                    .iter()
                    .map(|s| round_us(capture.relative(s.at)))
                    .collect(),
                time_us: samples.iter().map(|s| micros(capture.wall(s.at))).collect(),
                values,
            }
        })
        .collect();
    ScopeResult {
        state: state(capture, bus, name),
        columns: spec
            .fields
            .iter()
            .map(|f| FieldView {
                name: f.name(),
                unit: field::unit(*f),
            })
            .collect(),
        traces,
    }
}

/// The samples of `capture` as CSV: `time,t_s,drive,unit,` then one column
/// per field (named with its unit), one row per sample in time order.
pub fn csv(capture: &Capture, name: &dyn Fn(u8) -> String) -> String {
    let fields = &capture.spec().fields;
    let mut out = String::from("time,t_s,drive,unit");
    for f in fields {
        out.push(',');
        out.push_str(f.name());
    }
    out.push('\n');
    for s in capture.samples() {
        let _ = write!(
            out,
            "{},{},{},{}",
            rfc3339_micros(capture.wall(s.at)),
            round_us(capture.relative(s.at)),
            crate::monitor::view::csv_field(&name(s.unit)),
            s.unit
        );
        for f in fields {
            let _ = write!(out, ",{}", field::value(*f, &s.status));
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::Status;
    use crate::drive::StatusField;
    use crate::scope::spec::{Amount, CaptureSpec, Limits};
    use crate::scope::trigger::Trigger;
    use std::time::{Duration, Instant};

    #[test]
    fn traces_and_csv_with_units_in_the_column_names() {
        let spec = CaptureSpec {
            units: vec![1, 2],
            fields: vec![StatusField::SpeedRpm, StatusField::CurrentA],
            trigger: Trigger::Manual,
            pre_trigger: Amount::Samples(1),
            length: Amount::Samples(2),
            wait: Duration::from_secs(5),
        };
        let limits = Limits {
            max_samples: 100,
            wire_rate: 171.0,
            max_wait: Duration::from_secs(60),
        };
        let caps = spec.check(&limits).unwrap();
        let t0 = Instant::now();
        let wall = UNIX_EPOCH + Duration::from_secs(1_795_318_752);
        let mut c = Capture::arm(4, spec, caps, Duration::from_micros(5844), t0, wall);
        let ms = Duration::from_millis(1);
        let status = |rpm, counts| Status {
            speed_rpm: rpm,
            current_counts: counts,
            ..Status::default()
        };
        c.on_sample(1, &status(10, 64), t0 + ms);
        c.trigger_now(t0 + 2 * ms, crate::bus::Origin::Http { who: "op".into() })
            .unwrap();
        for i in 0..2 {
            c.on_sample(1, &status(20, 128), t0 + (3 + 2 * i) * ms);
            c.on_sample(2, &status(-5, -32), t0 + (4 + 2 * i) * ms);
        }
        assert_eq!(c.phase().name(), "complete");
        let name = |u: u8| format!("drive{u}");
        let r = result(&c, "line1", &name);
        assert_eq!(r.state.state, "complete");
        assert_eq!(r.state.trigger.source.as_deref(), Some("HTTP op"));
        assert_eq!(
            r.state.trigger.time.as_deref(),
            Some("2026-11-22T03:39:12.002000Z")
        );
        assert_eq!(r.traces.len(), 2);
        assert_eq!(r.traces[0].t_s, [-0.001, 0.001, 0.003]);
        assert_eq!(r.traces[0].values["current_a"], [0.5, 1.0, 1.0]);
        assert_eq!(r.traces[1].values["speed_rpm"], [-5.0, -5.0]);
        assert_eq!(r.traces[0].time_us[0], 1_795_318_752_001_000);
        let json = serde_json::to_value(&r).unwrap();
        assert_eq!(json["state"], "complete");
        assert_eq!(json["columns"][1]["unit"], "A");

        let text = csv(&c, &name);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "time,t_s,drive,unit,speed_rpm,current_a");
        assert_eq!(
            lines[1],
            "2026-11-22T03:39:12.001000Z,-0.001,drive1,1,10,0.5"
        );
        assert_eq!(
            lines[3],
            "2026-11-22T03:39:12.004000Z,0.002,drive2,2,-5,-0.25"
        );
        assert_eq!(lines.len(), 6);
    }
}
