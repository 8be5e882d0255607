//! What the node does with kept data coming back out of the outbox: a
//! device's data is replayed only after that device's DBIRTH (a host
//! drops data of a device it has not seen born), so the data of a drive
//! not born yet (offline at the reconnect, or born later) waits here, in
//! order, and goes as soon as its birth is out; the data of a drive no
//! longer configured is dropped (it will never be born again). Pure.

use std::collections::{BTreeMap, VecDeque};

use super::sparkplug_b::payload::Metric;

/// How many kept messages may wait for their device's birth in memory.
/// Past it the node stops taking from the outbox (the data stays on disk)
/// until a birth lets some go.
pub const HELD_MAX: usize = 4096;

/// Where a device stands when its kept data comes out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Device {
    /// Its DBIRTH is out on this connection.
    Born,
    /// Configured, not born yet.
    Unborn,
    /// No longer a configured drive.
    Gone,
}

/// What became of a kept message offered for replay.
#[derive(Debug, PartialEq)]
pub enum Verdict {
    /// Publish it now.
    Send(String, Vec<Metric>),
    /// Held until its device is born.
    Held,
    /// Dropped: its drive is no longer configured.
    Dropped,
}

/// The kept data waiting for its device's birth, oldest first per device.
#[derive(Debug)]
pub struct Held {
    waiting: BTreeMap<String, VecDeque<Vec<Metric>>>,
    count: usize,
    max: usize,
}

impl Default for Held {
    fn default() -> Self {
        Self::new(HELD_MAX)
    }
}

impl Held {
    /// Holds at most `max` messages.
    pub fn new(max: usize) -> Self {
        Held {
            waiting: BTreeMap::new(),
            count: 0,
            max,
        }
    }

    /// No more may be held: take nothing more from the outbox for now.
    pub fn full(&self) -> bool {
        self.count >= self.max
    }

    /// How many messages wait.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Nothing waits.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// A message just taken from the outbox, of `device` in state `state`.
    /// A born device's message goes unless older ones of it still wait
    /// (they go first: it joins them).
    pub fn offer(&mut self, device: String, metrics: Vec<Metric>, state: Device) -> Verdict {
        match state {
            Device::Gone => Verdict::Dropped,
            Device::Born if !self.waiting.contains_key(&device) => Verdict::Send(device, metrics),
            Device::Born | Device::Unborn => {
                self.waiting.entry(device).or_default().push_back(metrics);
                self.count += 1;
                Verdict::Held
            }
        }
    }

    /// The oldest waiting message of a device that `state` says is born
    /// now, taken out.
    pub fn next_born(&mut self, state: impl Fn(&str) -> Device) -> Option<(String, Vec<Metric>)> {
        let device = self
            .waiting
            .keys()
            .find(|d| state(d) == Device::Born)?
            .clone();
        let queue = self.waiting.get_mut(&device)?;
        let metrics = queue.pop_front()?;
        if queue.is_empty() {
            self.waiting.remove(&device);
        }
        self.count -= 1;
        Some((device, metrics))
    }

    /// Drops what waits for devices that `state` says are gone; how many
    /// messages that was.
    pub fn drop_gone(&mut self, state: impl Fn(&str) -> Device) -> usize {
        let gone: Vec<String> = self
            .waiting
            .keys()
            .filter(|d| state(d) == Device::Gone)
            .cloned()
            .collect();
        let mut dropped = 0;
        for d in gone {
            dropped += self.waiting.remove(&d).map_or(0, |q| q.len());
        }
        self.count -= dropped;
        dropped
    }

    /// Everything that waits, oldest first per device, taken out (at
    /// shutdown, back to the outbox).
    pub fn drain(&mut self) -> Vec<(String, Vec<Metric>)> {
        self.count = 0;
        std::mem::take(&mut self.waiting)
            .into_iter()
            .flat_map(|(d, q)| q.into_iter().map(move |m| (d.clone(), m)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A message told apart by its one metric's name.
    fn msg(name: &str) -> Vec<Metric> {
        vec![Metric {
            name: Some(name.to_string()),
            ..Default::default()
        }]
    }

    fn name(m: &[Metric]) -> &str {
        m[0].name.as_deref().unwrap_or("")
    }

    #[test]
    fn a_born_devices_data_goes_at_once() {
        let mut held = Held::default();
        assert_eq!(
            held.offer("conveyor".into(), msg("a"), Device::Born),
            Verdict::Send("conveyor".into(), msg("a"))
        );
        assert!(held.is_empty());
    }

    #[test]
    fn an_unborn_devices_data_waits_for_its_birth_in_order() {
        let mut held = Held::default();
        assert_eq!(
            held.offer("lift".into(), msg("1"), Device::Unborn),
            Verdict::Held
        );
        assert_eq!(
            held.offer("lift".into(), msg("2"), Device::Unborn),
            Verdict::Held
        );
        assert_eq!(held.len(), 2);
        // Not born yet: nothing comes out.
        assert_eq!(held.next_born(|_| Device::Unborn), None);
        // Born: oldest first.
        let (d, m) = held.next_born(|_| Device::Born).unwrap();
        assert_eq!((d.as_str(), name(&m)), ("lift", "1"));
        let (_, m) = held.next_born(|_| Device::Born).unwrap();
        assert_eq!(name(&m), "2");
        assert!(held.is_empty());
        assert_eq!(held.next_born(|_| Device::Born), None);
    }

    #[test]
    fn newer_data_of_a_device_just_born_queues_behind_its_older_data() {
        let mut held = Held::default();
        held.offer("lift".into(), msg("old"), Device::Unborn);
        // Born now, with its old data still waiting: the new one joins it.
        assert_eq!(
            held.offer("lift".into(), msg("new"), Device::Born),
            Verdict::Held
        );
        let order: Vec<String> = std::iter::from_fn(|| held.next_born(|_| Device::Born))
            .map(|(_, m)| name(&m).to_string())
            .collect();
        assert_eq!(order, ["old", "new"]);
    }

    #[test]
    fn only_born_devices_data_is_released() {
        let mut held = Held::default();
        held.offer("lift".into(), msg("l"), Device::Unborn);
        held.offer("feeder".into(), msg("f"), Device::Unborn);
        let state = |d: &str| {
            if d == "feeder" {
                Device::Born
            } else {
                Device::Unborn
            }
        };
        let (d, _) = held.next_born(state).unwrap();
        assert_eq!(d, "feeder");
        assert_eq!(held.next_born(state), None);
        assert_eq!(held.len(), 1);
    }

    #[test]
    fn the_data_of_a_drive_no_longer_configured_is_dropped_and_counted() {
        let mut held = Held::default();
        assert_eq!(
            held.offer("old".into(), msg("x"), Device::Gone),
            Verdict::Dropped
        );
        held.offer("lift".into(), msg("1"), Device::Unborn);
        held.offer("lift".into(), msg("2"), Device::Unborn);
        held.offer("feeder".into(), msg("f"), Device::Unborn);
        let gone = |d: &str| {
            if d == "lift" {
                Device::Gone
            } else {
                Device::Unborn
            }
        };
        assert_eq!(held.drop_gone(gone), 2);
        assert_eq!(held.len(), 1);
        assert_eq!(held.drop_gone(gone), 0);
    }

    #[test]
    fn it_is_full_at_its_bound_and_drains_everything_in_order() {
        let mut held = Held::new(2);
        held.offer("lift".into(), msg("1"), Device::Unborn);
        assert!(!held.full());
        held.offer("lift".into(), msg("2"), Device::Unborn);
        assert!(held.full());
        let all: Vec<String> = held
            .drain()
            .into_iter()
            .map(|(_, m)| name(&m).to_string())
            .collect();
        assert_eq!(all, ["1", "2"]);
        assert!(held.is_empty() && !held.full());
    }
}
