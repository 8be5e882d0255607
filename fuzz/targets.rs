// The fuzz targets' bodies. Included both by the cargo-fuzz binaries in
// fuzz/fuzz_targets/ and by tests/protocol/fuzz_corpus.rs, which replays the
// committed corpus in every `cargo test`.

/// Arbitrary bytes arriving where the RTU master expects the reply to a
/// request: framing, the reply check, the drive-level decoding.
pub fn rtu_reply(data: &[u8]) {
    use drivegate::drive::{ConfigCommand, DriveRequest};
    use drivegate::modbus::{reply, rtu_frame};
    let Some((&selector, frame)) = data.split_first() else {
        return;
    };
    let requests = [
        DriveRequest::ReadStatus,
        DriveRequest::Speed { rpm: 100 },
        DriveRequest::Config(ConfigCommand::Activate),
        DriveRequest::OverCurrent {
            limit_counts: 128,
            stall_ms: 3000,
            save: false,
        },
        DriveRequest::LoadInertia { ratio: 10, save: true },
    ];
    let request = requests[usize::from(selector) % requests.len()];
    let Ok(pdu) = request.pdu() else {
        return;
    };
    let _ = rtu_frame::response_length(frame);
    // As received, and with a valid CRC so the checks behind it are reached.
    let with_crc = frame
        .split_first()
        .map(|(&unit, rest)| rtu_frame::encode(unit, rest))
        .unwrap_or_default();
    for candidate in [frame, &with_crc[..]] {
        if let Ok(reply) = reply::check(1, &pdu, candidate) {
            let _ = request.parse_reply(&reply);
        }
        if let Ok((_, reply)) = rtu_frame::decode(candidate) {
            let _ = request.parse_reply(reply);
            let _ = DriveRequest::from_pdu(reply);
        }
    }
}

/// Arbitrary text as a configuration file.
pub fn config(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = drivegate::config::Config::parse(text, "fuzz.toml");
    }
}

/// Arbitrary bytes arriving at the simulated drives as a request frame
/// (third-party masters can send them anything).
pub fn sim_request(data: &[u8]) {
    use drivegate::modbus::rtu_frame;
    use drivegate::sim::SimConfig;
    use drivegate::sim::bus::Bus;
    let now = std::time::Instant::now();
    let mut bus = Bus::new(&SimConfig::for_units(1..=2), now);
    let mut reply = Vec::new();
    // Each input is a sequence of frames separated by 0xFF 0xFF; each frame
    // goes in as received and with a valid CRC.
    for chunk in data.split(|&b| b == 0xFF).filter(|c| !c.is_empty()) {
        let _ = rtu_frame::request_length(chunk);
        reply.clear();
        let _ = bus.request(chunk, now, None, &mut reply);
        if let Some((&unit, rest)) = chunk.split_first() {
            let framed = rtu_frame::encode(unit % 4, rest);
            reply.clear();
            let collisions = bus.stats().collisions;
            let _ = bus.request(&framed, now, None, &mut reply);
            // Two drives given one address by a broadcast both answer, as on
            // a real bus: that garbled reply is counted as a collision.
            if !reply.is_empty() && bus.stats().collisions == collisions {
                assert!(rtu_frame::decode(&reply).is_ok(), "the simulator sent a bad frame");
            }
        }
    }
}

/// Arbitrary bytes from a Modbus TCP client: the MBAP framing and every
/// check a request goes through before the bus (shape, read-only class,
/// broadcast, the write decoder and its meaning, the polled copy).
pub fn mbap(data: &[u8]) {
    use drivegate::bus::DriveSnapshot;
    use drivegate::modbus_tcp::{mbap, polled_copy, request};
    let mut rest = data;
    while let Ok(Some((frame, used))) = mbap::parse(rest) {
        // A frame re-encodes to exactly the bytes it came from.
        let mut again = Vec::new();
        mbap::encode(frame.transaction, frame.unit, &frame.pdu, &mut again);
        assert_eq!(again, rest[..used], "MBAP frame does not round-trip");
        let _ = request::check_shape(&frame.pdu);
        let _ = request::reads_only(&frame.pdu);
        let _ = request::broadcastable(&frame.pdu);
        // What the control core makes of it as a write, and its words.
        let write = drivegate::control::Write::pdu(frame.pdu.clone());
        let _ = write.meaning();
        let _ = write.describe();
        // What goes to the drive for it, and the client's reply from that.
        if let Ok(sent) = write.encode() {
            let _ = request::reply_to(&frame.pdu, sent);
        }
        let _ = polled_copy::status_registers(&frame.pdu);
        let snapshot = DriveSnapshot {
            unit: frame.unit,
            status: Some(drivegate::drive::Status::default()),
            seen_at: Some(std::time::SystemTime::now()),
            seen_instant: Some(std::time::Instant::now()),
            link: drivegate::bus::cache::Link::Online,
            consecutive_failures: 0,
        };
        let live = drivegate::bus::freshness::Verdict {
            freshness: drivegate::bus::freshness::Freshness::Live,
            since: None,
            age: Some(std::time::Duration::ZERO),
            cause: drivegate::bus::freshness::Cause::Polled,
            stale_at: None,
        };
        if let Some(reply) =
            polled_copy::answer(&frame.pdu, &snapshot, &live, std::time::Duration::from_secs(1))
        {
            assert!(!reply.is_empty());
        }
        rest = &rest[used..];
    }
}

/// Arbitrary bytes as the JSON body of an API request (the first byte picks
/// the route): the request types' parsing, then the range checks and unit
/// conversions behind them. What passes the checks must be within the
/// range the OpenAPI document states and make a frame the drive accepts,
/// which decodes back to the same request.
pub fn http_body(data: &[u8]) {
    use drivegate::api::body_schemas;
    use drivegate::api::buses::{AddressBody, ScanBody};
    use drivegate::api::config_commands::ModeBody;
    use drivegate::api::setpoints::{RenewBody, SetpointBody};
    use drivegate::api::settings::{
        InertiaBody, PositionRampBody, ProtectionBody, Rs485Body, SpeedRampBody,
    };
    use drivegate::api::stream::ClientMessage;
    use drivegate::drive::{ConfigCommand, DriveRequest, units};

    fn sent(request: DriveRequest) {
        let pdu = request.pdu().expect("a checked request encodes");
        assert_eq!(DriveRequest::from_pdu(&pdu), Some(request), "{pdu:02X?}");
    }

    let Some((&selector, json)) = data.split_first() else {
        return;
    };
    match selector % 8 {
        0 => {
            let Ok(body) = serde_json::from_slice::<SetpointBody>(json) else {
                return;
            };
            match body.request() {
                Ok(request) => {
                    if let Some(rpm) = body.speed_rpm {
                        let (lo, hi) = body_schemas::SPEED_RPM_EXCLUSIVE;
                        assert!(rpm > lo && rpm < hi, "{rpm} rpm accepted");
                    }
                    if let Some(deg) = body.position_deg {
                        let (lo, hi) = body_schemas::POSITION_DEG;
                        assert!(deg >= lo && deg <= hi, "{deg} deg accepted");
                    }
                    if let Some(a) = body.torque_a {
                        let (lo, hi) = body_schemas::TORQUE_A;
                        assert!(a >= lo && a <= hi, "{a} A accepted");
                    }
                    sent(request);
                }
                Err(problem) => {
                    assert!(matches!(problem.status, 400 | 422), "{problem:?}");
                    if problem.status == 422 {
                        let range = problem.valid_range.clone().expect("422 names its range");
                        assert!(range.min <= range.max);
                    }
                }
            }
        }
        1 => {
            let Ok(body) = serde_json::from_slice::<ProtectionBody>(json) else {
                return;
            };
            let limit = match (body.limit_a, body.limit_counts) {
                (Some(a), None) => units::current_limit(a),
                (None, Some(c)) => units::current_limit_counts(c),
                _ => return,
            };
            if let (Ok(limit_counts), Ok(stall_ms)) = (limit, units::stall_time_ms(body.stall_ms)) {
                sent(DriveRequest::OverCurrent {
                    limit_counts,
                    stall_ms,
                    save: body.save,
                });
            }
        }
        2 => {
            let Ok(body) = serde_json::from_slice::<SpeedRampBody>(json) else {
                return;
            };
            if let (Some(t), Some(rpm)) = (body.time_s, body.step_rpm)
                && let Ok(alpha) = units::speed_ramp_alpha(t, rpm, 3.75)
            {
                assert!(alpha >= 1);
                let time = units::speed_ramp_time(alpha, rpm, 3.75).expect("a ramp");
                assert!(time.is_finite() && time > 0.0);
                sent(DriveRequest::SpeedRamp { alpha, save: body.save });
            }
        }
        3 => {
            let Ok(body) = serde_json::from_slice::<PositionRampBody>(json) else {
                return;
            };
            if let (Some(t), Some(deg)) = (body.time_s, body.step_deg)
                && let Ok(alpha) = units::position_ramp_alpha(t, deg)
            {
                assert!(alpha >= 1);
                let time = units::position_ramp_time(alpha, deg).expect("a ramp");
                assert!(time.is_finite() && time > 0.0);
                sent(DriveRequest::PositionRamp { alpha, save: body.save });
            }
        }
        4 => {
            if let Ok(body) = serde_json::from_slice::<InertiaBody>(json)
                && let Ok(ratio) = units::inertia_ratio(body.ratio)
            {
                sent(DriveRequest::LoadInertia { ratio, save: body.save });
            }
        }
        5 => {
            let _ = serde_json::from_slice::<Option<ScanBody>>(json);
            if let Ok(body) = serde_json::from_slice::<AddressBody>(json)
                && let Ok(address) = u8::try_from(body.address)
                && address >= 1
            {
                sent(DriveRequest::SetAddress { address });
            }
        }
        6 => {
            if let Ok(body) = serde_json::from_slice::<ModeBody>(json)
                && let Some(mode) = ConfigCommand::mode_named(&body.mode)
            {
                sent(DriveRequest::Config(mode));
            }
            let _ = serde_json::from_slice::<Option<RenewBody>>(json);
            if let Ok(body) = serde_json::from_slice::<Rs485Body>(json) {
                sent(DriveRequest::Rs485Control { enabled: body.enabled });
            }
        }
        _ => {
            let _ = serde_json::from_slice::<ClientMessage>(json);
        }
    }
}
