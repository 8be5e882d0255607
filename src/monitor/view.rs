//! A frame as the API shows it (JSON) and as the CSV download lists it.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::Serialize;
use utoipa::ToSchema;

use super::decode::{self, hex};
use super::record::FrameRecord;
use crate::timestamp::rfc3339_micros;

/// One frame on the wire, decoded.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct FrameView {
    /// Position in the bus's sequence of frames (from 0 at start-up); a gap
    /// is a frame this client did not get.
    pub seq: u64,
    /// When (RFC 3339, UTC, µs): a request's first byte, a reply's last
    /// byte or the end of its wait, when stray bytes were read.
    pub time: String,
    /// The same time in µs since 1970-01-01 UTC, for plotting.
    pub time_us: u64,
    /// `request` (drivegate to the drives), `reply` (a drive to
    /// drivegate, or no reply: `outcome` = `timeout`), `noise` (bytes that
    /// belong to no reply).
    pub direction: &'static str,
    /// The unit the transaction addressed (0: broadcast).
    pub unit: u8,
    /// The Modbus function of the transaction, without the exception bit.
    pub function: Option<u8>,
    /// The bytes, hex, CRC included: `01 03 00 C0 00 07 04 34`.
    pub bytes: String,
    /// Bytes seen (noise longer than 256 bytes is cut in `bytes`).
    pub length: u16,
    /// What it means: the drive's message (`speed setpoint 100 rpm`, the
    /// status values), or generic Modbus.
    pub meaning: String,
    /// `drive` (one of the manual's messages), `modbus` (generic), `none`.
    pub decoded_as: &'static str,
    /// `ok`, `bad` or `none` (no frame to check).
    pub crc: &'static str,
    /// `sent`, `broadcast` (requests); `ok`, `exception`, `timeout`,
    /// `crc_error`, `bad_reply` (replies); `stray` (noise).
    pub outcome: &'static str,
    /// Why a reply was refused (`bad_reply`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<&'static str>,
    /// Attempt of the transaction: 1, or 2 and more for a retry.
    pub attempt: u8,
    /// Replies: µs from the end of the request on the wire to the start of
    /// the reply (the drive's turnaround), estimated from the reply's end
    /// and length.
    pub turnaround_us: Option<u32>,
    /// µs of silence on the line before the frame, as drivegate measured
    /// it: before a request, from the end of the previous frame (its last
    /// byte received, or sent) to the request's first byte (t3.5, or the
    /// drive's learned gap with `interframe = "auto"`, plus overhead);
    /// before a reply, the turnaround.
    pub silence_us: Option<u32>,
    /// µs the frame took on the wire at the line's baud rate.
    pub wire_us: u32,
    /// Who caused the transaction: `poller`, `scope`, `http`, `websocket`,
    /// `modbus-tcp`, `mqtt`, `lease-expiry`, `shutdown`, `internal`.
    pub source: &'static str,
    /// The client: token name (or client address), Modbus TCP peer, lease
    /// owner.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source_who: Option<String>,
    /// The WebSocket session, or the Modbus TCP transaction id.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source_ref: Option<u64>,
    /// The source in words: `Modbus TCP 10.0.0.7:50211 (transaction 17)`.
    pub source_text: String,
}

/// Converts the monitor's clock (ns since it started) to wall-clock time.
#[derive(Debug, Clone, Copy)]
pub struct WallClock {
    /// Wall-clock time of ns 0.
    pub epoch: SystemTime,
    /// ns one byte takes on the wire.
    pub char_ns: u64,
}

impl WallClock {
    /// The wall-clock time of `at_ns`.
    pub fn at(&self, at_ns: u64) -> SystemTime {
        self.epoch + Duration::from_nanos(at_ns)
    }
}

impl FrameView {
    /// The view of `record`.
    pub fn new(record: &FrameRecord, clock: &WallClock) -> Self {
        let meaning = decode::decode(record);
        let time = clock.at(record.at_ns);
        let time_us = time
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
        FrameView {
            seq: record.seq,
            time: rfc3339_micros(time),
            time_us,
            direction: record.direction.name(),
            unit: record.unit,
            function: record.function(),
            bytes: hex(record.bytes()),
            length: record.len,
            meaning: meaning.text,
            decoded_as: meaning.decoded_as.name(),
            crc: meaning.crc.name(),
            outcome: record.outcome.name(),
            detail: (!record.detail.is_empty()).then_some(record.detail),
            attempt: record.attempt,
            turnaround_us: record.turnaround_us,
            silence_us: record.silence_us,
            wire_us: u32::try_from(u64::from(record.len) * clock.char_ns / 1000)
                .unwrap_or(u32::MAX),
            source: record.origin.kind(),
            source_who: record.origin.who(),
            source_ref: record.origin.reference(),
            source_text: record.origin.to_string(),
        }
    }
}

/// The CSV header; one line per frame follows.
pub const CSV_HEADER: &str = "seq,time,time_us,direction,unit,function,bytes,length,meaning,decoded_as,crc,outcome,detail,attempt,turnaround_us,wire_us,source,source_who,source_ref,silence_us";

/// Quotes a CSV field when it needs it (RFC 4180).
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

impl FrameView {
    /// The frame as one CSV line (no line end), in [`CSV_HEADER`]'s order.
    pub fn csv_line(&self) -> String {
        let opt = |v: Option<String>| v.unwrap_or_default();
        [
            self.seq.to_string(),
            self.time.clone(),
            self.time_us.to_string(),
            self.direction.to_string(),
            self.unit.to_string(),
            opt(self.function.map(|f| format!("0x{f:02X}"))),
            self.bytes.clone(),
            self.length.to_string(),
            csv_field(&self.meaning),
            self.decoded_as.to_string(),
            self.crc.to_string(),
            self.outcome.to_string(),
            csv_field(self.detail.unwrap_or("")),
            self.attempt.to_string(),
            opt(self.turnaround_us.map(|t| t.to_string())),
            self.wire_us.to_string(),
            self.source.to_string(),
            csv_field(&opt(self.source_who.clone())),
            opt(self.source_ref.map(|r| r.to_string())),
            opt(self.silence_us.map(|t| t.to_string())),
        ]
        .join(",")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::Origin;
    use crate::modbus::rtu_frame::encode;
    use crate::monitor::record::{Direction, FrameOutcome};

    #[test]
    fn a_reply_as_json_and_csv() {
        let mut r = FrameRecord {
            seq: 41,
            at_ns: 1_500_000,
            direction: Direction::Reply,
            unit: 1,
            attempt: 2,
            outcome: FrameOutcome::Ok,
            turnaround_us: Some(480),
            silence_us: Some(480),
            origin: Origin::Http {
                who: "line, \"A\"".into(),
            },
            ..FrameRecord::default()
        };
        let echo = [0x06, 0x00, 0x06, 0x00, 0x64];
        r.set_request(&encode(1, &echo), true);
        r.set_bytes(&encode(1, &echo));
        let clock = WallClock {
            epoch: UNIX_EPOCH + Duration::from_secs(1_795_318_752),
            char_ns: 86_805,
        };
        let v = FrameView::new(&r, &clock);
        assert_eq!(v.time, "2026-11-22T03:39:12.001500Z");
        assert_eq!(v.time_us, 1_795_318_752_001_500);
        assert_eq!(v.bytes, "01 06 00 06 00 64 68 20");
        assert_eq!(v.meaning, "confirmed: speed setpoint 100 rpm");
        assert_eq!((v.crc, v.outcome, v.source), ("ok", "ok", "http"));
        assert_eq!(v.wire_us, 694);
        let line = v.csv_line();
        assert_eq!(
            line,
            "41,2026-11-22T03:39:12.001500Z,1795318752001500,reply,1,0x06,01 06 00 06 00 64 68 20,8,confirmed: speed setpoint 100 rpm,drive,ok,ok,,2,480,694,http,\"line, \"\"A\"\"\",,480"
        );
        assert_eq!(
            line.matches(',').count() - 1,
            CSV_HEADER.matches(',').count(),
            "one comma is inside a quoted field"
        );
    }
}
