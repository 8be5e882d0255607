//! Per-drive series, read from each bus's poll cache at scrape time.
//!
//! Every series carries `bus`, `unit` and `name`. The values of a status
//! (temperature, voltage, flags, faults...) are exported only while the
//! drive's data is live (`crate::bus::freshness`, the answer every face
//! shows): when its polls go missing, it stops answering, or its bus's
//! port is down, they vanish and `drivegate_drive_up` turns 0, so a
//! dashboard shows a gap and an alert on a value resolves into the
//! "offline" alert instead of holding on to a value nobody has read for a
//! while. `drivegate_drive_freshness` says which of those it is.

use std::sync::Arc;
use std::time::UNIX_EPOCH;

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Family, Kind, Spec};
use crate::bus::freshness::Freshness;
use crate::drive::{Fault, Mode, Status};
use crate::plant::Plant;

const LABELS: &[&str] = &["bus", "unit", "name"];

static UP: Spec = Spec {
    name: "drivegate_drive_up",
    help: "1 while the drive's data is live (it answers its status polls within its poll \
           period, on a working bus), 0 when it is stale, offline, its bus is down or it has \
           not answered yet.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static FRESHNESS: Spec = Spec {
    name: "drivegate_drive_freshness",
    help: "How fresh the drive's data is: 1 on the series of its state (live, stale, offline, \
           never, bus-down), 0 on the others.",
    kind: Kind::Gauge,
    labels: &["bus", "unit", "name", "freshness"],
};
static LAST_POLL: Spec = Spec {
    name: "drivegate_drive_last_status_timestamp_seconds",
    help: "Unix time of the last good status read from the drive (kept while it is offline).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static FAILURES: Spec = Spec {
    name: "drivegate_drive_consecutive_poll_failures",
    help: "Status polls of the drive that failed in a row (0 while it answers).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static POLL_INTERVAL: Spec = Spec {
    name: "drivegate_drive_poll_interval_seconds",
    help: "Configured status poll interval; 0 = as often as the bus allows (the wire is then \
           busy all the time by design).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static TEMPERATURE: Spec = Spec {
    name: "drivegate_drive_temperature_celsius",
    help: "Drive temperature (TEMP register), degrees Celsius.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static VOLTAGE: Spec = Spec {
    name: "drivegate_drive_supply_voltage_volts",
    help: "Drive supply voltage (VOLT register), volts.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static CURRENT: Spec = Spec {
    name: "drivegate_drive_current_amperes",
    help: "Motor current Iq (IQ register / 128), amperes; negative when braking or reversing.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static SPEED: Spec = Spec {
    name: "drivegate_drive_speed_rpm",
    help: "Speed at the gearbox output (SPEED register), revolutions per minute.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static ANGLE: Spec = Spec {
    name: "drivegate_drive_angle_degrees",
    help: "Angle within the turn (ANGLE register / 100), degrees, -180 to 180.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static TURNS: Spec = Spec {
    name: "drivegate_drive_turns",
    help: "Turn counter (CYCLE_NUM register), 0 to 65535, wrapping.",
    kind: Kind::Gauge,
    labels: LABELS,
};
static ACTIVE: Spec = Spec {
    name: "drivegate_drive_active",
    help: "1 while the drive is activated (STATUS bit 7).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static CALIBRATED: Spec = Spec {
    name: "drivegate_drive_calibrated",
    help: "1 once the encoder is calibrated (STATUS bit 6).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static STALLED: Spec = Spec {
    name: "drivegate_drive_stalled",
    help: "1 while a stall is latched (STATUS bit 5; needs a fault reset).",
    kind: Kind::Gauge,
    labels: LABELS,
};
static MODE: Spec = Spec {
    name: "drivegate_drive_mode",
    help: "Control mode (STATUS bits 4..3): 1 on the series of the current mode \
           (open_loop, speed, position, torque), 0 on the others.",
    kind: Kind::Gauge,
    labels: &["bus", "unit", "name", "mode"],
};
static FAULT: Spec = Spec {
    name: "drivegate_drive_fault",
    help: "1 on the series of the fault the drive reports (STATUS bits 2..0), 0 on the others.",
    kind: Kind::Gauge,
    labels: &["bus", "unit", "name", "fault"],
};
static FAULT_CODE: Spec = Spec {
    name: "drivegate_drive_fault_code",
    help: "Raw fault code (STATUS bits 2..0): 0 none, 1 current sense, 2 encoder, 3 power stage, \
           4 over-temperature, 5 under-voltage, 6 over-voltage, 7 reserved.",
    kind: Kind::Gauge,
    labels: LABELS,
};

static SPECS: [&Spec; 17] = [
    &UP,
    &FRESHNESS,
    &LAST_POLL,
    &FAILURES,
    &POLL_INTERVAL,
    &TEMPERATURE,
    &VOLTAGE,
    &CURRENT,
    &SPEED,
    &ANGLE,
    &TURNS,
    &ACTIVE,
    &CALIBRATED,
    &STALLED,
    &MODE,
    &FAULT,
    &FAULT_CODE,
];

/// Whether a fault kind has a 0/1 series of its own: every fault but
/// "healthy" and code 7, which is reserved by the maker and shows only in
/// the raw code. A match, so a new kind cannot be left out unnoticed.
const fn has_series(fault: Fault) -> bool {
    match fault {
        Fault::None | Fault::Reserved => false,
        Fault::CurrentSense
        | Fault::Encoder
        | Fault::PowerStage
        | Fault::OverTemperature
        | Fault::UnderVoltage
        | Fault::OverVoltage => true,
    }
}

/// Exports every configured drive from its bus's poll cache.
pub(crate) struct DriveCollector {
    plant: Arc<Plant>,
    descs: Vec<Desc>,
}

impl DriveCollector {
    pub(crate) fn new(plant: Arc<Plant>) -> Self {
        let descs = SPECS.iter().map(|s| s.desc()).collect();
        Self { plant, descs }
    }
}

/// The families of one scrape.
struct Families {
    up: Family,
    freshness: Family,
    last_poll: Family,
    failures: Family,
    poll_interval: Family,
    temperature: Family,
    voltage: Family,
    current: Family,
    speed: Family,
    angle: Family,
    turns: Family,
    active: Family,
    calibrated: Family,
    stalled: Family,
    mode: Family,
    fault: Family,
    fault_code: Family,
}

impl Families {
    fn new() -> Self {
        Self {
            up: UP.family(),
            freshness: FRESHNESS.family(),
            last_poll: LAST_POLL.family(),
            failures: FAILURES.family(),
            poll_interval: POLL_INTERVAL.family(),
            temperature: TEMPERATURE.family(),
            voltage: VOLTAGE.family(),
            current: CURRENT.family(),
            speed: SPEED.family(),
            angle: ANGLE.family(),
            turns: TURNS.family(),
            active: ACTIVE.family(),
            calibrated: CALIBRATED.family(),
            stalled: STALLED.family(),
            mode: MODE.family(),
            fault: FAULT.family(),
            fault_code: FAULT_CODE.family(),
        }
    }

    fn status(&mut self, l: &[&str; 3], s: &Status) {
        self.temperature.set(l, f64::from(s.temperature_c));
        self.voltage.set(l, f64::from(s.voltage_v));
        self.current.set(l, s.current_a());
        self.speed.set(l, f64::from(s.speed_rpm));
        self.angle.set(l, s.angle_deg());
        self.turns.set(l, f64::from(s.turns));
        self.active.set_bool(l, s.active());
        self.calibrated.set_bool(l, s.calibrated());
        self.stalled.set_bool(l, s.stalled());
        let [bus, unit, name] = *l;
        for mode in Mode::ALL {
            self.mode
                .set_bool(&[bus, unit, name, mode.name()], s.mode() == mode);
        }
        for fault in Fault::ALL.into_iter().filter(|&f| has_series(f)) {
            self.fault
                .set_bool(&[bus, unit, name, fault.name()], s.fault() == fault);
        }
        self.fault_code.set(l, f64::from(s.fault().code()));
    }

    fn finish(self) -> Vec<MetricFamily> {
        [
            self.up,
            self.freshness,
            self.last_poll,
            self.failures,
            self.poll_interval,
            self.temperature,
            self.voltage,
            self.current,
            self.speed,
            self.angle,
            self.turns,
            self.active,
            self.calibrated,
            self.stalled,
            self.mode,
            self.fault,
            self.fault_code,
        ]
        .into_iter()
        .map(Family::finish)
        .collect()
    }
}

impl Collector for DriveCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut f = Families::new();
        let plant = self.plant.now();
        let now = std::time::Instant::now();
        for (index, bus) in plant.indexed_buses() {
            let snapshots = bus.handle.drives();
            let verdicts = bus.handle.freshness_all(now);
            for drive in plant.drives().filter(|d| d.bus == index) {
                let unit = drive.unit.to_string();
                let l = [bus.handle.name(), unit.as_str(), drive.name.as_str()];
                let snap = snapshots.iter().find(|s| s.unit == drive.unit);
                let status = snap.and_then(|s| s.status.as_ref());
                let freshness = verdicts
                    .iter()
                    .find(|(u, _)| *u == drive.unit)
                    .map_or(Freshness::Never, |(_, v)| v.freshness);
                let up = freshness.is_live();
                f.up.set_bool(&l, up && status.is_some());
                let [b, u, n] = l;
                for state in Freshness::ALL {
                    f.freshness
                        .set_bool(&[b, u, n, state.name()], state == freshness);
                }
                if let Some(seen) = snap
                    .and_then(|s| s.seen_at)
                    .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
                {
                    f.last_poll.set(&l, seen.as_secs_f64());
                }
                f.failures
                    .set(&l, f64::from(snap.map_or(0, |s| s.consecutive_failures)));
                if let Some(config) = bus.config.drives.iter().find(|d| d.unit() == drive.unit) {
                    let ms = config
                        .poll_interval_ms
                        .unwrap_or(bus.config.poll_interval_ms);
                    f.poll_interval.set(&l, ms as f64 / 1000.0);
                }
                if let (true, Some(status)) = (up, status) {
                    f.status(&l, status);
                }
            }
        }
        f.finish()
    }
}
