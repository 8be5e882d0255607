//! What a probe heard, and what it usually means on an RS-485 line: pure
//! functions from observations to advice, so every rule is unit-tested.
//!
//! The rules are the ones a commissioning engineer applies by hand:
//! - not one byte back: nothing is powered, A and B are swapped, the port is
//!   not the adapter, or the drives listen at another baud rate (a drive
//!   cannot read a request sent at the wrong rate, so it stays silent);
//! - our own request back, byte for byte: the adapter hears itself (no
//!   automatic direction control, or echo switched on);
//! - bytes that are no valid answer: a wrong baud rate, A/B swapped on
//!   adapters that read an inverted line as bytes, noise; at one address
//!   only, two drives answering at once;
//! - answers, some corrupted: reflections or a floating line (termination,
//!   bias), long stubs, untwisted cable.

use std::fmt;

use crate::bus::master::Fault;
use crate::drive::Status;
use crate::drive::message::{DriveReply, DriveRequest};
use crate::modbus::rtu_frame;

/// The baud rates tried when the asked one finds nothing, most common first
/// (the drives' own default first).
pub const COMMON_BAUDS: [u32; 5] = [115_200, 9_600, 19_200, 38_400, 57_600];

/// What one read of one unit brought back.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Heard {
    /// A valid status reply.
    Status(Status),
    /// A valid Modbus exception (a device that is not this kind of drive).
    Exception(u8),
    /// Not one byte.
    Silence,
    /// Our own request, byte for byte, and after it the drive's status if
    /// one answered.
    Echo(Option<Status>),
    /// Bytes that are no valid answer to the request.
    Garbage {
        /// They were framed as a reply from this unit, but the CRC was wrong.
        crc: bool,
    },
}

/// Sorts what came back for a status read of `unit`: `reply` is the PDU the
/// master accepted (CRC, unit and function checked), if any, `fault` what
/// the master found wrong otherwise, and `received` every byte read after
/// the request went out, in order (the bytes of a reply cut short at its
/// first byte are not among them: the fault says they came).
pub fn classify(unit: u8, reply: Option<&[u8]>, fault: Option<&Fault>, received: &[u8]) -> Heard {
    let crc_error = fault == Some(&Fault::Crc);
    let request = DriveRequest::ReadStatus;
    if let Some(pdu) = reply {
        return match request.parse_reply(pdu) {
            Ok(DriveReply::Status(s)) => Heard::Status(s),
            _ => match pdu {
                [function, code] if function & 0x80 != 0 => Heard::Exception(*code),
                _ => Heard::Garbage { crc: false },
            },
        };
    }
    if received.is_empty() {
        return match fault {
            Some(Fault::Mismatch(_)) => Heard::Garbage { crc: false },
            _ => Heard::Silence,
        };
    }
    if let Ok(frame) = request.frame(unit)
        && let Some(echoed) = echo_end(&frame, received)
    {
        // The master frames what comes first as the reply and may drop the
        // rest of the echo with it: look for the drive's answer anywhere
        // after the part of the echo that was seen.
        let rest = &received[echoed..];
        let after = (0..rest.len()).find_map(|i| {
            let (from, pdu) = rtu_frame::decode(&rest[i..]).ok()?;
            match request.parse_reply(pdu) {
                Ok(DriveReply::Status(s)) if from == unit => Some(s),
                _ => None,
            }
        });
        return Heard::Echo(after);
    }
    Heard::Garbage { crc: crc_error }
}

/// Where the echo of our own request ends in `received`, when there is
/// one: `received` begins with the whole request or at least its first
/// four bytes (unit, function and address: no drive's answer and no wrong
/// rate's garbage starts so), or holds the whole request, CRC included,
/// further on (behind the late answer to the request before, which a
/// starved or slow line delivers after its attempt ended).
fn echo_end(request: &[u8], received: &[u8]) -> Option<usize> {
    let same = request
        .iter()
        .zip(received)
        .take_while(|(a, b)| a == b)
        .count();
    if same >= 4.min(request.len()) {
        return Some(same);
    }
    received
        .windows(request.len())
        .position(|w| w == request)
        .map(|at| at + request.len())
}

/// What one unit answered over all its reads at one rate.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitReads {
    /// The address.
    pub unit: u8,
    /// The last good status.
    pub status: Option<Status>,
    /// The exception code, if it answered with one.
    pub exception: Option<u8>,
    /// Reads with a valid answer (status or exception).
    pub ok: u32,
    /// Reads that came back as our own request.
    pub echo: u32,
    /// Reads with bytes that were no valid answer.
    pub garbage: u32,
    /// Reads with nothing back.
    pub silent: u32,
}

impl UnitReads {
    /// No read yet.
    pub fn new(unit: u8) -> Self {
        UnitReads {
            unit,
            status: None,
            exception: None,
            ok: 0,
            echo: 0,
            garbage: 0,
            silent: 0,
        }
    }

    /// Counts one read.
    pub fn add(&mut self, heard: &Heard) {
        match heard {
            Heard::Status(s) => {
                self.ok += 1;
                self.status = Some(*s);
            }
            Heard::Exception(code) => {
                self.ok += 1;
                self.exception = Some(*code);
            }
            Heard::Silence => self.silent += 1,
            Heard::Echo(after) => {
                self.echo += 1;
                if let Some(s) = after {
                    self.status = Some(*s);
                }
            }
            Heard::Garbage { .. } => self.garbage += 1,
        }
    }

    /// Reads made.
    pub fn reads(&self) -> u32 {
        self.ok + self.echo + self.garbage + self.silent
    }

    /// Something at this address answered at least once (an answer behind
    /// an echo does not count: the line is not usable as it is).
    pub fn found(&self) -> bool {
        self.ok > 0
    }

    /// Reads after the first that the unit did not answer cleanly.
    pub fn bad(&self) -> u32 {
        self.garbage + self.silent
    }
}

/// One scan of a range of units at one baud rate.
#[derive(Debug, Clone, PartialEq)]
pub struct RateScan {
    /// The rate.
    pub baud: u32,
    /// Every unit scanned, in order.
    pub units: Vec<UnitReads>,
}

impl RateScan {
    /// Units that answered.
    pub fn found(&self) -> impl Iterator<Item = &UnitReads> {
        self.units.iter().filter(|u| u.found())
    }

    fn any_found(&self) -> bool {
        self.found().next().is_some()
    }

    fn all_echo(&self) -> bool {
        !self.units.is_empty() && self.units.iter().all(|u| u.echo > 0)
    }

    fn garbled(&self) -> Vec<u8> {
        self.units
            .iter()
            .filter(|u| u.garbage > 0 && u.ok == 0)
            .map(|u| u.unit)
            .collect()
    }

    fn all_silent(&self) -> bool {
        self.units.iter().all(|u| u.silent == u.reads())
    }
}

/// Whether the probe should scan the common rates after a scan at the
/// asked rate: when asked to, or when bytes came back but no answer (the
/// usual sign of a wrong baud rate). Not after an echo: the adapter must be
/// fixed first, and every rate would echo alike.
pub fn try_other_rates(asked: &RateScan, forced: bool) -> bool {
    if asked.any_found() || asked.all_echo() {
        return false;
    }
    forced || !asked.garbled().is_empty()
}

/// One thing the probe has to say about the line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Advice {
    /// Nothing at all came back, at any rate tried.
    Silence {
        /// The rates scanned.
        bauds: Vec<u32>,
    },
    /// The adapter returned every request as sent.
    Echo {
        /// Units whose status came after the echo.
        behind: Vec<u8>,
    },
    /// Nothing answered at the asked rate, but drives did at another.
    OtherBaud {
        /// The rate asked for.
        asked: u32,
        /// The rate they answered at.
        found: u32,
    },
    /// Bytes came back, never a valid answer, at every rate tried.
    Garbage {
        /// Units where it happened.
        units: Vec<u8>,
        /// The rates scanned.
        bauds: Vec<u32>,
    },
    /// Drives answer, but at these addresses only garbage came back.
    Collision {
        /// The addresses.
        units: Vec<u8>,
    },
    /// A unit that answered did not answer every read cleanly.
    Intermittent {
        /// The address.
        unit: u8,
        /// Reads that failed.
        bad: u32,
        /// Reads made.
        reads: u32,
    },
}

/// What the scans (the asked rate first, then any other rates tried) mean.
pub fn diagnose(scans: &[RateScan]) -> Vec<Advice> {
    let Some(asked) = scans.first() else {
        return Vec::new();
    };
    let bauds: Vec<u32> = scans.iter().map(|s| s.baud).collect();
    let mut advice = Vec::new();
    if asked.all_echo() {
        advice.push(Advice::Echo {
            behind: asked
                .units
                .iter()
                .filter(|u| u.status.is_some())
                .map(|u| u.unit)
                .collect(),
        });
        return advice;
    }
    let answering = scans.iter().find(|s| s.any_found());
    match answering {
        None if scans.iter().all(RateScan::all_silent) => {
            advice.push(Advice::Silence { bauds });
        }
        None => {
            let mut units: Vec<u8> = scans.iter().flat_map(RateScan::garbled).collect();
            units.sort_unstable();
            units.dedup();
            advice.push(Advice::Garbage { units, bauds });
        }
        Some(scan) => {
            if scan.baud != asked.baud {
                advice.push(Advice::OtherBaud {
                    asked: asked.baud,
                    found: scan.baud,
                });
            }
            let garbled = scan.garbled();
            if !garbled.is_empty() {
                advice.push(Advice::Collision { units: garbled });
            }
            for u in scan.found() {
                // The first read found it; the others tell how clean the
                // line is.
                if u.bad() > 0 {
                    advice.push(Advice::Intermittent {
                        unit: u.unit,
                        bad: u.bad(),
                        reads: u.reads(),
                    });
                }
            }
        }
    }
    advice
}

fn list(units: &[u8]) -> String {
    units
        .iter()
        .map(u8::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

fn rates(bauds: &[u32]) -> String {
    bauds
        .iter()
        .map(u32::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

impl fmt::Display for Advice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Advice::Silence { bauds } => {
                writeln!(
                    f,
                    "Silence: not one byte came back (baud {}). On RS-485 that usually means:",
                    rates(bauds)
                )?;
                writeln!(
                    f,
                    "  - no drive is powered, or none at the addresses scanned;"
                )?;
                writeln!(
                    f,
                    "  - A and B are swapped (swap the two data wires at the adapter: harmless to try);"
                )?;
                writeln!(
                    f,
                    "  - this port is not the RS-485 adapter (ls -l /dev/serial/by-id/ names them);"
                )?;
                if bauds.len() == 1 {
                    writeln!(
                        f,
                        "  - the drives listen at another baud rate: a drive cannot read a request \
                         sent at the wrong rate and stays silent (--try-bauds scans the common rates);"
                    )?;
                }
                write!(
                    f,
                    "  - no common ground (GND) between the adapter and the drives on a long line."
                )
            }
            Advice::Echo { behind } => {
                writeln!(
                    f,
                    "Echo: every request came back byte for byte before any answer. The adapter hears \
                     its own transmission: it has no automatic direction control, or its echo is on."
                )?;
                writeln!(
                    f,
                    "  Fix: use an adapter with automatic send/receive switching, or turn its echo \
                     off (a DIP switch or jumper named echo, RE or loopback on many); on a UART that \
                     switches with RTS, set [bus.rs485] direction = \"rts\" (the kernel then stops \
                     receiving while sending)."
                )?;
                if behind.is_empty() {
                    write!(f, "  No drive answered after the echo.")
                } else {
                    write!(
                        f,
                        "  Behind the echo, unit(s) {} answered: the drives and the wiring are fine; \
                         fix the adapter and probe again.",
                        list(behind)
                    )
                }
            }
            Advice::OtherBaud { asked, found } => write!(
                f,
                "Wrong baud rate: nothing answered at {asked} baud, the drives answered at {found} baud. \
                 Set baud = {found} for this bus (or change the drives' rate)."
            ),
            Advice::Garbage { units, bauds } => {
                writeln!(
                    f,
                    "Garbage: bytes came back from unit(s) {} but never a valid answer (baud {}). \
                     On RS-485 that usually means:",
                    list(units),
                    rates(bauds)
                )?;
                writeln!(
                    f,
                    "  - a baud rate other than the ones tried (or parity/stop bits other than 8N1);"
                )?;
                writeln!(
                    f,
                    "  - A and B swapped: some adapters read the inverted line as bytes;"
                )?;
                write!(
                    f,
                    "  - a noisy line: missing termination or bias, an untwisted or unshielded cable."
                )
            }
            Advice::Collision { units } => write!(
                f,
                "Unit(s) {} answered only with garbage while others answered cleanly: usually two \
                 drives set to the same address answering at once; power one off and scan again.",
                list(units)
            ),
            Advice::Intermittent { unit, bad, reads } => write!(
                f,
                "Unit {unit}: {bad} of {reads} reads failed (corrupted or lost). An intermittent fault \
                 on a line that works is usually termination: 120 ohm across A and B at both ends of \
                 the line and nowhere else, bias on one end, no long stubs, twisted pair cable."
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status() -> Status {
        Status::from_registers([0, 0, 0, 0, 24, 31, 0])
    }

    fn reads(unit: u8, heard: &[Heard]) -> UnitReads {
        let mut r = UnitReads::new(unit);
        for h in heard {
            r.add(h);
        }
        r
    }

    fn scan(baud: u32, units: Vec<UnitReads>) -> RateScan {
        RateScan { baud, units }
    }

    fn silent(units: std::ops::RangeInclusive<u8>) -> Vec<UnitReads> {
        units.map(|u| reads(u, &[Heard::Silence])).collect()
    }

    #[test]
    fn a_status_reply_is_a_drive() {
        // 01 03 0E, 14 bytes of status: the PDU without unit and CRC.
        let mut pdu = vec![0x03, 0x0E];
        pdu.extend_from_slice(&status().to_bytes());
        assert_eq!(classify(1, Some(&pdu), None, &[]), Heard::Status(status()));
        assert_eq!(
            classify(1, Some(&[0x83, 0x02]), None, &[]),
            Heard::Exception(2)
        );
    }

    #[test]
    fn our_own_request_back_is_an_echo_with_the_answer_behind_it() {
        let request = DriveRequest::ReadStatus.frame(5).unwrap();
        assert_eq!(
            classify(5, None, Some(&Fault::Crc), &request),
            Heard::Echo(None)
        );
        let mut pdu = vec![0x03, 0x0E];
        pdu.extend_from_slice(&status().to_bytes());
        let mut both = request.clone();
        both.extend_from_slice(&rtu_frame::encode(5, &pdu));
        assert_eq!(
            classify(5, None, Some(&Fault::Crc), &both),
            Heard::Echo(Some(status()))
        );
        // The master framed the echo's first five bytes as the reply and
        // dropped the rest of what it had read: still an echo, and the
        // answer after it is found.
        let mut cut = request[..5].to_vec();
        cut.extend_from_slice(&both[request.len()..]);
        assert_eq!(
            classify(5, None, Some(&Fault::Crc), &cut),
            Heard::Echo(Some(status()))
        );
        // Two bytes alike are not an echo.
        assert_eq!(
            classify(5, None, Some(&Fault::Crc), &request[..2]),
            Heard::Garbage { crc: true }
        );
        // The late answer to the read of unit 4 before it, then our
        // echo: still an echo.
        let mut late = rtu_frame::encode(4, &pdu);
        late.extend_from_slice(&request);
        assert_eq!(
            classify(5, None, Some(&Fault::Mismatch("unit 4")), &late),
            Heard::Echo(None)
        );
    }

    #[test]
    fn nothing_is_silence_and_other_bytes_garbage() {
        assert_eq!(
            classify(1, None, Some(&Fault::Timeout), &[]),
            Heard::Silence
        );
        assert_eq!(
            classify(
                1,
                None,
                Some(&Fault::Mismatch("reply cut short")),
                &[0x00, 0xF8, 0x80]
            ),
            Heard::Garbage { crc: false }
        );
        // A reply from another unit: its bytes were dropped with the fault.
        let other = Fault::Mismatch("reply from another unit");
        assert_eq!(
            classify(1, None, Some(&other), &[]),
            Heard::Garbage { crc: false }
        );
    }

    #[test]
    fn a_silent_line_says_what_silence_means_and_offers_the_rates() {
        let asked = scan(115_200, silent(1..=8));
        assert!(!try_other_rates(&asked, false));
        assert!(try_other_rates(&asked, true));
        let advice = diagnose(&[asked]);
        assert_eq!(
            advice,
            [Advice::Silence {
                bauds: vec![115_200]
            }]
        );
        let text = advice[0].to_string();
        assert!(text.contains("A and B are swapped"), "{text}");
        assert!(text.contains("--try-bauds"), "{text}");
    }

    #[test]
    fn garbage_tries_the_other_rates_and_names_the_one_that_answered() {
        let asked = scan(9_600, vec![reads(1, &[Heard::Garbage { crc: false }])]);
        assert!(try_other_rates(&asked, false));
        let other = scan(19_200, vec![reads(1, &[Heard::Status(status())])]);
        let advice = diagnose(&[asked.clone(), other]);
        assert_eq!(
            advice,
            [Advice::OtherBaud {
                asked: 9_600,
                found: 19_200
            }]
        );
        assert!(advice[0].to_string().contains("baud = 19200"));
        // Garbage at every rate.
        let still = scan(19_200, vec![reads(1, &[Heard::Garbage { crc: true }])]);
        let advice = diagnose(&[asked, still]);
        assert_eq!(
            advice,
            [Advice::Garbage {
                units: vec![1],
                bauds: vec![9_600, 19_200]
            }]
        );
        assert!(advice[0].to_string().contains("A and B swapped"));
    }

    #[test]
    fn an_echo_on_every_unit_is_the_adapter() {
        let asked = scan(
            115_200,
            vec![
                reads(1, &[Heard::Echo(Some(status()))]),
                reads(2, &[Heard::Echo(None)]),
            ],
        );
        assert!(!try_other_rates(&asked, true));
        let advice = diagnose(&[asked]);
        assert_eq!(advice, [Advice::Echo { behind: vec![1] }]);
        let text = advice[0].to_string();
        assert!(text.contains("direction control"), "{text}");
        assert!(text.contains("unit(s) 1 answered"), "{text}");
    }

    #[test]
    fn corrupted_rereads_of_a_drive_that_answers_point_at_termination() {
        let crc = Heard::Garbage { crc: true };
        let ok = Heard::Status(status());
        let asked = scan(
            115_200,
            vec![
                reads(1, &[ok, ok, crc, ok]),
                reads(2, &[Heard::Silence]),
                reads(3, &[crc, ok, ok]),
                reads(4, &[ok, ok]),
            ],
        );
        let advice = diagnose(&[asked]);
        assert_eq!(
            advice,
            [
                Advice::Intermittent {
                    unit: 1,
                    bad: 1,
                    reads: 4
                },
                Advice::Intermittent {
                    unit: 3,
                    bad: 1,
                    reads: 3
                },
            ]
        );
        assert!(advice[0].to_string().contains("120 ohm"));
    }

    #[test]
    fn garbage_at_one_address_among_clean_answers_is_a_collision() {
        let asked = scan(
            115_200,
            vec![
                reads(1, &[Heard::Status(status())]),
                reads(2, &[Heard::Garbage { crc: true }]),
            ],
        );
        assert!(!try_other_rates(&asked, true));
        assert_eq!(diagnose(&[asked]), [Advice::Collision { units: vec![2] }]);
    }

    #[test]
    fn a_clean_line_needs_no_advice() {
        let asked = scan(
            115_200,
            vec![
                reads(1, &[Heard::Status(status()); 3]),
                reads(2, &[Heard::Silence]),
            ],
        );
        assert!(diagnose(&[asked]).is_empty());
    }
}
