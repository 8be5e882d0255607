//! Everything a bus needs to run, as the configuration builds it and the
//! scheduler takes it.

use std::time::Duration;

use super::freshness::Expected;
use super::master::MasterSettings;
use super::observers::Observers;
use super::queue::QueueLimits;

/// Everything a bus needs to run.
#[derive(Debug, Clone)]
pub struct BusSettings {
    /// Name used in logs, metrics and the API.
    pub name: String,
    /// Serial device path, or `tcp://host:port` for a serial device server.
    pub port: String,
    /// Master timing, retries and RS-485 settings.
    pub master: MasterSettings,
    /// Polled drives: unit and poll interval (zero: as fast as the bus allows).
    pub drives: Vec<(u8, Duration)>,
    /// Failed polls in a row before a drive is marked offline.
    pub offline_after: u32,
    /// First and longest poll backoff for an offline drive.
    pub offline_backoff: (Duration, Duration),
    /// First and longest delay between attempts to reopen a failed port.
    pub reopen_backoff: (Duration, Duration),
    /// Queue capacities.
    pub queue: QueueLimits,
    /// How long a job may wait in the queue before it is dropped unsent.
    pub queue_timeout: Duration,
    /// After this many commands in a row while a poll is due, the poll goes
    /// first, so a flood of commands cannot freeze the status of every drive.
    pub poll_share: u32,
    /// Who watches the wire and may steer the polling (the bus monitor,
    /// the scope); none by default.
    pub observers: Observers,
}

impl BusSettings {
    /// Defaults for a bus on `port` at `baud` with the given drives.
    pub fn new(name: &str, port: &str, baud: u32, drives: Vec<(u8, Duration)>) -> Self {
        Self {
            name: name.to_string(),
            port: port.to_string(),
            master: MasterSettings::new(baud, Duration::from_millis(50), 1),
            drives,
            offline_after: 3,
            offline_backoff: (Duration::from_secs(1), Duration::from_secs(30)),
            reopen_backoff: (Duration::from_millis(200), Duration::from_secs(5)),
            queue: QueueLimits::default(),
            queue_timeout: Duration::from_secs(5),
            poll_share: 4,
            observers: Observers::default(),
        }
    }

    /// How often each of its drives is polled: what their data's age is
    /// measured against.
    pub fn expected(&self) -> Vec<(u8, Expected)> {
        let master = &self.master;
        self.drives
            .iter()
            .map(|&(unit, interval)| {
                let expected = Expected::new(
                    interval,
                    (self.drives.len(), self.poll_share),
                    (master.line, master.interframe.shortest(master.line)),
                    u32::from(master.retries) + 1,
                    master.response_timeout,
                );
                (unit, expected)
            })
            .collect()
    }
}
