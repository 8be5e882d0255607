//! `drivegate sim`: a simulated bus of drives on a pty, or on TCP as a serial
//! device server serves a line, for third-party tools (mbpoll, pymodbus, the
//! daemon with `port = "tcp://..."`).

use std::fmt;
use std::io::{self, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::str::FromStr;

use tokio::signal::unix::{SignalKind, signal};

use super::Simulator;
use super::config::{DEFAULT_GEAR_RATIO, SimConfig, SimDriveConfig};
use super::delivery::Delivery;
use super::faults::FaultRates;

/// Arguments of `drivegate sim`.
#[derive(Debug, Clone, clap::Args)]
pub struct SimArgs {
    /// Where to link the pty (a symlink to /dev/pts/N, removed on exit).
    #[arg(long, conflicts_with = "listen")]
    pub link: Option<PathBuf>,
    /// Serve the bus on TCP at this address (e.g. 127.0.0.1:4001), as a
    /// serial device server does, instead of on a pty.
    #[arg(long)]
    pub listen: Option<SocketAddr>,
    /// Addresses of the simulated drives: ranges and lists, e.g. "1-8" or "1,3,5-7".
    #[arg(long, default_value = "1-8")]
    pub units: UnitList,
    /// Baud rate whose timing the wire models.
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
    /// Drive processing time before a reply, in ms.
    #[arg(long, default_value_t = 0.5)]
    pub turnaround_ms: f64,
    /// Seed of the fault injection (same seed, same faults).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Gearbox ratio of every drive.
    #[arg(long, default_value_t = DEFAULT_GEAR_RATIO)]
    pub gear_ratio: f64,
    /// Fraction of requests left unanswered.
    #[arg(long, default_value_t = 0.0)]
    pub drop_rate: f64,
    /// Fraction of replies sent with a bad CRC.
    #[arg(long, default_value_t = 0.0)]
    pub crc_error_rate: f64,
    /// Fraction of replies sent late.
    #[arg(long, default_value_t = 0.0)]
    pub late_rate: f64,
    /// How late a late reply is, in ms.
    #[arg(long, default_value_t = 50.0)]
    pub late_ms: f64,
    /// Fraction of replies followed by 1 to 4 noise bytes.
    #[arg(long, default_value_t = 0.0)]
    pub noise_rate: f64,
    /// Units that never answer, e.g. "3,5".
    #[arg(long)]
    pub silent_units: Option<UnitList>,
    /// Units of plain register devices (meters, I/O modules) beside the
    /// drives, e.g. "100": 65536 holding registers each, for long reads.
    #[arg(long)]
    pub devices: Option<UnitList>,
    /// Reply bytes handed over together, as a USB adapter does (1: on time,
    /// as a UART does: the first and the last byte as they arrive).
    #[arg(long, default_value_t = 1)]
    pub chunk_bytes: u16,
    /// Largest extra delay of each chunk, in microseconds.
    #[arg(long, default_value_t = 0)]
    pub jitter_us: u32,
    /// The silence after which the drives part frames, in µs (e.g. 350: 4
    /// characters at 115200 baud): a request that follows the last frame
    /// sooner is garbled to a drive, which does not answer; a drive answers
    /// this long (and the turnaround) after a request. Default: the drives
    /// frame requests by length and answer t3.5 after them.
    #[arg(long)]
    pub frame_gap_us: Option<u32>,
    /// Drives that part frames only after the spec's t3.5 (1.75 ms above
    /// 19200 baud), e.g. "8": strict drives beside fast ones.
    #[arg(long)]
    pub strict_units: Option<UnitList>,
    /// Echo every byte the master sends, as an adapter without automatic
    /// direction control does (the master hears its own request first).
    #[arg(long)]
    pub echo: bool,
    /// Model a master at another baud rate than --baud: the bytes each way
    /// are what a UART at one rate reads of bits sent at the other (so the
    /// drives stay silent to a master at the wrong rate). Pty only.
    #[arg(long, conflicts_with = "listen")]
    pub check_master_baud: bool,
}

impl SimArgs {
    /// The frame separation of the drive at `unit`.
    fn frame_gap(&self, unit: u8) -> Option<std::time::Duration> {
        if self
            .strict_units
            .as_ref()
            .is_some_and(|s| s.0.contains(&unit))
        {
            return Some(crate::modbus::timing::LineTiming::new_8n1(self.baud).t3_5());
        }
        self.frame_gap_us
            .map(|us| std::time::Duration::from_micros(u64::from(us)))
    }

    /// The simulated bus these arguments describe.
    pub fn config(&self) -> SimConfig {
        SimConfig {
            baud: self.baud,
            turnaround_ms: self.turnaround_ms,
            seed: self.seed,
            drives: self
                .units
                .0
                .iter()
                .map(|&unit| SimDriveConfig {
                    unit,
                    gear_ratio: self.gear_ratio,
                    frame_gap: self.frame_gap(unit),
                })
                .collect(),
            devices: self.devices.clone().map(|u| u.0).unwrap_or_default(),
            faults: FaultRates {
                drop_rate: self.drop_rate,
                crc_error_rate: self.crc_error_rate,
                late_rate: self.late_rate,
                late_ms: self.late_ms,
                noise_rate: self.noise_rate,
                silent_units: self.silent_units.clone().map(|u| u.0).unwrap_or_default(),
            },
            delivery: Delivery {
                chunk_bytes: self.chunk_bytes,
                jitter_us: self.jitter_us,
            },
            listen: self.listen,
            max_lag: None,
            echo: self.echo,
            check_master_baud: self.check_master_baud,
            ..SimConfig::default()
        }
    }
}

/// Runs the simulator until SIGINT or SIGTERM: prints the pty path (and the
/// link), or the `tcp://` address, on one line of stdout, and a line of
/// counters on exit.
pub async fn run(args: SimArgs) -> io::Result<()> {
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut terminate = signal(SignalKind::terminate())?;
    let mut handle = Simulator::start(args.config())?;
    if let Some(link) = &args.link {
        handle.link_at(link)?;
    }
    {
        let mut out = io::stdout().lock();
        match handle.link_path() {
            Some(link) => writeln!(out, "{} {}", handle.port_path().display(), link.display())?,
            None => writeln!(out, "{}", handle.port_path().display())?,
        }
        out.flush()?;
    }
    tokio::select! {
        _ = interrupt.recv() => {}
        _ = terminate.recv() => {}
    }
    let stats = handle.stats();
    handle.stop();
    println!("{stats}");
    Ok(())
}

/// A set of drive addresses written as ranges and lists ("1-8", "1,3,5-7").
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnitList(pub Vec<u8>);

/// A unit list that cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UnitListError {
    /// Not a number or a range of numbers.
    #[error("\"{0}\" is not a unit or a range of units like 3 or 1-8")]
    Syntax(String),
    /// Outside 1..=255.
    #[error("unit {0} is out of range: valid 1 to 255 (0 is the broadcast address)")]
    OutOfRange(u32),
    /// A range written backwards.
    #[error("the range {0}-{1} is backwards: write it low-high")]
    Backwards(u8, u8),
    /// Nothing given.
    #[error("no units given")]
    Empty,
}

impl FromStr for UnitList {
    type Err = UnitListError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let unit = |text: &str| -> Result<u8, UnitListError> {
            let n: u32 = text
                .trim()
                .parse()
                .map_err(|_| UnitListError::Syntax(text.trim().to_string()))?;
            match u8::try_from(n) {
                Ok(u) if u != 0 => Ok(u),
                _ => Err(UnitListError::OutOfRange(n)),
            }
        };
        let mut units = Vec::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            match part.split_once('-') {
                Some((low, high)) => {
                    let (low, high) = (unit(low)?, unit(high)?);
                    if low > high {
                        return Err(UnitListError::Backwards(low, high));
                    }
                    units.extend(low..=high);
                }
                None => units.push(unit(part)?),
            }
        }
        units.sort_unstable();
        units.dedup();
        if units.is_empty() {
            return Err(UnitListError::Empty);
        }
        Ok(UnitList(units))
    }
}

impl fmt::Display for UnitList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut first = true;
        let mut i = 0;
        while i < self.0.len() {
            let mut j = i;
            while j + 1 < self.0.len() && self.0[j + 1] == self.0[j].wrapping_add(1) {
                j += 1;
            }
            if !first {
                f.write_str(",")?;
            }
            first = false;
            if j > i {
                write!(f, "{}-{}", self.0[i], self.0[j])?;
            } else {
                write!(f, "{}", self.0[i])?;
            }
            i = j + 1;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: SimArgs,
    }

    #[test]
    fn unit_lists_take_ranges_and_lists() {
        assert_eq!(
            "1-8".parse::<UnitList>().unwrap().0,
            (1..=8).collect::<Vec<u8>>()
        );
        assert_eq!(
            "1,3,5-7".parse::<UnitList>().unwrap().0,
            vec![1, 3, 5, 6, 7]
        );
        assert_eq!(" 5 , 3,3 ".parse::<UnitList>().unwrap().0, vec![3, 5]);
        assert_eq!("0".parse::<UnitList>(), Err(UnitListError::OutOfRange(0)));
        assert_eq!(
            "1-256".parse::<UnitList>(),
            Err(UnitListError::OutOfRange(256))
        );
        assert_eq!(
            "8-1".parse::<UnitList>(),
            Err(UnitListError::Backwards(8, 1))
        );
        assert_eq!(
            "x".parse::<UnitList>(),
            Err(UnitListError::Syntax("x".into()))
        );
        assert_eq!("".parse::<UnitList>(), Err(UnitListError::Empty));
        assert_eq!(
            "1,3,5-7,9".parse::<UnitList>().unwrap().to_string(),
            "1,3,5-7,9"
        );
    }

    #[test]
    fn arguments_make_a_valid_config() {
        let cli = Cli::parse_from(["sim"]);
        let config = cli.args.config();
        assert_eq!(config.drives.len(), 8);
        assert_eq!((config.baud, config.turnaround_ms), (115_200, 0.5));
        assert_eq!(config.validate(), Ok(()));
        let cli = Cli::parse_from([
            "sim",
            "--units",
            "2,4-5",
            "--silent-units",
            "4",
            "--drop-rate",
            "0.1",
            "--seed",
            "9",
            "--gear-ratio",
            "10",
        ]);
        let config = cli.args.config();
        let units: Vec<u8> = config.drives.iter().map(|d| d.unit).collect();
        assert_eq!(units, vec![2, 4, 5]);
        assert_eq!(config.faults.silent_units, vec![4]);
        assert_eq!((config.faults.drop_rate, config.seed), (0.1, 9));
        assert_eq!(config.drives[0].gear_ratio, 10.0);
        assert_eq!(config.drives[0].frame_gap, None);
        let cli = Cli::parse_from([
            "sim",
            "--units",
            "1-8",
            "--frame-gap-us",
            "350",
            "--strict-units",
            "8",
        ]);
        let gaps: Vec<_> = cli
            .args
            .config()
            .drives
            .iter()
            .map(|d| d.frame_gap)
            .collect();
        let us = |n| Some(std::time::Duration::from_micros(n));
        assert_eq!(gaps[..7], [us(350); 7]);
        assert_eq!(gaps[7], us(1750));
        assert!(Cli::try_parse_from(["sim", "--units", "0-3"]).is_err());
        let cli = Cli::parse_from(["sim", "--listen", "127.0.0.1:4001"]);
        assert_eq!(
            cli.args.config().listen,
            Some("127.0.0.1:4001".parse().unwrap())
        );
        assert!(
            Cli::try_parse_from(["sim", "--listen", "127.0.0.1:4001", "--link", "/tmp/x"]).is_err()
        );
    }
}
