//! Property tests of the pure protocol code: encode/decode round trips and
//! decoders that never panic on arbitrary bytes.

use drivegate::drive::units;
use drivegate::drive::{ConfigCommand, DriveReply, DriveRequest, Register, Status};
use drivegate::modbus::rtu_frame::{self, FrameLength};
use proptest::prelude::*;

fn any_request() -> impl Strategy<Value = DriveRequest> {
    prop_oneof![
        (1u8..=255).prop_map(|address| DriveRequest::SetAddress { address }),
        proptest::sample::select(ConfigCommand::ALL.to_vec()).prop_map(DriveRequest::Config),
        (-2048i16..=2047).prop_map(|rpm| DriveRequest::Speed { rpm }),
        (-18000i16..=18000).prop_map(|centideg| DriveRequest::Position { centideg }),
        (-2048i16..=2047).prop_map(|counts| DriveRequest::Torque { counts }),
        Just(DriveRequest::ReadStatus),
        (0u16..=2047, 0u16..=60000, any::<bool>()).prop_map(|(limit_counts, stall_ms, save)| {
            DriveRequest::OverCurrent {
                limit_counts,
                stall_ms,
                save,
            }
        }),
        (any::<u32>(), any::<bool>())
            .prop_map(|(alpha, save)| DriveRequest::SpeedRamp { alpha, save }),
        (any::<u32>(), any::<bool>())
            .prop_map(|(alpha, save)| DriveRequest::PositionRamp { alpha, save }),
        (1u16..=65535, any::<bool>())
            .prop_map(|(ratio, save)| DriveRequest::LoadInertia { ratio, save }),
        any::<bool>().prop_map(|enabled| DriveRequest::Rs485Control { enabled }),
    ]
}

proptest! {
    #[test]
    fn requests_round_trip_through_frames(request in any_request(), unit in 1u8..=255) {
        let frame = request.frame(unit).unwrap();
        let (got_unit, pdu) = rtu_frame::decode(&frame).unwrap();
        prop_assert_eq!(got_unit, if request.is_broadcast() { 0 } else { unit });
        prop_assert_eq!(DriveRequest::from_pdu(pdu), Some(request));
        prop_assert_eq!(rtu_frame::request_length(&frame), FrameLength::Known(frame.len()));
    }

    #[test]
    fn a_valid_echo_confirms_and_any_changed_byte_does_not(request in any_request(), flip in 0usize..16, bit in 0u8..8) {
        prop_assume!(!request.is_broadcast() && request != DriveRequest::ReadStatus);
        let pdu = request.pdu().unwrap();
        let reply = if pdu[0] == 0x06 { pdu.clone() } else { pdu[..5].to_vec() };
        prop_assert_eq!(request.parse_reply(&reply), Ok(DriveReply::Confirmed));
        let mut bad = reply.clone();
        let i = flip % bad.len();
        bad[i] ^= 1 << bit;
        prop_assert_ne!(request.parse_reply(&bad), Ok(DriveReply::Confirmed));
    }

    #[test]
    fn status_round_trips(regs in any::<[u16; 7]>()) {
        let s = Status::from_registers(regs);
        prop_assert_eq!(s.to_registers(), regs);
        prop_assert_eq!(Status::from_bytes(&s.to_bytes()), Some(s));
    }

    #[test]
    fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = rtu_frame::decode(&bytes);
        let _ = rtu_frame::response_length(&bytes);
        let _ = rtu_frame::request_length(&bytes);
        let _ = DriveRequest::from_pdu(&bytes);
        let _ = DriveRequest::ReadStatus.parse_reply(&bytes);
        let _ = DriveRequest::Speed { rpm: 1 }.parse_reply(&bytes);
        let _ = Status::from_bytes(&bytes);
        if let Some(len) = bytes.first() {
            let _ = Register::block(u16::from(*len) * 2, bytes.len() as u16);
        }
    }

    #[test]
    fn corrupted_frames_fail_the_crc(request in any_request(), unit in 1u8..=255, flip in 0usize..64, bit in 0u8..8) {
        let mut frame = request.frame(unit).unwrap();
        let i = flip % frame.len();
        frame[i] ^= 1 << bit;
        prop_assert!(rtu_frame::decode(&frame).is_err());
    }

    #[test]
    fn speed_setpoints_round_trip(rpm in -2048i16..=2047) {
        prop_assert_eq!(units::speed_setpoint(f64::from(rpm)), Ok(rpm));
    }

    #[test]
    fn positions_round_trip(centideg in -18000i16..=18000) {
        let degrees = f64::from(centideg) / 100.0;
        prop_assert_eq!(units::position_setpoint(degrees), Ok(centideg));
        prop_assert_eq!(units::centideg_to_degrees(centideg), degrees);
    }

    #[test]
    fn currents_round_trip(counts in -2048i16..=2047) {
        prop_assert_eq!(units::torque_setpoint(units::counts_to_amps(counts)), Ok(counts));
    }

    #[test]
    fn out_of_range_values_are_refused(rpm in prop_oneof![-1.0e6..-2048.6f64, 2047.6..1.0e6f64]) {
        let err = units::speed_setpoint(rpm).unwrap_err();
        prop_assert_eq!((err.min, err.max), (-2048.0, 2047.0));
    }

    #[test]
    fn speed_ramp_alpha_inverts_formula_2(alpha in 1u32..=50_000_000, rpm in 1.0..2047.0f64, ratio in 0.1..100.0f64) {
        let t = units::speed_ramp_time(alpha, rpm, ratio).unwrap();
        if let Ok(solved) = units::speed_ramp_alpha(t, rpm, ratio) {
            // Rounding to an integer alpha moves it by at most 0.5 (+ float noise).
            prop_assert!((f64::from(solved) - f64::from(alpha)).abs() <= 0.5 + 1e-6 * f64::from(alpha));
        }
    }

    #[test]
    fn position_ramp_alpha_inverts_formula_3(alpha in 1u32..=50_000_000, degrees in 0.01..360.0f64) {
        let t = units::position_ramp_time(alpha, degrees).unwrap();
        let solved = units::position_ramp_alpha(t, degrees).unwrap();
        prop_assert!((f64::from(solved) - f64::from(alpha)).abs() <= 0.5 + 1e-6 * f64::from(alpha));
    }
}
