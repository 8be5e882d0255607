//! Every golden frame of `tests/vectors/frames.tsv` (the maker's frames with
//! their CRCs), built and parsed byte for byte by the drive protocol.

use crate::support::vectors::{VECTORS, vector, vectors};
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest, Fault, Mode, ReplyError, Status};
use drivegate::modbus::ExceptionCode;
use drivegate::modbus::rtu_frame;

/// The request each request vector must encode from.
fn request_for(name: &str) -> Option<(u8, DriveRequest)> {
    let config = |c| Some((1, DriveRequest::Config(c)));
    match name {
        "set_address_5" => Some((0, DriveRequest::SetAddress { address: 5 })),
        "config_activate" => config(ConfigCommand::Activate),
        "config_deactivate" => config(ConfigCommand::Deactivate),
        "config_calibrate" => config(ConfigCommand::Calibrate),
        "config_calibration_fine_tune" => config(ConfigCommand::FineTuneCalibration),
        "config_set_zero" => config(ConfigCommand::SetZero),
        "config_emergency_brake" => config(ConfigCommand::EmergencyBrake),
        "config_factory_reset" => config(ConfigCommand::FactoryReset),
        "config_soft_reset" => config(ConfigCommand::SoftReset),
        "config_fault_reset" => config(ConfigCommand::FaultReset),
        "config_speed_mode" => config(ConfigCommand::SpeedMode),
        "config_position_mode" => config(ConfigCommand::PositionMode),
        "config_torque_mode" => config(ConfigCommand::TorqueMode),
        "speed_100rpm" => Some((1, DriveRequest::Speed { rpm: 100 })),
        "speed_minus_100rpm" => Some((1, DriveRequest::Speed { rpm: -100 })),
        "speed_min" => Some((1, DriveRequest::Speed { rpm: -2048 })),
        "position_90deg" => Some((1, DriveRequest::Position { centideg: 9000 })),
        "position_minus_180deg" => Some((1, DriveRequest::Position { centideg: -18000 })),
        "torque_1A" => Some((1, DriveRequest::Torque { counts: 128 })),
        "torque_minus_half_A" => Some((1, DriveRequest::Torque { counts: -64 })),
        "use_485_on" => Some((7, DriveRequest::Rs485Control { enabled: true })),
        "status_read" => Some((1, DriveRequest::ReadStatus)),
        "overcurrent_set" => Some((
            1,
            DriveRequest::OverCurrent {
                limit_counts: 128,
                stall_ms: 3000,
                save: false,
            },
        )),
        "speed_ramp_default" => Some((
            1,
            DriveRequest::SpeedRamp {
                alpha: 500_000,
                save: true,
            },
        )),
        "position_ramp_200" => Some((
            1,
            DriveRequest::PositionRamp {
                alpha: 200,
                save: false,
            },
        )),
        "inertia_10" => Some((
            1,
            DriveRequest::LoadInertia {
                ratio: 10,
                save: true,
            },
        )),
        _ => None,
    }
}

#[test]
fn the_project_copy_matches_the_shared_vectors() {
    // CI checks out the shared material beside the project; when it is there
    // the copy compiled into these tests must not have drifted from it.
    let shared =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/vectors/frames.tsv");
    if let Ok(text) = std::fs::read_to_string(&shared) {
        assert_eq!(
            text,
            VECTORS,
            "tests/vectors/frames.tsv differs from {}",
            shared.display()
        );
    }
}

#[test]
fn every_vector_has_a_valid_crc() {
    let all = vectors();
    assert_eq!(all.len(), 33, "frames.tsv changed: update these tests");
    for v in &all {
        assert!(rtu_frame::decode(&v.bytes).is_ok(), "{}: bad CRC", v.name);
    }
}

#[test]
fn every_request_vector_is_built_byte_for_byte() {
    let mut built = 0;
    for v in vectors() {
        if let Some((unit, request)) = request_for(&v.name) {
            assert_eq!(request.frame(unit).unwrap(), v.bytes, "{}", v.name);
            // ... and read back as the same request.
            let (_, pdu) = rtu_frame::decode(&v.bytes).unwrap();
            assert_eq!(DriveRequest::from_pdu(pdu), Some(request), "{}", v.name);
            built += 1;
        }
    }
    assert_eq!(built, 26, "every request vector must be covered");
}

#[test]
fn echoes_confirm_their_writes() {
    for v in vectors() {
        if let Some((_, request)) = request_for(&v.name)
            && request.reply_len() == Some(8)
            && v.bytes[1] == 0x06
        {
            let (_, pdu) = rtu_frame::decode(&v.bytes).unwrap();
            assert_eq!(
                request.parse_reply(pdu),
                Ok(DriveReply::Confirmed),
                "{}",
                v.name
            );
        }
    }
}

#[test]
fn block_write_acknowledgements() {
    for (request_name, ack_name) in [
        ("overcurrent_set", "overcurrent_ack"),
        ("speed_ramp_default", "speed_ramp_ack"),
        ("position_ramp_200", "position_ramp_ack"),
        ("inertia_10", "inertia_ack"),
    ] {
        let (_, request) = request_for(request_name).unwrap();
        let ack = vector(ack_name);
        assert_eq!(request.reply_len(), Some(ack.len()), "{ack_name}");
        let (unit, pdu) = rtu_frame::decode(&ack).unwrap();
        assert_eq!(unit, 1);
        assert_eq!(
            request.parse_reply(pdu),
            Ok(DriveReply::Confirmed),
            "{ack_name}"
        );
        // An ack for another block does not confirm this one.
        let (_, other) = request_for("inertia_10").unwrap();
        if request_name != "inertia_10" {
            assert!(matches!(
                other.parse_reply(pdu),
                Err(ReplyError::Mismatch(_))
            ));
        }
    }
}

#[test]
fn status_replies_decode() {
    let reply = vector("status_reply");
    assert_eq!(DriveRequest::ReadStatus.reply_len(), Some(reply.len()));
    let (unit, pdu) = rtu_frame::decode(&reply).unwrap();
    assert_eq!(unit, 1);
    let DriveReply::Status(s) = DriveRequest::ReadStatus.parse_reply(pdu).unwrap() else {
        panic!("not a status")
    };
    assert_eq!(
        (
            s.turns,
            s.angle_deg(),
            s.speed_rpm,
            s.current_counts,
            s.current_a()
        ),
        (3, 45.0, -120, 256, 2.0)
    );
    assert_eq!((s.voltage_v, s.temperature_c, s.flags), (24, 41, 0x00C8));
    assert!(s.active() && s.calibrated() && !s.stalled());
    assert_eq!((s.mode(), s.fault()), (Mode::Speed, Fault::None));

    let reply = vector("status_reply_faulted");
    let (unit, pdu) = rtu_frame::decode(&reply).unwrap();
    assert_eq!(unit, 2);
    let DriveReply::Status(s) = DriveRequest::ReadStatus.parse_reply(pdu).unwrap() else {
        panic!("not a status")
    };
    assert_eq!((s.turns, s.angle_deg(), s.speed_rpm), (65535, -180.0, 0));
    assert_eq!(
        (s.current_counts, s.voltage_v, s.temperature_c),
        (-2048, 255, -128)
    );
    assert!(s.active() && s.calibrated() && s.stalled());
    assert_eq!(
        (s.mode(), s.fault()),
        (Mode::Position, Fault::OverTemperature)
    );
    assert_eq!(s.fault().name(), "over_temperature");

    // Re-encoding the decoded status gives the same frame back.
    let mut rebuilt = vec![0x03, 0x0E];
    rebuilt.extend_from_slice(&s.to_bytes());
    assert_eq!(rtu_frame::encode(2, &rebuilt), reply);
    let _: Status = s;
}

#[test]
fn exception_reply_decodes() {
    let reply = vector("exception_illegal_address");
    assert_eq!(
        rtu_frame::response_length(&reply),
        rtu_frame::FrameLength::Known(reply.len())
    );
    let (_, pdu) = rtu_frame::decode(&reply).unwrap();
    assert_eq!(
        DriveRequest::ReadStatus.parse_reply(pdu),
        Err(ReplyError::Exception(ExceptionCode::ILLEGAL_DATA_ADDRESS))
    );
}

#[test]
fn reply_lengths_frame_every_reply_vector() {
    for v in vectors() {
        let len = rtu_frame::response_length(&v.bytes[..3.min(v.bytes.len())]);
        if v.name.ends_with("_ack")
            || v.name.starts_with("status_reply")
            || v.name.starts_with("exception")
        {
            assert_eq!(
                len,
                rtu_frame::FrameLength::Known(v.bytes.len()),
                "{}",
                v.name
            );
        }
        let req_len = rtu_frame::request_length(&v.bytes[..7.min(v.bytes.len())]);
        if request_for(&v.name).is_some() {
            assert_eq!(
                req_len,
                rtu_frame::FrameLength::Known(v.bytes.len()),
                "{}",
                v.name
            );
        }
    }
}
