//! `drivegate probe`: finds the drives on a line without any configuration,
//! and when nothing (or garbage) answers, says what that usually means on
//! RS-485 from what it actually heard.
//!
//! It runs the bus's own RTU master on the port (the t3.5 silences, reply
//! framing and checks, the guard after a fault), reads the drive's status
//! block from each unit, and watches every byte that comes back through the
//! master's tap, as the bus monitor does: that is how an adapter's echo or
//! a wrong rate's garbage is told from silence. [`diagnosis`] turns what it
//! heard into advice.
//!
//! The probe owns the port while it runs: stop the daemon (or the bus) that
//! uses it first. A port another program holds is named as such, with
//! that program and its pid ([`crate::port_holders`]).

pub mod diagnosis;

use std::io::{IsTerminal, Write};
use std::sync::Arc;
use std::time::Duration;

use crate::bus::master::{MasterSettings, RtuMaster};
use crate::bus::port::{PortError, Rs485Settings};
use crate::bus::transport::{self, OpenError};
use crate::drive::DriveRequest;
use crate::modbus::timing::LineTiming;
use crate::monitor::record::Direction;
use crate::monitor::{BusMonitor, MonitorSettings};
use crate::port_holders::{self, Holder};
use crate::sim::cli::UnitList;
use diagnosis::{COMMON_BAUDS, Heard, RateScan, UnitReads};

/// Arguments of `drivegate probe`.
#[derive(Debug, Clone, clap::Args)]
pub struct ProbeArgs {
    /// The adapter (e.g. /dev/serial/by-id/usb-FTDI...), a pty, or a serial
    /// device server as tcp://host:port.
    #[arg(long)]
    pub port: String,
    /// Baud rate to scan at first (8N1).
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
    /// Units to scan: ranges and lists, e.g. "1-32" or "1,3,5-7".
    #[arg(long, default_value = "1-255")]
    pub units: UnitList,
    /// Scan the common rates (115200, 9600, 19200, 38400, 57600) too when
    /// nothing answers at --baud (done anyway when garbage comes back).
    #[arg(long)]
    pub try_bauds: bool,
    /// How long to wait for a reply's first byte, ms.
    #[arg(long, default_value_t = 100)]
    pub timeout_ms: u64,
    /// Reads of each unit that answers (more reads find intermittent faults).
    #[arg(long, default_value_t = 10)]
    pub reads: u32,
}

/// Runs the probe, printing to stdout (and progress to stderr on a
/// terminal); an error when the port cannot be used at all.
pub async fn run(args: ProbeArgs) -> Result<(), String> {
    if !(300..=4_000_000).contains(&args.baud) {
        return Err(format!(
            "baud {} is out of range: valid 300 to 4000000",
            args.baud
        ));
    }
    if !(10..=10_000).contains(&args.timeout_ms) {
        return Err(format!(
            "timeout {} ms is out of range: valid 10 to 10000",
            args.timeout_ms
        ));
    }
    let mut out = std::io::stdout();
    let mut progress = Progress::new();
    let units = &args.units.0;
    let reads = args.reads.clamp(1, 1000);
    let timeout = Duration::from_millis(args.timeout_ms);
    say(
        &mut out,
        &format!(
            "Probing {} at {} baud 8N1, units {}, {} ms timeout",
            args.port,
            args.baud,
            span(units),
            args.timeout_ms
        ),
    );
    let mut scans = vec![scan(&args.port, args.baud, units, timeout, reads, &mut progress).await?];
    let device_server = crate::bus::tcp_port::address(&args.port).is_some();
    if device_server && diagnosis::try_other_rates(&scans[0], args.try_bauds) {
        say(
            &mut out,
            "(Not trying other rates: a serial device server talks to the drives at the rate \
             set in its own settings, whatever --baud says; check that rate there.)",
        );
    } else if diagnosis::try_other_rates(&scans[0], args.try_bauds) {
        for &baud in COMMON_BAUDS.iter().filter(|&&b| b != args.baud) {
            say(&mut out, &format!("Trying {baud} baud"));
            let found = scan(&args.port, baud, units, timeout, reads, &mut progress).await?;
            let any = found.found().next().is_some();
            scans.push(found);
            if any {
                break;
            }
        }
    }
    let answering = scans.iter().find(|s| s.found().next().is_some());
    match answering {
        Some(s) => {
            say(&mut out, &format!("Found at {} baud:", s.baud));
            for u in s.found() {
                say(&mut out, &describe(u));
            }
        }
        None => say(&mut out, "No drive found."),
    }
    for advice in diagnosis::diagnose(&scans) {
        say(&mut out, "");
        say(&mut out, &advice.to_string());
    }
    if let Some(s) = answering {
        say(&mut out, "");
        say(&mut out, "For the configuration:");
        say(&mut out, &config_lines(&args.port, s));
    }
    Ok(())
}

fn say(out: &mut impl Write, line: &str) {
    // stdout gone (a closed pipe) leaves nothing to tell.
    let _ = writeln!(out, "{line}");
}

/// A unit list as ranges: "1-8", "1, 3-4".
fn span(units: &[u8]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < units.len() {
        let start = units[i];
        let mut end = start;
        while i + 1 < units.len() && units[i + 1] == end.wrapping_add(1) {
            i += 1;
            end = units[i];
        }
        parts.push(if start == end {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        i += 1;
    }
    parts.join(", ")
}

/// One line per unit found.
fn describe(u: &UnitReads) -> String {
    let reads = format!("{} of {} reads answered", u.ok, u.reads());
    match (&u.status, u.exception) {
        (Some(s), _) => format!(
            "  unit {:>3}: mode {}, {}, {} V, {} °C, fault {} ({})",
            u.unit,
            s.mode().name(),
            if s.active() { "active" } else { "inactive" },
            s.voltage_v,
            s.temperature_c,
            s.fault().name(),
            reads
        ),
        (None, Some(code)) => format!(
            "  unit {:>3}: answers with Modbus exception {code}: not a drive of this kind? ({reads})",
            u.unit
        ),
        (None, None) => format!("  unit {:>3}: {reads}", u.unit),
    }
}

/// The `[[bus]]` and `[[bus.drive]]` lines for what was found.
fn config_lines(port: &str, scan: &RateScan) -> String {
    let mut text = format!(
        "[[bus]]\nname = \"line1\"\nport = {}\nbaud = {}\n",
        toml::Value::String(port.to_string()),
        scan.baud
    );
    for u in scan.found().filter(|u| u.status.is_some()) {
        text.push_str(&format!(
            "\n[[bus.drive]]\nunit = {}\nname = \"drive{}\"\n",
            u.unit, u.unit
        ));
    }
    text.pop();
    text
}

/// Progress on stderr, only on a terminal.
struct Progress {
    tty: bool,
}

impl Progress {
    fn new() -> Self {
        Progress {
            tty: std::io::stderr().is_terminal(),
        }
    }

    fn unit(&mut self, baud: u32, unit: u8, done: usize, total: usize) {
        if self.tty {
            eprint!("\r  {baud} baud: unit {unit:>3} ({done}/{total})   ");
        }
    }

    fn end(&mut self) {
        if self.tty {
            eprint!("\r{:60}\r", "");
        }
    }
}

/// Scans `units` at `baud`: one read each, and `reads` in all of those that
/// answered (or whose reply came back corrupted).
async fn scan(
    port: &str,
    baud: u32,
    units: &[u8],
    timeout: Duration,
    reads: u32,
    progress: &mut Progress,
) -> Result<RateScan, String> {
    let rs485 = Rs485Settings::default();
    let opened = transport::open(port, baud, &rs485)
        .await
        .map_err(|e| open_error(port, &e))?;
    // One attempt per read, with the full timeout (see `read`).
    let settings = MasterSettings::new(baud, timeout, 0);
    let line = LineTiming::new_8n1(baud);
    let mut master = RtuMaster::new(opened, settings)
        .map_err(|e| format!("cannot start the line's timer: {e}"))?;
    let monitor = Arc::new(BusMonitor::new(
        MonitorSettings {
            enabled: true,
            ring_frames: 1024,
        },
        line,
        Vec::new(),
    ));
    let observer: Arc<dyn crate::bus::observers::WireObserver> = monitor.clone();
    master.tap().attach(vec![observer]);
    let mut cursor = 0;
    let mut result = RateScan {
        baud,
        units: Vec::with_capacity(units.len()),
    };
    for (i, &unit) in units.iter().enumerate() {
        progress.unit(baud, unit, i + 1, units.len());
        let mut reads_of = UnitReads::new(unit);
        let first = read(&mut master, &monitor, &mut cursor, unit).await?;
        reads_of.add(&first);
        let again = matches!(
            first,
            Heard::Status(_) | Heard::Exception(_) | Heard::Garbage { crc: true }
        );
        if again {
            for _ in 1..reads {
                let heard = read(&mut master, &monitor, &mut cursor, unit).await?;
                reads_of.add(&heard);
            }
        }
        result.units.push(reads_of);
    }
    progress.end();
    Ok(result)
}

/// Why `port` could not be opened, in words: taken by another program
/// (the system says "busy", or its lock is held), that program is named,
/// with what to do before probing again.
fn open_error(port: &str, e: &OpenError) -> String {
    match e {
        OpenError::Serial(PortError::Held { holders, .. }) => in_use(port, holders),
        _ => e.to_string(),
    }
}

/// What the probe says when `port` is held by `holders`: who, and what to
/// do.
fn in_use(port: &str, holders: &[Holder]) -> String {
    if holders.is_empty() {
        return format!(
            "{port} is in use by another program, which holds it exclusively (the system does \
             not say which to this user: `sudo fuser -v {port}` names it). Stop it, or stop \
             drivegate if it polls this line (sudo systemctl stop drivegate), then probe again"
        );
    }
    let stop = if port_holders::is_drivegate(holders) {
        "A drivegate daemon polls this line: stop it first (sudo systemctl stop drivegate), \
         or probe from the console's commissioning page, which scans through the daemon"
    } else {
        "Stop it first"
    };
    let who = if holders.len() == 1 {
        "another program"
    } else {
        "other programs"
    };
    format!(
        "{port} is in use by {who}: {}. {stop}, then probe again",
        port_holders::named(holders)
    )
}

/// One status read of `unit`, sorted by what came back.
async fn read(
    master: &mut RtuMaster,
    monitor: &BusMonitor,
    cursor: &mut u64,
    unit: u8,
) -> Result<Heard, String> {
    let pdu = DriveRequest::ReadStatus
        .pdu()
        .map_err(|e| format!("the status read cannot be built: {e}"))?;
    // A scan: the full timeout the user gave, whatever the line answered
    // before; nothing is learned about units that may not exist.
    let report = master
        .scan(unit, &pdu)
        .await
        .map_err(|e| format!("the port failed: {e}"))?;
    // Every byte the master read after the request: the reply it framed,
    // then whatever its guard discarded.
    let mut frames = Vec::new();
    if let Some(ring) = monitor.ring() {
        ring.read(cursor, usize::MAX, &mut frames);
    }
    let after_request = frames
        .iter()
        .rposition(|f| f.direction == Direction::Request)
        .map_or(0, |i| i + 1);
    let received: Vec<u8> = frames[after_request..]
        .iter()
        .flat_map(|f| f.bytes().iter().copied())
        .collect();
    Ok(diagnosis::classify(
        unit,
        report.reply.as_deref(),
        report.fault.as_ref(),
        &received,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_lists_print_as_ranges() {
        assert_eq!(span(&[1, 2, 3, 5, 7, 8]), "1-3, 5, 7-8");
        assert_eq!(span(&[255]), "255");
    }
}
