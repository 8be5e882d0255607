//! The drives on one simulated bus and what happens to a framed request:
//! who hears it, who answers, what faults befall the answer. Pure code: the
//! caller passes the time and does the I/O.
//!
//! Each drive's model is advanced lazily, from the time it was last looked
//! at, whenever a request reaches it or the handle reads it.

use std::time::{Duration, Instant};

use super::config::SimConfig;
use super::device::RegisterDevice;
use super::faults::{FaultInjector, FaultRates, Noise};
use super::model::{DriveModel, SimDriveView};
use super::slave;
use super::stats::{GapHistogram, SimStats};
use crate::modbus::crc::crc_bytes;
use crate::modbus::function::{WRITE_MULTIPLE_REGISTERS, WRITE_SINGLE_REGISTER};
use crate::modbus::rtu_frame;

/// A drive and the time its model was last advanced to.
#[derive(Debug)]
struct Slot {
    /// Its unit in the configuration (its address at power-on: a write
    /// may have given it another since).
    unit: u8,
    model: DriveModel,
    clock: Instant,
    /// See [`SimDriveConfig::frame_gap`](super::config::SimDriveConfig).
    frame_gap: Option<Duration>,
}

impl Slot {
    /// True when a frame after `silence` is one garbled frame with the
    /// last, to this drive.
    fn merges(&self, silence: Option<Duration>) -> bool {
        matches!((self.frame_gap, silence), (Some(gap), Some(s)) if s < gap)
    }
}

impl Slot {
    fn advance_to(&mut self, now: Instant) {
        if now > self.clock {
            self.model.advance((now - self.clock).as_secs_f64());
            self.clock = now;
        }
    }
}

/// What the wire must do after a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Outcome {
    /// A reply frame is in the caller's buffer.
    pub reply: bool,
    /// Extra delay before it (injected lateness).
    pub late: Duration,
    /// Noise to write about t3.5 after it.
    pub noise: Option<Noise>,
    /// The answering drive's frame gap, after which it answers (`None`:
    /// t3.5).
    pub frame_gap: Option<Duration>,
}

/// The simulated drives, the fault injection and the counters.
#[derive(Debug)]
pub struct Bus {
    slots: Vec<Slot>,
    devices: Vec<RegisterDevice>,
    faults: FaultInjector,
    stats: SimStats,
    gaps: GapHistogram,
    pdu: Vec<u8>,
    scratch: Vec<u8>,
    /// Units that go silent once they have carried out this many more
    /// writes (a drive that stops answering part-way through a sequence).
    silent_after_writes: Vec<(u8, u32)>,
    /// The fault rates and seed last configured: a reload that keeps them
    /// keeps the rates set at runtime too.
    configured_faults: (FaultRates, u64),
}

impl Bus {
    /// The drives of `config`, powered on at `now`.
    pub fn new(config: &SimConfig, now: Instant) -> Self {
        let reboot = config.reboot_ms / 1000.0;
        Bus {
            slots: config
                .drives
                .iter()
                .map(|d| Slot {
                    unit: d.unit,
                    model: DriveModel::new(d.unit, d.gear_ratio, config.calibrated, reboot),
                    clock: now,
                    frame_gap: d.frame_gap,
                })
                .collect(),
            devices: config
                .devices
                .iter()
                .map(|&u| RegisterDevice::new(u))
                .collect(),
            faults: FaultInjector::new(config.faults.clone(), config.seed),
            stats: SimStats::default(),
            gaps: GapHistogram::default(),
            pdu: Vec::with_capacity(256),
            scratch: Vec::with_capacity(256),
            silent_after_writes: Vec::new(),
            configured_faults: (config.faults.clone(), config.seed),
        }
    }

    /// Follows `config` at `now` (a reload): the drives on the line stay
    /// as they are (turning, in their mode, at their position: a reload
    /// is no power cut), taking its frame separation; those it adds join
    /// the line as a technician wires them in, fresh from the factory;
    /// those it no longer names stay wired as they are (a drive taken out
    /// of the configuration is not taken off the line: it is found as it
    /// was if it comes back). The devices follow alike, and new fault
    /// rates or a new seed apply from the next request.
    pub fn follow(&mut self, config: &SimConfig, now: Instant) {
        let reboot = config.reboot_ms / 1000.0;
        for d in &config.drives {
            match self.slots.iter_mut().find(|s| s.unit == d.unit) {
                Some(slot) => slot.frame_gap = d.frame_gap,
                None => self.slots.push(Slot {
                    unit: d.unit,
                    model: DriveModel::new(d.unit, d.gear_ratio, config.calibrated, reboot),
                    clock: now,
                    frame_gap: d.frame_gap,
                }),
            }
        }
        for &unit in &config.devices {
            if self.device(unit).is_none() {
                self.devices.push(RegisterDevice::new(unit));
            }
        }
        let faults = (config.faults.clone(), config.seed);
        if faults != self.configured_faults {
            if faults.1 == self.configured_faults.1 {
                self.faults.set_rates(faults.0.clone());
            } else {
                self.faults = FaultInjector::new(faults.0.clone(), faults.1);
            }
            self.configured_faults = faults;
        }
    }

    /// The counters.
    pub fn stats(&self) -> SimStats {
        self.stats
    }

    /// The counters, for the wire to update.
    pub fn stats_mut(&mut self) -> &mut SimStats {
        &mut self.stats
    }

    /// The silences seen before each request.
    pub fn gaps(&self) -> &GapHistogram {
        &self.gaps
    }

    /// Counts the silence before a request.
    pub fn record_gap(&mut self, gap: Duration) {
        self.gaps.record(gap);
    }

    /// The fault rates in force.
    pub fn fault_rates(&self) -> &FaultRates {
        self.faults.rates()
    }

    /// Changes the fault rates.
    pub fn set_fault_rates(&mut self, rates: FaultRates) {
        self.faults.set_rates(rates);
    }

    /// Sets the silence after which the drive at `unit` parts frames
    /// (`None`: by length); false when there is no such drive.
    pub fn set_frame_gap(&mut self, unit: u8, gap: Option<Duration>) -> bool {
        let mut found = false;
        for slot in self.slots.iter_mut().filter(|s| s.model.address() == unit) {
            slot.frame_gap = gap;
            found = true;
        }
        found
    }

    /// Makes `unit` silent or lets it answer again.
    pub fn set_silent(&mut self, unit: u8, silent: bool) {
        self.faults.set_silent(unit, silent);
    }

    /// Makes `unit` silent once it has carried out `writes` more writes
    /// (function 0x06 or 0x10): reads do not count, so a sequence of writes
    /// can be cut after its first whatever the polls between them.
    pub fn silence_after_writes(&mut self, unit: u8, writes: u32) {
        self.silent_after_writes.retain(|&(u, _)| u != unit);
        if writes == 0 {
            self.set_silent(unit, true);
        } else {
            self.silent_after_writes.push((unit, writes));
        }
    }

    /// Counts a write `unit` carried out, silencing it after its last.
    fn count_write(&mut self, unit: u8) {
        let Some(entry) = self
            .silent_after_writes
            .iter_mut()
            .find(|(u, _)| *u == unit)
        else {
            return;
        };
        entry.1 = entry.1.saturating_sub(1);
        if entry.1 == 0 {
            self.silent_after_writes.retain(|&(u, _)| u != unit);
            self.set_silent(unit, true);
        }
    }

    /// The drive answering to `unit` (its address now), advanced to `now`.
    pub fn drive(&mut self, unit: u8, now: Instant) -> Option<&mut DriveModel> {
        let slot = self.slots.iter_mut().find(|s| s.model.address() == unit)?;
        slot.advance_to(now);
        Some(&mut slot.model)
    }

    /// The plain register device at `unit`, if there is one.
    pub fn device(&self, unit: u8) -> Option<&RegisterDevice> {
        self.devices.iter().find(|d| d.unit() == unit)
    }

    /// Snapshots of every drive, advanced to `now`, in configuration order.
    pub fn views(&mut self, now: Instant) -> Vec<SimDriveView> {
        self.slots
            .iter_mut()
            .map(|slot| {
                slot.advance_to(now);
                slot.model.view()
            })
            .collect()
    }

    /// Handles one framed request heard at `now`, `silence` after the last
    /// frame on the line (`None`: unknown, long); a reply frame, if any, is
    /// left in `reply`.
    pub fn request(
        &mut self,
        frame: &[u8],
        now: Instant,
        silence: Option<Duration>,
        reply: &mut Vec<u8>,
    ) -> Outcome {
        reply.clear();
        let Ok((unit, pdu)) = rtu_frame::decode(frame) else {
            self.stats.bad_crc_requests += 1;
            return Outcome::default();
        };
        self.stats.requests += 1;
        if unit == 0 {
            self.stats.broadcasts += 1;
            for slot in &mut self.slots {
                slot.advance_to(now);
                if slot.model.online()
                    && !slot.merges(silence)
                    && !self.faults.rates().is_silent(slot.model.address())
                {
                    slave::broadcast(&mut slot.model, pdu, &mut self.scratch);
                }
            }
            return Outcome::default();
        }
        if self.faults.rates().is_silent(unit) {
            self.stats.unanswered += 1;
            return Outcome::default();
        }
        let (answering, frame_gap) = self.answer(unit, pdu, now, silence, reply);
        if answering == 0 {
            self.stats.unanswered += 1;
            return Outcome::default();
        }
        if answering > 1 {
            self.stats.collisions += 1;
        }
        if matches!(
            pdu.first(),
            Some(&(WRITE_SINGLE_REGISTER | WRITE_MULTIPLE_REGISTERS))
        ) {
            self.count_write(unit);
        }
        let fate = self.faults.decide();
        if fate.drop {
            self.stats.dropped += 1;
            reply.clear();
            return Outcome::default();
        }
        if let Some((byte, mask)) = fate.corrupt {
            let at = reply.len() - 2 + byte;
            reply[at] ^= mask;
            self.stats.corrupted += 1;
        }
        if fate.late.is_some() {
            self.stats.late += 1;
        }
        if fate.noise.is_some() {
            self.stats.noise_bursts += 1;
        }
        self.stats.replies += 1;
        Outcome {
            reply: true,
            late: fate.late.unwrap_or_default(),
            noise: fate.noise,
            frame_gap,
        }
    }

    /// The drives and devices at `unit` answer `pdu` heard at `now`
    /// `silence` after the last frame: their reply (collided, if more than
    /// one) into `reply`; how many answered, and the first drive's frame
    /// gap.
    fn answer(
        &mut self,
        unit: u8,
        pdu: &[u8],
        now: Instant,
        silence: Option<Duration>,
        reply: &mut Vec<u8>,
    ) -> (u32, Option<Duration>) {
        let mut answering = 0;
        let mut frame_gap = None;
        for slot in &mut self.slots {
            if slot.model.address() != unit {
                continue;
            }
            slot.advance_to(now);
            if slot.merges(silence) {
                // Heard as one garbled frame with the last: no CRC holds.
                self.stats.merged_frames += 1;
                continue;
            }
            if !slot.model.online() {
                continue;
            }
            frame_gap = slot.frame_gap;
            let exception = slave::answer(&mut slot.model, pdu, &mut self.pdu);
            answering += 1;
            if answering == 1 {
                if exception.is_some() {
                    self.stats.exceptions += 1;
                }
                frame_into(reply, unit, &self.pdu);
            } else {
                // Two drivers on the line at once: the bytes collide.
                frame_into(&mut self.scratch, unit, &self.pdu);
                collide(reply, &self.scratch);
            }
        }
        for device in self.devices.iter_mut().filter(|d| d.unit() == unit) {
            let exception = device.answer(pdu, &mut self.pdu);
            answering += 1;
            if answering == 1 {
                if exception.is_some() {
                    self.stats.exceptions += 1;
                }
                frame_into(reply, unit, &self.pdu);
            } else {
                frame_into(&mut self.scratch, unit, &self.pdu);
                collide(reply, &self.scratch);
            }
        }
        (answering, frame_gap)
    }
}

/// `rtu_frame::encode` into a reusable buffer (no allocation per reply).
fn frame_into(out: &mut Vec<u8>, unit: u8, pdu: &[u8]) {
    out.clear();
    out.push(unit);
    out.extend_from_slice(pdu);
    let crc = crc_bytes(out);
    out.extend_from_slice(&crc);
}

/// Two replies driven at once: a 0 from either driver wins each bit, the
/// longer frame's tail goes through.
fn collide(line: &mut Vec<u8>, other: &[u8]) {
    for (i, &b) in other.iter().enumerate() {
        match line.get_mut(i) {
            Some(x) => *x &= b,
            None => line.push(b),
        }
    }
}

/// Locks the shared bus; a panic elsewhere does not make its state unusable.
pub(super) fn lock(bus: &std::sync::Mutex<Bus>) -> std::sync::MutexGuard<'_, Bus> {
    bus.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::{ConfigCommand, DriveRequest, Status};

    fn bus(units: &[u8]) -> (Bus, Instant) {
        let now = Instant::now();
        (
            Bus::new(&SimConfig::for_units(units.iter().copied()), now),
            now,
        )
    }

    fn send(bus: &mut Bus, unit: u8, req: DriveRequest, now: Instant) -> Option<Vec<u8>> {
        let mut reply = Vec::new();
        let frame = req.frame(unit).unwrap();
        bus.request(&frame, now, None, &mut reply)
            .reply
            .then_some(reply)
    }

    #[test]
    fn only_the_addressed_drive_answers() {
        let (mut bus, now) = bus(&[1, 2]);
        let reply = send(&mut bus, 2, DriveRequest::ReadStatus, now).unwrap();
        assert_eq!(reply[0], 2);
        assert!(crate::modbus::crc::frame_crc_ok(&reply));
        assert_eq!(
            rtu_frame::decode(&reply).unwrap().1.len(),
            2 + Status::BYTES
        );
        assert_eq!(send(&mut bus, 9, DriveRequest::ReadStatus, now), None);
        let s = bus.stats();
        assert_eq!((s.requests, s.replies, s.unanswered), (2, 1, 1));
    }

    #[test]
    fn bad_crc_is_ignored_and_counted() {
        let (mut bus, now) = bus(&[1]);
        let mut frame = DriveRequest::ReadStatus.frame(1).unwrap();
        frame[7] ^= 1;
        let mut reply = Vec::new();
        assert!(!bus.request(&frame, now, None, &mut reply).reply);
        assert_eq!((bus.stats().bad_crc_requests, bus.stats().requests), (1, 0));
    }

    #[test]
    fn broadcast_address_setting_readdresses_every_drive() {
        let (mut bus, now) = bus(&[1, 2]);
        assert_eq!(
            send(&mut bus, 0, DriveRequest::SetAddress { address: 5 }, now),
            None
        );
        assert_eq!(bus.stats().broadcasts, 1);
        assert!(bus.drive(1, now).is_none() && bus.drive(2, now).is_none());
        assert_eq!(bus.drive(5, now).map(|d| d.address()), Some(5));
        // Both answer at address 5 now: their replies collide on the wire.
        let reply = send(
            &mut bus,
            5,
            DriveRequest::Config(ConfigCommand::Activate),
            now,
        )
        .unwrap();
        assert_eq!(
            reply,
            DriveRequest::Config(ConfigCommand::Activate)
                .frame(5)
                .unwrap()
        );
        assert_eq!(bus.stats().collisions, 1);
    }

    #[test]
    fn silent_units_and_rebooting_drives_do_not_answer() {
        let (mut bus, now) = bus(&[1, 2]);
        bus.set_silent(2, true);
        assert_eq!(send(&mut bus, 2, DriveRequest::ReadStatus, now), None);
        bus.drive(1, now).unwrap().power_cycle();
        assert_eq!(send(&mut bus, 1, DriveRequest::ReadStatus, now), None);
        let later = now + Duration::from_millis(301);
        assert!(send(&mut bus, 1, DriveRequest::ReadStatus, later).is_some());
        assert_eq!(bus.stats().unanswered, 2);
    }

    #[test]
    fn a_unit_can_go_silent_after_some_writes() {
        let (mut bus, now) = bus(&[1]);
        bus.silence_after_writes(1, 2);
        let inertia = |ratio| DriveRequest::LoadInertia { ratio, save: false };
        assert!(send(&mut bus, 1, inertia(2), now).is_some());
        // Reads do not count.
        assert!(send(&mut bus, 1, DriveRequest::ReadStatus, now).is_some());
        assert!(send(&mut bus, 1, inertia(3), now).is_some());
        assert_eq!(send(&mut bus, 1, DriveRequest::ReadStatus, now), None);
        assert_eq!(send(&mut bus, 1, inertia(4), now), None);
        assert_eq!(bus.drive(1, now).unwrap().view().settings.inertia_ratio, 3);
        bus.set_silent(1, false);
        assert!(send(&mut bus, 1, DriveRequest::ReadStatus, now).is_some());
    }

    #[test]
    fn exceptions_are_counted_and_faults_applied() {
        let (mut bus, now) = bus(&[1]);
        let reply = send(&mut bus, 1, DriveRequest::Speed { rpm: 5 }, now).unwrap();
        assert_eq!(reply[1], 0x86, "an exception: the drive is not active");
        assert_eq!(bus.stats().exceptions, 1);
        bus.set_fault_rates(FaultRates {
            crc_error_rate: 1.0,
            ..FaultRates::default()
        });
        let reply = send(&mut bus, 1, DriveRequest::ReadStatus, now).unwrap();
        assert!(!crate::modbus::crc::frame_crc_ok(&reply));
        bus.set_fault_rates(FaultRates {
            drop_rate: 1.0,
            ..FaultRates::default()
        });
        assert_eq!(send(&mut bus, 1, DriveRequest::ReadStatus, now), None);
        let s = bus.stats();
        assert_eq!((s.corrupted, s.dropped, s.replies), (1, 1, 2));
    }

    #[test]
    fn plain_devices_answer_long_reads() {
        let now = Instant::now();
        let mut config = SimConfig::for_units([1]);
        config.devices = vec![100];
        let mut bus = Bus::new(&config, now);
        let frame = rtu_frame::encode(100, &[0x03, 0x00, 0x00, 0x00, 125]);
        let mut reply = Vec::new();
        assert!(bus.request(&frame, now, None, &mut reply).reply);
        assert_eq!(reply.len(), 255, "the longest RTU frame");
        assert_eq!(&reply[..3], &[100, 0x03, 250]);
        assert!(crate::modbus::crc::frame_crc_ok(&reply));
        assert_eq!(bus.device(100).map(|d| d.register(3)), Some(3));
    }

    #[test]
    fn models_advance_with_the_clock() {
        let (mut bus, now) = bus(&[1]);
        for req in [
            DriveRequest::Config(ConfigCommand::Activate),
            DriveRequest::Config(ConfigCommand::SpeedMode),
            DriveRequest::Speed { rpm: 100 },
        ] {
            send(&mut bus, 1, req, now).unwrap();
        }
        let later = now + Duration::from_millis(500);
        assert_eq!(bus.drive(1, later).unwrap().status().speed_rpm, 100);
    }

    #[test]
    fn a_reload_keeps_the_drives_on_the_line_as_they_are() {
        let (mut bus, now) = bus(&[1, 2]);
        for req in [
            DriveRequest::Config(ConfigCommand::Activate),
            DriveRequest::Config(ConfigCommand::SpeedMode),
            DriveRequest::Speed { rpm: 100 },
        ] {
            send(&mut bus, 1, req, now).unwrap();
        }
        bus.set_silent(2, true);
        // Units 1 and 2 out of the configuration, unit 3 in: unit 1 turns
        // on, still wired.
        let later = now + Duration::from_millis(500);
        let mut config = SimConfig::for_units([3]);
        config.devices = vec![100];
        bus.follow(&config, later);
        let one = bus
            .drive(1, later + Duration::from_millis(100))
            .unwrap()
            .view();
        assert!(
            one.active && one.mode == crate::drive::Mode::Speed,
            "{one:?}"
        );
        assert_eq!(one.status.speed_rpm, 100);
        let three = bus.drive(3, later).unwrap().view();
        assert!(!three.active, "a drive wired in is fresh from the factory");
        assert!(bus.device(100).is_some());
        // Back in the configuration, unit 1 is found as it was.
        bus.follow(&SimConfig::for_units([1, 3]), later);
        assert_eq!(bus.views(later).len(), 3);
        assert!(bus.drive(1, later).unwrap().view().active);
        // The same fault rates: the silent unit set at runtime stays so.
        assert!(bus.fault_rates().is_silent(2));
        config.faults.drop_rate = 1.0;
        bus.follow(&config, later);
        assert!(!bus.fault_rates().is_silent(2));
        assert_eq!(send(&mut bus, 1, DriveRequest::ReadStatus, later), None);
    }
}
