//! The monitor's frames as a PCAP file that Wireshark and `tshark` decode
//! as Modbus RTU.
//!
//! A PCAP has no link type for a serial line that Wireshark decodes as
//! Modbus RTU out of the box, so each RTU frame (unit, PDU, CRC, exactly as
//! on the wire) is the payload of a UDP datagram over raw IPv4 (link type
//! 101), which Wireshark's `mbrtu` dissector takes once its UDP port is set
//! to 502; it then tells queries (to 502) from responses (from 502) by the
//! port, which it cannot do from an RTU frame alone (a write's echo is the
//! write):
//!
//! ```text
//! tshark -r line1.pcap -o mbrtu.udp.port:502
//! ```
//!
//! (In Wireshark: Preferences, Protocols, Modbus/RTU, UDP port 502.)
//!
//! The addresses and ports are labels, not a network: drivegate is
//! 127.0.0.1 port 49152, unit N is 127.0.1.N port 502 (so requests go to
//! port 502 and Wireshark shows them as queries, replies as responses),
//! broadcasts go to 127.0.1.0. Stray bytes (noise) come from 127.0.1.255
//! port 9 (discard) to drivegate, so they are listed but not taken for
//! Modbus. Timeouts have no bytes and are not in the file; the CSV and
//! JSON downloads list them. Times are the frames' wall-clock times in µs.

use std::time::UNIX_EPOCH;

use super::record::{Direction, FrameRecord};
use super::view::WallClock;

/// LINKTYPE_RAW: each packet is an IPv4 (or IPv6) datagram.
pub const LINKTYPE_RAW: u32 = 101;
/// The UDP port frames to and from the drives use (Modbus's).
pub const MODBUS_PORT: u16 = 502;
/// drivegate's UDP port in the file.
pub const MASTER_PORT: u16 = 49152;
/// The port stray bytes come from (discard): not decoded as Modbus.
pub const NOISE_PORT: u16 = 9;

const MASTER_IP: [u8; 4] = [127, 0, 0, 1];
const NOISE_IP: [u8; 4] = [127, 0, 1, 255];

fn unit_ip(unit: u8) -> [u8; 4] {
    [127, 0, 1, unit]
}

/// Writes the PCAP global header (microsecond timestamps, raw IP).
pub fn write_header(out: &mut Vec<u8>) {
    out.extend_from_slice(&0xA1B2_C3D4u32.to_le_bytes()); // magic, µs
    out.extend_from_slice(&2u16.to_le_bytes()); // version 2.4
    out.extend_from_slice(&4u16.to_le_bytes());
    out.extend_from_slice(&0i32.to_le_bytes()); // UTC
    out.extend_from_slice(&0u32.to_le_bytes()); // accuracy
    out.extend_from_slice(&65_535u32.to_le_bytes()); // snap length
    out.extend_from_slice(&LINKTYPE_RAW.to_le_bytes());
}

/// The IPv4 header checksum (RFC 791): one's complement of the one's
/// complement sum of the header's 16-bit words.
fn ip_checksum(header: &[u8]) -> u16 {
    let mut sum: u32 = header
        .chunks(2)
        .map(|w| u32::from(u16::from_be_bytes([w[0], *w.get(1).unwrap_or(&0)])))
        .sum();
    while sum > 0xFFFF {
        sum = (sum & 0xFFFF) + (sum >> 16);
    }
    !(sum as u16)
}

/// Appends `record` as one packet; a record without bytes (a timeout) is
/// skipped. Returns whether a packet was written.
pub fn write_record(out: &mut Vec<u8>, record: &FrameRecord, clock: &WallClock) -> bool {
    let payload = record.bytes();
    if payload.is_empty() {
        return false;
    }
    let (src, sport, dst, dport) = match record.direction {
        Direction::Request => (MASTER_IP, MASTER_PORT, unit_ip(record.unit), MODBUS_PORT),
        Direction::Reply => (unit_ip(record.unit), MODBUS_PORT, MASTER_IP, MASTER_PORT),
        Direction::Noise => (NOISE_IP, NOISE_PORT, MASTER_IP, MASTER_PORT),
    };
    let udp_len = 8 + payload.len();
    let ip_len = 20 + udp_len;
    let since = clock
        .at(record.at_ns)
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default();
    // Packet record header: seconds, µs, captured and original length.
    out.extend_from_slice(&(since.as_secs() as u32).to_le_bytes());
    out.extend_from_slice(&since.subsec_micros().to_le_bytes());
    out.extend_from_slice(&(ip_len as u32).to_le_bytes());
    out.extend_from_slice(&(ip_len as u32).to_le_bytes());
    // IPv4: version 4, 20-byte header, no options, not fragmented, TTL 64, UDP.
    let mut ip = [0u8; 20];
    ip[0] = 0x45;
    ip[2..4].copy_from_slice(&(ip_len as u16).to_be_bytes());
    ip[4..6].copy_from_slice(&(record.seq as u16).to_be_bytes());
    ip[6] = 0x40; // don't fragment
    ip[8] = 64;
    ip[9] = 17;
    ip[12..16].copy_from_slice(&src);
    ip[16..20].copy_from_slice(&dst);
    let checksum = ip_checksum(&ip);
    ip[10..12].copy_from_slice(&checksum.to_be_bytes());
    out.extend_from_slice(&ip);
    // UDP, without a checksum (allowed over IPv4).
    out.extend_from_slice(&sport.to_be_bytes());
    out.extend_from_slice(&dport.to_be_bytes());
    out.extend_from_slice(&(udp_len as u16).to_be_bytes());
    out.extend_from_slice(&0u16.to_be_bytes());
    out.extend_from_slice(payload);
    true
}

/// A whole file of `records`.
pub fn file<'a>(records: impl IntoIterator<Item = &'a FrameRecord>, clock: &WallClock) -> Vec<u8> {
    let mut out = Vec::new();
    write_header(&mut out);
    for r in records {
        write_record(&mut out, r, clock);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::rtu_frame::encode;
    use crate::monitor::record::FrameOutcome;
    use std::time::Duration;

    #[test]
    fn one_request_as_ipv4_udp_to_port_502() {
        let mut r = FrameRecord {
            seq: 7,
            at_ns: 2_000_123_000,
            unit: 3,
            ..FrameRecord::default()
        };
        let frame = encode(3, &[0x03, 0x00, 0xC0, 0x00, 0x07]);
        r.set_bytes(&frame);
        let clock = WallClock {
            epoch: UNIX_EPOCH + Duration::from_secs(1_000),
            char_ns: 86_805,
        };
        let bytes = file([&r], &clock);
        assert_eq!(&bytes[..4], &[0xD4, 0xC3, 0xB2, 0xA1]);
        assert_eq!(u32::from_le_bytes(bytes[20..24].try_into().unwrap()), 101);
        let packet = &bytes[24..];
        assert_eq!(u32::from_le_bytes(packet[0..4].try_into().unwrap()), 1_002);
        assert_eq!(u32::from_le_bytes(packet[4..8].try_into().unwrap()), 123);
        let len = u32::from_le_bytes(packet[8..12].try_into().unwrap()) as usize;
        assert_eq!(len, 20 + 8 + frame.len());
        let ip = &packet[16..];
        assert_eq!(ip.len(), len);
        assert_eq!(ip_checksum(&ip[..20]), 0, "a valid header sums to zero");
        assert_eq!(&ip[16..20], &[127, 0, 1, 3]);
        assert_eq!(u16::from_be_bytes([ip[22], ip[23]]), 502);
        assert_eq!(&ip[28..], frame.as_slice());
    }

    #[test]
    fn timeouts_are_left_out() {
        let r = FrameRecord {
            direction: Direction::Reply,
            outcome: FrameOutcome::Timeout,
            ..FrameRecord::default()
        };
        let clock = WallClock {
            epoch: UNIX_EPOCH,
            char_ns: 86_805,
        };
        assert_eq!(file([&r], &clock).len(), 24);
    }
}
