// The fuzz targets' bodies. Included both by the cargo-fuzz binaries in
// fuzz/fuzz_targets/ and by tests/fuzz_corpus.rs, which replays the
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
        let _ = bus.request(chunk, now, &mut reply);
        if let Some((&unit, rest)) = chunk.split_first() {
            let framed = rtu_frame::encode(unit % 4, rest);
            reply.clear();
            let collisions = bus.stats().collisions;
            let _ = bus.request(&framed, now, &mut reply);
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
/// broadcast, the polled copy).
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
        let _ = request::describe(&frame.pdu);
        let _ = polled_copy::status_registers(&frame.pdu);
        let snapshot = DriveSnapshot {
            unit: frame.unit,
            status: Some(drivegate::drive::Status::default()),
            seen_at: Some(std::time::SystemTime::now()),
            seen_instant: Some(std::time::Instant::now()),
            link: drivegate::bus::cache::Link::Online,
            consecutive_failures: 0,
        };
        if let Some(reply) = polled_copy::answer(&frame.pdu, &snapshot, std::time::Duration::from_secs(1)) {
            assert!(!reply.is_empty());
        }
        rest = &rest[used..];
    }
}
