//! Everything a bus needs to run, as the configuration builds it and the
//! scheduler takes it, and what a change of it asks of a running bus
//! ([`BusSettings::reach`], pure): the open port's own settings (its path,
//! the baud rate, RS-485 direction control) need the port reopened;
//! everything else (timing, retries, the silence before requests, the
//! drives and their poll rates, offline detection, the queue) the
//! scheduler takes between two transactions, on the open port.

use std::time::Duration;

use super::freshness::Expected;
use super::master::MasterSettings;
use super::observers::Observers;
use super::queue::QueueLimits;

/// What new settings ask of a running bus, from the least to the most.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Reach {
    /// Nothing changed.
    Same,
    /// Taken between two transactions, the port kept open
    /// (`BusHandle::retune`).
    InPlace,
    /// The open port's own settings changed: it is closed and opened again.
    Reopen,
}

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

    /// What taking `new` in place of these asks of the running bus: the
    /// port, the baud rate and RS-485 direction control are the open
    /// port's ([`Reach::Reopen`]); the rest is the scheduler's to take
    /// between two transactions. The observers are the plant's, not
    /// compared.
    pub fn reach(&self, new: &BusSettings) -> Reach {
        let (a, b) = (&self.master, &new.master);
        if self.name != new.name || self.port != new.port || a.line != b.line || a.rs485 != b.rs485
        {
            return Reach::Reopen;
        }
        let same = a == b
            && self.drives == new.drives
            && self.offline_after == new.offline_after
            && self.offline_backoff == new.offline_backoff
            && self.reopen_backoff == new.reopen_backoff
            && self.queue == new.queue
            && self.queue_timeout == new.queue_timeout
            && self.poll_share == new.poll_share;
        if same { Reach::Same } else { Reach::InPlace }
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

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    /// A change, named.
    type Change = (&'static str, fn(&mut BusSettings));

    fn line1() -> BusSettings {
        BusSettings::new(
            "line1",
            "/dev/ttyUSB0",
            115_200,
            vec![(1, Duration::ZERO), (2, MS * 100)],
        )
    }

    #[test]
    fn only_the_ports_own_settings_reopen_it() {
        let old = line1();
        assert_eq!(old.reach(&old.clone()), Reach::Same);
        // What the scheduler takes between two transactions.
        let in_place: Vec<Change> = vec![
            ("poll rates", |s| s.drives[1].1 = MS * 50),
            ("a drive added", |s| s.drives.push((3, Duration::ZERO))),
            ("a drive removed", |s| {
                s.drives.pop();
            }),
            ("response timeout", |s| s.master.response_timeout = MS * 250),
            ("retries", |s| s.master.retries = 3),
            ("guard", |s| {
                s.master.guard = crate::bus::master::Guard::Fixed(MS * 50);
            }),
            ("interframe", |s| {
                s.master.interframe = crate::bus::interframe::Interframe::Auto;
            }),
            ("reply timeout floor", |s| {
                s.master.reply_timeout_floor = MS * 9
            }),
            ("broadcast delay", |s| s.master.broadcast_delay = MS * 40),
            ("offline detection", |s| s.offline_after = 5),
            ("offline backoff", |s| s.offline_backoff.1 = MS * 9000),
            ("queue", |s| s.queue.per_class = 16),
            ("queue timeout", |s| s.queue_timeout = MS * 900),
            ("poll share", |s| s.poll_share = 2),
        ];
        for (what, change) in in_place {
            let mut new = old.clone();
            change(&mut new);
            assert_eq!(old.reach(&new), Reach::InPlace, "{what}");
        }
        // What only a reopen can apply.
        let reopen: Vec<Change> = vec![
            ("port", |s| s.port = "/dev/ttyUSB1".into()),
            ("transport", |s| s.port = "tcp://10.0.0.7:4001".into()),
            ("baud", |s| {
                s.master.line = crate::modbus::timing::LineTiming::new_8n1(19_200);
            }),
            ("rs485", |s| s.master.rs485.delay_after_send_us = 40),
        ];
        for (what, change) in reopen {
            let mut new = old.clone();
            change(&mut new);
            // A reopen wins over what else changed with it.
            new.drives.push((9, Duration::ZERO));
            assert_eq!(old.reach(&new), Reach::Reopen, "{what}");
        }
    }
}
