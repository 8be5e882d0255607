//! Status reads answered from the latest poll instead of the bus.
//!
//! A dashboard polling the status block at 10 Hz per drive would otherwise
//! take a large share of a 115200-baud bus. The scheduler polls every drive
//! anyway, so a read of registers inside 0x00C0..=0x00CC (manual 1.7) can be
//! answered from that copy, if it is younger than the configured maximum
//! age and the drive's data is live as the bus judges it
//! ([`crate::bus::freshness`]): its port up, the drive answering its polls
//! within their period. A copy is never answered for a drive whose wire is
//! gone, however young: the read goes to the bus instead, which refuses it
//! unsent while the port is down (0x0A) and reports a drive that does not
//! answer (0x0B), as for any read. Addressing is the drive's: registers sit
//! at even byte addresses and quantities count 16-bit words, so a
//! one-register read at 0x00C2 is ANGLE.

use std::time::Duration;

use crate::bus::cache::{DriveSnapshot, Link};
use crate::bus::freshness::Verdict;
use crate::drive::registers::{STATUS_BLOCK_LEN, STATUS_BLOCK_START};
use crate::modbus::function::{READ_HOLDING_REGISTERS, be_u16};

/// The registers of the status block a read asks for: (index of the first
/// register, count), if the read lies wholly inside the block.
pub fn status_registers(pdu: &[u8]) -> Option<(usize, usize)> {
    if pdu.len() != 5 || pdu[0] != READ_HOLDING_REGISTERS {
        return None;
    }
    let (start, count) = (be_u16(pdu, 1)?, be_u16(pdu, 3)?);
    let offset = start.checked_sub(STATUS_BLOCK_START)?;
    if offset % 2 != 0 || count == 0 {
        return None;
    }
    let first = usize::from(offset / 2);
    let count = usize::from(count);
    (first + count <= usize::from(STATUS_BLOCK_LEN)).then_some((first, count))
}

/// The reply to `pdu` from `snapshot`, if it is a status read the copy can
/// answer: the drive's data `live` by `freshness` (judged after the
/// snapshot was taken) and the copy at most `max_age` old.
pub fn answer(
    pdu: &[u8],
    snapshot: &DriveSnapshot,
    freshness: &Verdict,
    max_age: Duration,
) -> Option<Vec<u8>> {
    let (first, count) = status_registers(pdu)?;
    if !freshness.freshness.is_live() || snapshot.link == Link::Offline || snapshot.age()? > max_age
    {
        return None;
    }
    let registers = snapshot.status?.to_registers();
    let mut reply = Vec::with_capacity(2 + 2 * count);
    reply.push(READ_HOLDING_REGISTERS);
    reply.push((2 * count) as u8);
    for register in &registers[first..first + count] {
        reply.extend_from_slice(&register.to_be_bytes());
    }
    Some(reply)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::freshness::{Expected, Facts, judge};
    use crate::bus::handle::PortState;
    use crate::drive::Status;
    use std::time::{Instant, SystemTime};

    const EXPECTED: Expected = Expected {
        period: Duration::from_millis(100),
        poll: Duration::from_millis(100),
        slack: Duration::from_millis(400),
    };

    /// What the bus would say of `snapshot` on a port in `port`, now.
    fn judged(snapshot: &DriveSnapshot, port: &PortState) -> Verdict {
        let facts = Facts {
            seen_at: snapshot.seen_at,
            seen_instant: snapshot.seen_instant,
            link: snapshot.link,
            failures: snapshot.consecutive_failures,
            offline_since: None,
            last_failure: None,
        };
        judge(port, &facts, EXPECTED, Instant::now())
    }

    fn up() -> PortState {
        PortState::Up {
            since: SystemTime::now(),
        }
    }

    fn live(snapshot: &DriveSnapshot) -> Verdict {
        judged(snapshot, &up())
    }

    fn snapshot(age: Duration, link: Link) -> DriveSnapshot {
        DriveSnapshot {
            unit: 1,
            status: Some(Status {
                turns: 7,
                angle_centideg: -9000,
                speed_rpm: 100,
                current_counts: 64,
                voltage_v: 24,
                temperature_c: 31,
                flags: 0xC8,
            }),
            seen_at: Some(SystemTime::now()),
            seen_instant: Instant::now().checked_sub(age),
            link,
            consecutive_failures: 0,
        }
    }

    #[test]
    fn which_reads_lie_in_the_block() {
        assert_eq!(
            status_registers(&[0x03, 0x00, 0xC0, 0x00, 0x07]),
            Some((0, 7))
        );
        // one register at 0x00C2 is ANGLE
        assert_eq!(
            status_registers(&[0x03, 0x00, 0xC2, 0x00, 0x01]),
            Some((1, 1))
        );
        // the last register alone
        assert_eq!(
            status_registers(&[0x03, 0x00, 0xCC, 0x00, 0x01]),
            Some((6, 1))
        );
        // odd address, past the end, before the start, zero count, other code
        assert_eq!(status_registers(&[0x03, 0x00, 0xC1, 0x00, 0x01]), None);
        assert_eq!(status_registers(&[0x03, 0x00, 0xCC, 0x00, 0x02]), None);
        assert_eq!(status_registers(&[0x03, 0x00, 0xBE, 0x00, 0x02]), None);
        assert_eq!(status_registers(&[0x03, 0x00, 0xC0, 0x00, 0x00]), None);
        assert_eq!(status_registers(&[0x04, 0x00, 0xC0, 0x00, 0x07]), None);
        assert_eq!(status_registers(&[0x03, 0x00, 0xC0, 0x00]), None);
    }

    #[test]
    fn a_fresh_copy_answers_as_the_drive_would() {
        let s = snapshot(Duration::from_millis(10), Link::Online);
        let full = answer(
            &[0x03, 0x00, 0xC0, 0x00, 0x07],
            &s,
            &live(&s),
            Duration::from_millis(100),
        )
        .unwrap();
        let mut expected = vec![0x03, 14];
        expected.extend_from_slice(&s.status.unwrap().to_bytes());
        assert_eq!(full, expected);
        // ANGLE and SPEED: -9000 = 0xDCD8, 100 = 0x0064
        let two = answer(
            &[0x03, 0x00, 0xC2, 0x00, 0x02],
            &s,
            &live(&s),
            Duration::from_millis(100),
        )
        .unwrap();
        assert_eq!(two, [0x03, 4, 0xDC, 0xD8, 0x00, 0x64]);
    }

    #[test]
    fn a_stale_or_offline_copy_goes_to_the_bus() {
        let read = [0x03, 0x00, 0xC0, 0x00, 0x07];
        let max_age = Duration::from_millis(100);
        let old = snapshot(Duration::from_millis(300), Link::Online);
        assert_eq!(answer(&read, &old, &live(&old), max_age), None);
        let offline = snapshot(Duration::from_millis(1), Link::Offline);
        assert_eq!(answer(&read, &offline, &live(&offline), max_age), None);
        let mut never = snapshot(Duration::ZERO, Link::Unknown);
        never.status = None;
        never.seen_instant = None;
        assert_eq!(answer(&read, &never, &live(&never), max_age), None);
    }

    #[test]
    fn a_young_copy_is_not_answered_once_the_wire_is_gone_or_the_data_stale() {
        let read = [0x03, 0x00, 0xC0, 0x00, 0x07];
        // Well within a long maximum age, and the drive's link still
        // online: what decides is the bus's freshness.
        let max_age = Duration::from_secs(60);
        let young = snapshot(Duration::from_millis(5), Link::Online);
        assert!(answer(&read, &young, &live(&young), max_age).is_some());
        let down = PortState::Down {
            since: SystemTime::now(),
            reason: "serial port /dev/ttyUSB0 failed: gone".into(),
        };
        let bus_down = judged(&young, &down);
        assert_eq!(bus_down.freshness.name(), "bus-down");
        assert_eq!(answer(&read, &young, &bus_down, max_age), None);
        // Polls missing past the drive's period and slack: stale, though
        // younger than max_age.
        let late = snapshot(Duration::from_secs(2), Link::Online);
        let stale = live(&late);
        assert_eq!(stale.freshness.name(), "stale");
        assert_eq!(answer(&read, &late, &stale, max_age), None);
    }
}
