//! What a frame means, in words: the drive's own message where the bytes are
//! one of the manual's (a speed setpoint of 100 rpm, the status block with
//! its values), generic Modbus otherwise (function, address, count,
//! values). Pure: bytes in, text out; run when a frame is shown, never on
//! the bus thread.

use std::fmt::Write as _;

use super::record::{Direction, FrameOutcome, FrameRecord};
use crate::drive::{ConfigCommand, DriveRequest, Register, Status};
use crate::modbus::ExceptionCode;
use crate::modbus::crc::frame_crc_ok;
use crate::modbus::function::{self, be_u16};

/// How a frame was understood.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodedAs {
    /// One of the drive manual's messages (or its reply).
    Drive,
    /// Generic Modbus.
    Modbus,
    /// Not a frame (noise, a timeout, too short).
    None,
}

impl DecodedAs {
    /// Stable name: `drive`, `modbus`, `none`.
    pub fn name(self) -> &'static str {
        match self {
            DecodedAs::Drive => "drive",
            DecodedAs::Modbus => "modbus",
            DecodedAs::None => "none",
        }
    }
}

/// The CRC of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Crc {
    /// Matches.
    Ok,
    /// Does not match.
    Bad,
    /// No frame to check (a timeout, noise, fewer than 4 bytes).
    None,
}

impl Crc {
    /// Stable name: `ok`, `bad`, `none`.
    pub fn name(self) -> &'static str {
        match self {
            Crc::Ok => "ok",
            Crc::Bad => "bad",
            Crc::None => "none",
        }
    }
}

/// A frame's meaning.
#[derive(Debug, Clone, PartialEq)]
pub struct Meaning {
    /// In words.
    pub text: String,
    /// How it was understood.
    pub decoded_as: DecodedAs,
    /// Its CRC.
    pub crc: Crc,
}

/// The CRC state of `bytes` as a frame.
pub fn crc_of(bytes: &[u8]) -> Crc {
    if bytes.len() < 4 {
        Crc::None
    } else if frame_crc_ok(bytes) {
        Crc::Ok
    } else {
        Crc::Bad
    }
}

/// Decodes one record.
pub fn decode(record: &FrameRecord) -> Meaning {
    let bytes = record.bytes();
    match record.direction {
        Direction::Noise => Meaning {
            text: format!("{} stray byte{}", record.len, plural(record.len.into())),
            decoded_as: DecodedAs::None,
            crc: Crc::None,
        },
        Direction::Request => {
            let crc = crc_of(bytes);
            match pdu_of(bytes) {
                Some(pdu) => {
                    let (text, decoded_as) = request_text(pdu);
                    let text = if bytes.first() == Some(&0) {
                        format!("broadcast: {text}")
                    } else {
                        text
                    };
                    Meaning {
                        text,
                        decoded_as,
                        crc,
                    }
                }
                None => Meaning {
                    text: "too short to be a request".into(),
                    decoded_as: DecodedAs::None,
                    crc,
                },
            }
        }
        Direction::Reply => {
            let request_pdu = record.request_pdu();
            if record.outcome == FrameOutcome::Timeout && bytes.is_empty() {
                let (asked, _) = request_text(request_pdu);
                return Meaning {
                    text: format!("no reply to: {asked}"),
                    decoded_as: DecodedAs::None,
                    crc: Crc::None,
                };
            }
            let crc = crc_of(bytes);
            match pdu_of(bytes) {
                Some(pdu) => {
                    let (text, decoded_as) = reply_text(request_pdu, pdu);
                    Meaning {
                        text,
                        decoded_as,
                        crc,
                    }
                }
                None => Meaning {
                    text: format!(
                        "{} byte{}: not a whole frame",
                        bytes.len(),
                        plural(bytes.len())
                    ),
                    decoded_as: DecodedAs::None,
                    crc,
                },
            }
        }
    }
}

fn plural(n: usize) -> &'static str {
    if n == 1 { "" } else { "s" }
}

/// The PDU of a frame (unit and CRC stripped), if it can hold one.
fn pdu_of(frame: &[u8]) -> Option<&[u8]> {
    (frame.len() >= 4).then(|| &frame[1..frame.len() - 2])
}

/// The text of a request PDU.
pub fn request_text(pdu: &[u8]) -> (String, DecodedAs) {
    match DriveRequest::from_pdu(pdu) {
        Some(request) => (drive_request_text(&request), DecodedAs::Drive),
        None if pdu.is_empty() => ("unknown request".into(), DecodedAs::None),
        None => (modbus_request_text(pdu), DecodedAs::Modbus),
    }
}

/// A drive request in words, with its values in engineering units.
pub fn drive_request_text(request: &DriveRequest) -> String {
    let save = |s: bool| if s { ", saved to flash" } else { "" };
    match *request {
        DriveRequest::SetAddress { address } => format!("set address to {address}"),
        DriveRequest::Config(c) => format!("command {}", config_text(c)),
        DriveRequest::Speed { rpm } => format!("speed setpoint {rpm} rpm"),
        DriveRequest::Position { centideg } => {
            format!("position setpoint {:.2}°", f64::from(centideg) / 100.0)
        }
        DriveRequest::Torque { counts } => format!(
            "torque setpoint {:.2} A ({counts} counts)",
            crate::drive::units::counts_to_amps(counts)
        ),
        DriveRequest::ReadStatus => "read status".into(),
        DriveRequest::OverCurrent {
            limit_counts,
            stall_ms,
            save: s,
        } => format!(
            "over-current protection {:.2} A for {stall_ms} ms{}",
            f64::from(limit_counts) / crate::drive::units::COUNTS_PER_AMP,
            save(s)
        ),
        DriveRequest::SpeedRamp { alpha, save: s } => {
            format!("speed ramp alpha {alpha}{}", save(s))
        }
        DriveRequest::PositionRamp { alpha, save: s } => {
            format!("position ramp alpha {alpha}{}", save(s))
        }
        DriveRequest::LoadInertia { ratio, save: s } => {
            format!("load inertia {ratio} x rotor{}", save(s))
        }
        DriveRequest::Rs485Control { enabled } => format!(
            "RS-485 control {}",
            if enabled {
                "on (CAN ignored)"
            } else {
                "off (CAN controls)"
            }
        ),
    }
}

fn config_text(c: ConfigCommand) -> &'static str {
    match c {
        ConfigCommand::Activate => "activate",
        ConfigCommand::Deactivate => "deactivate",
        ConfigCommand::Calibrate => "calibrate encoder",
        ConfigCommand::FineTuneCalibration => "fine-tune calibration",
        ConfigCommand::SetZero => "set zero",
        ConfigCommand::EmergencyBrake => "emergency brake",
        ConfigCommand::FactoryReset => "factory reset",
        ConfigCommand::SoftReset => "soft reset",
        ConfigCommand::FaultReset => "fault reset",
        ConfigCommand::SpeedMode => "speed mode",
        ConfigCommand::PositionMode => "position mode",
        ConfigCommand::TorqueMode => "torque mode",
    }
}

/// A register address with the drive's name for it, if it has one.
fn register(address: u16) -> String {
    match Register::at(address) {
        Some(r) => format!("0x{address:04X} {}", r.name()),
        None => format!("0x{address:04X}"),
    }
}

/// A generic Modbus request in words.
pub fn modbus_request_text(pdu: &[u8]) -> String {
    let f = pdu[0];
    let name = function_name(f);
    match f {
        0x01..=0x04 => match (be_u16(pdu, 1), be_u16(pdu, 3)) {
            (Some(a), Some(n)) => format!("{name} {} x {n}", register(a)),
            _ => format!("{name} (short)"),
        },
        0x05 | 0x06 => match (be_u16(pdu, 1), be_u16(pdu, 3)) {
            (Some(a), Some(v)) => format!("{name} {} = 0x{v:04X} ({v})", register(a)),
            _ => format!("{name} (short)"),
        },
        0x0F | 0x10 => match (be_u16(pdu, 1), be_u16(pdu, 3)) {
            (Some(a), Some(n)) => {
                let mut text = format!("{name} {} x {n}", register(a));
                if f == 0x10 {
                    let values = pdu.get(6..).unwrap_or(&[]);
                    if !values.is_empty() {
                        text.push(':');
                        for pair in values.chunks(2) {
                            let _ = match pair {
                                [hi, lo] => {
                                    write!(text, " 0x{:04X}", u16::from_be_bytes([*hi, *lo]))
                                }
                                [b] => write!(text, " 0x{b:02X}"),
                                _ => Ok(()),
                            };
                        }
                    }
                }
                text
            }
            _ => format!("{name} (short)"),
        },
        _ => format!(
            "{name}, {} data byte{}",
            pdu.len() - 1,
            plural(pdu.len() - 1)
        ),
    }
}

/// The reply PDU `pdu` to the request PDU `request` (possibly empty), in
/// words.
pub fn reply_text(request: &[u8], pdu: &[u8]) -> (String, DecodedAs) {
    let Some(&f) = pdu.first() else {
        return ("empty reply".into(), DecodedAs::None);
    };
    if f & function::EXCEPTION_BIT != 0 {
        let code = ExceptionCode(pdu.get(1).copied().unwrap_or(0));
        return (
            format!(
                "exception 0x{:02X} ({}) to {}",
                code.0,
                code.name(),
                function_name(f & 0x7F)
            ),
            DecodedAs::Modbus,
        );
    }
    // The drive's own replies: the status block, echoes, acknowledgements.
    let drive_request = DriveRequest::from_pdu(request);
    if drive_request == Some(DriveRequest::ReadStatus)
        && f == function::READ_HOLDING_REGISTERS
        && let Some(status) = pdu.get(2..).and_then(Status::from_bytes)
    {
        return (status_text(&status), DecodedAs::Drive);
    }
    if let Some(req) = drive_request
        && req.is_write()
        && request.first() == Some(&f)
    {
        let confirms = match f {
            function::WRITE_SINGLE_REGISTER => pdu == request,
            _ => pdu.get(..5) == request.get(..5),
        };
        if confirms {
            return (
                format!("confirmed: {}", drive_request_text(&req)),
                DecodedAs::Drive,
            );
        }
    }
    let name = function_name(f);
    let text = match f {
        0x01..=0x04 => {
            let data = pdu.get(2..).unwrap_or(&[]);
            let mut text = format!("{name}: {} byte{}", data.len(), plural(data.len()));
            if f >= 0x03 && !data.is_empty() {
                text.push(':');
                for pair in data.chunks(2) {
                    let _ = match pair {
                        [hi, lo] => write!(text, " 0x{:04X}", u16::from_be_bytes([*hi, *lo])),
                        [b] => write!(text, " 0x{b:02X}"),
                        _ => Ok(()),
                    };
                }
            }
            text
        }
        0x05 | 0x06 => match (be_u16(pdu, 1), be_u16(pdu, 3)) {
            (Some(a), Some(v)) => format!("{name} echo {} = 0x{v:04X} ({v})", register(a)),
            _ => format!("{name} echo (short)"),
        },
        0x0F | 0x10 => match (be_u16(pdu, 1), be_u16(pdu, 3)) {
            (Some(a), Some(n)) => format!("{name} acknowledged {} x {n}", register(a)),
            _ => format!("{name} acknowledgement (short)"),
        },
        _ => format!(
            "{name}, {} data byte{}",
            pdu.len() - 1,
            plural(pdu.len() - 1)
        ),
    };
    (text, DecodedAs::Modbus)
}

/// The status block in words.
pub fn status_text(s: &Status) -> String {
    let mut flags = Vec::new();
    flags.push(if s.active() { "active" } else { "inactive" });
    if !s.calibrated() {
        flags.push("not calibrated");
    }
    if s.stalled() {
        flags.push("STALLED");
    }
    format!(
        "status: {} rpm, {:.2}°, turn {}, {:.2} A, {} V, {} °C, {}, {} mode, fault {}",
        s.speed_rpm,
        s.angle_deg(),
        s.turns,
        s.current_a(),
        s.voltage_v,
        s.temperature_c,
        flags.join(", "),
        s.mode().name(),
        s.fault().name()
    )
}

/// A function code in words.
pub fn function_name(f: u8) -> String {
    match function::label(f) {
        "other" => format!("function 0x{f:02X}"),
        label => label.replace('_', " "),
    }
}

/// Bytes as hex pairs separated by spaces: `01 03 00 C0`.
pub fn hex(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() * 3);
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            s.push(' ');
        }
        let _ = write!(s, "{b:02X}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::rtu_frame::encode;

    fn request(unit: u8, pdu: &[u8]) -> FrameRecord {
        let mut r = FrameRecord {
            unit,
            ..FrameRecord::default()
        };
        r.set_bytes(&encode(unit, pdu));
        r
    }

    fn reply(unit: u8, request_pdu: &[u8], frame: &[u8], outcome: FrameOutcome) -> FrameRecord {
        let mut r = FrameRecord {
            direction: Direction::Reply,
            unit,
            outcome,
            ..FrameRecord::default()
        };
        r.set_request(&encode(unit, request_pdu), true);
        r.set_bytes(frame);
        r
    }

    #[test]
    fn drive_messages_in_words() {
        // 01 06 00 06 00 64: speed setpoint 100 rpm (manual 1.4).
        let m = decode(&request(1, &[0x06, 0x00, 0x06, 0x00, 0x64]));
        assert_eq!(m.text, "speed setpoint 100 rpm");
        assert_eq!((m.decoded_as, m.crc), (DecodedAs::Drive, Crc::Ok));
        // CONFIG = 5: emergency brake.
        let m = decode(&request(2, &[0x06, 0x00, 0x02, 0x00, 0x05]));
        assert_eq!(m.text, "command emergency brake");
        // The status read (1.7) and its reply.
        let status_read = [0x03, 0x00, 0xC0, 0x00, 0x07];
        assert_eq!(decode(&request(1, &status_read)).text, "read status");
        let status = Status {
            turns: 3,
            angle_centideg: 9000,
            speed_rpm: 120,
            current_counts: 64,
            voltage_v: 24,
            temperature_c: 31,
            flags: 0x80 | 0x40 | (1 << 3),
        };
        let mut pdu = vec![0x03, 14];
        pdu.extend_from_slice(&status.to_bytes());
        let m = decode(&reply(1, &status_read, &encode(1, &pdu), FrameOutcome::Ok));
        assert_eq!(
            m.text,
            "status: 120 rpm, 90.00°, turn 3, 0.50 A, 24 V, 31 °C, active, speed mode, fault none"
        );
        // The echo of a write confirms it.
        let echo = [0x06, 0x00, 0x06, 0x00, 0x64];
        let m = decode(&reply(1, &echo, &encode(1, &echo), FrameOutcome::Ok));
        assert_eq!(m.text, "confirmed: speed setpoint 100 rpm");
        // A broadcast.
        let m = decode(&request(0, &[0x06, 0x00, 0x00, 0x00, 0x05]));
        assert_eq!(m.text, "broadcast: set address to 5");
    }

    #[test]
    fn generic_modbus_in_words() {
        let m = decode(&request(7, &[0x04, 0x01, 0x00, 0x00, 0x02]));
        assert_eq!(m.text, "read input registers 0x0100 x 2");
        assert_eq!(m.decoded_as, DecodedAs::Modbus);
        let m = decode(&request(7, &[0x03, 0x00, 0x06, 0x00, 0x01]));
        assert_eq!(m.text, "read holding registers 0x0006 SPEED_REF x 1");
        let m = decode(&request(7, &[0x2B, 0x0E, 0x01, 0x00]));
        assert_eq!(m.text, "encapsulated interface, 3 data bytes");
        let m = decode(&reply(
            7,
            &[0x03, 0x00, 0x06, 0x00, 0x01],
            &encode(7, &[0x83, 0x02]),
            FrameOutcome::Exception,
        ));
        assert_eq!(
            m.text,
            "exception 0x02 (illegal data address) to read holding registers"
        );
        let m = decode(&reply(
            7,
            &[0x03, 0x00, 0x06, 0x00, 0x01],
            &encode(7, &[0x03, 0x02, 0x00, 0x64]),
            FrameOutcome::Ok,
        ));
        assert_eq!(m.text, "read holding registers: 2 bytes: 0x0064");
    }

    #[test]
    fn faults_in_words() {
        let read = [0x03, 0x00, 0xC0, 0x00, 0x07];
        let m = decode(&reply(3, &read, &[], FrameOutcome::Timeout));
        assert_eq!(m.text, "no reply to: read status");
        assert_eq!(m.crc, Crc::None);
        let mut frame = encode(3, &[0x83, 0x02]);
        frame[3] ^= 0xFF;
        let m = decode(&reply(3, &read, &frame, FrameOutcome::CrcError));
        assert_eq!(m.crc, Crc::Bad);
        let m = decode(&reply(3, &read, &[0x03, 0x03], FrameOutcome::BadReply));
        assert_eq!(m.text, "2 bytes: not a whole frame");
        let noise = FrameRecord {
            direction: Direction::Noise,
            len: 3,
            ..FrameRecord::default()
        };
        assert_eq!(decode(&noise).text, "3 stray bytes");
        assert_eq!(hex(&[1, 0xC0, 0x0F]), "01 C0 0F");
    }
}
