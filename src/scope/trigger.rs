//! What starts a capture, and the pure detector that watches the samples
//! for it.

use super::field;
use crate::drive::{Status, StatusField};

/// Which way a level is crossed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Edge {
    /// From below the level to at or above it.
    Rising,
    /// From above the level to at or below it.
    Falling,
}

/// A capture's trigger, with drives as unit addresses.
#[derive(Debug, Clone, PartialEq)]
pub enum Trigger {
    /// A field of a captured drive crosses a level.
    Level {
        /// The drive watched.
        unit: u8,
        /// The field.
        field: StatusField,
        /// The level, in the field's unit.
        level: f64,
        /// Which way.
        edge: Edge,
    },
    /// A captured drive reports a fault (its fault code leaves 0).
    Fault {
        /// The drive watched.
        unit: u8,
    },
    /// A captured drive stalls (its stall bit sets).
    Stall {
        /// The drive watched.
        unit: u8,
    },
    /// A write to the drive (or a broadcast) goes on the wire, from any
    /// face: HTTP, WebSocket, Modbus TCP, a lease's end, the shutdown.
    Write {
        /// The drive written to.
        unit: u8,
    },
    /// A client asks for it (`POST .../scope/trigger`).
    Manual,
    /// At once: the capture starts as it is armed.
    Immediate,
}

impl Trigger {
    /// The drive whose samples it watches, if any.
    pub fn watched_unit(&self) -> Option<u8> {
        match self {
            Trigger::Level { unit, .. } | Trigger::Fault { unit } | Trigger::Stall { unit } => {
                Some(*unit)
            }
            _ => None,
        }
    }

    /// Stable name: `rising`, `falling`, `fault`, `stall`, `write`,
    /// `manual`, `immediate`.
    pub fn kind(&self) -> &'static str {
        match self {
            Trigger::Level {
                edge: Edge::Rising, ..
            } => "rising",
            Trigger::Level {
                edge: Edge::Falling,
                ..
            } => "falling",
            Trigger::Fault { .. } => "fault",
            Trigger::Stall { .. } => "stall",
            Trigger::Write { .. } => "write",
            Trigger::Manual => "manual",
            Trigger::Immediate => "immediate",
        }
    }
}

/// Watches one drive's samples for a [`Trigger`]: every condition is an
/// edge (a change from one sample to the next), so a drive already stalled
/// when the capture is armed does not fire a stall trigger.
#[derive(Debug, Clone)]
pub struct Detector {
    trigger: Trigger,
    previous: Option<Status>,
}

impl Detector {
    /// A detector for `trigger`.
    pub fn new(trigger: Trigger) -> Self {
        Self {
            trigger,
            previous: None,
        }
    }

    /// The trigger watched.
    pub fn trigger(&self) -> &Trigger {
        &self.trigger
    }

    /// A sample of `unit`: `Some(what happened)` when it fires.
    pub fn sample(&mut self, unit: u8, status: &Status) -> Option<String> {
        if self.trigger.watched_unit() != Some(unit) {
            return None;
        }
        let previous = self.previous.replace(*status)?;
        match &self.trigger {
            Trigger::Level {
                field, level, edge, ..
            } => {
                let (before, now) = (
                    field::value(*field, &previous),
                    field::value(*field, status),
                );
                let crossed = match edge {
                    Edge::Rising => before < *level && now >= *level,
                    Edge::Falling => before > *level && now <= *level,
                };
                crossed.then(|| {
                    format!(
                        "{} went from {before} to {now} {}, crossing {level}",
                        field.name(),
                        field::unit(*field)
                    )
                    .replace("  ", " ")
                })
            }
            Trigger::Fault { .. } => (previous.fault().code() == 0 && status.fault().code() != 0)
                .then(|| format!("fault {}", status.fault().name())),
            Trigger::Stall { .. } => {
                (!previous.stalled() && status.stalled()).then(|| "the drive stalled".to_string())
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::status::FLAG_STALLED;

    fn speed(rpm: i16) -> Status {
        Status {
            speed_rpm: rpm,
            ..Status::default()
        }
    }

    #[test]
    fn rising_and_falling_edges() {
        let mut d = Detector::new(Trigger::Level {
            unit: 1,
            field: StatusField::SpeedRpm,
            level: 100.0,
            edge: Edge::Rising,
        });
        // The first sample has nothing to compare with.
        assert_eq!(d.sample(1, &speed(150)), None);
        assert_eq!(d.sample(1, &speed(50)), None);
        assert_eq!(d.sample(2, &speed(500)), None, "another drive");
        assert_eq!(
            d.sample(1, &speed(100)).as_deref(),
            Some("speed_rpm went from 50 to 100 rpm, crossing 100")
        );
        assert_eq!(d.sample(1, &speed(120)), None, "already above");
        let mut d = Detector::new(Trigger::Level {
            unit: 1,
            field: StatusField::SpeedRpm,
            level: 0.0,
            edge: Edge::Falling,
        });
        d.sample(1, &speed(10));
        assert!(d.sample(1, &speed(-1)).is_some());
    }

    #[test]
    fn stall_and_fault_fire_on_the_change_only() {
        let stalled = Status {
            flags: FLAG_STALLED,
            ..Status::default()
        };
        let mut d = Detector::new(Trigger::Stall { unit: 3 });
        d.sample(3, &stalled);
        assert_eq!(d.sample(3, &stalled), None, "stalled when armed");
        d.sample(3, &Status::default());
        assert!(d.sample(3, &stalled).is_some());
        let mut d = Detector::new(Trigger::Fault { unit: 3 });
        d.sample(3, &Status::default());
        let fault = Status {
            flags: 5,
            ..Status::default()
        };
        assert_eq!(d.sample(3, &fault).as_deref(), Some("fault under_voltage"));
    }
}
