//! The write path the REST routes and the stream's commands share: checks
//! that the drive can take the request, sends it through the bus, waits for
//! the drive's confirmation, and writes the audit log. A request is never
//! reported done before the drive echoed or acknowledged it.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::auth::Caller;
use super::problem::{BusContext, Kind, Problem};
use super::state::Target;
use crate::audit;
use crate::bus::cache::Link;
use crate::bus::handle::JobOptions;
use crate::bus::{BusError, Priority};
use crate::drive::units::COUNTS_PER_AMP;
use crate::drive::{DriveReply, DriveRequest, Register, Status};

/// One register value written, in engineering units and raw.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Written {
    /// The register's name in the manual (`SPEED_REF`).
    pub register: String,
    /// Its address as the manual gives it (`0x0006`).
    pub address: String,
    /// What the value means.
    pub quantity: String,
    /// The value in engineering units.
    pub value: f64,
    /// The engineering unit (`rpm`, `deg`, `A`, `ms`; empty for plain numbers).
    pub unit: String,
    /// The raw 16-bit register value, as a signed or unsigned number.
    pub raw: i64,
}

impl Written {
    fn new(register: Register, quantity: &str, value: f64, unit: &str, raw: i64) -> Self {
        Written {
            register: register.name().to_string(),
            address: format!("0x{:04X}", register.address()),
            quantity: quantity.to_string(),
            value,
            unit: unit.to_string(),
            raw,
        }
    }

    fn flag(register: Register, on: bool, quantity: &str) -> Self {
        Written::new(
            register,
            quantity,
            f64::from(u8::from(on)),
            "",
            i64::from(on),
        )
    }
}

/// The registers a request writes, with their values (empty for a read).
pub fn written(request: &DriveRequest) -> Vec<Written> {
    match *request {
        DriveRequest::SetAddress { address } => vec![Written::new(
            Register::SlaveAddr,
            "drive address",
            f64::from(address),
            "",
            i64::from(address),
        )],
        DriveRequest::Config(command) => vec![Written::new(
            Register::Config,
            &format!("config command {}", command.name()),
            f64::from(command.code()),
            "",
            i64::from(command.code()),
        )],
        DriveRequest::Speed { rpm } => vec![Written::new(
            Register::SpeedRef,
            "speed setpoint",
            f64::from(rpm),
            "rpm",
            i64::from(rpm),
        )],
        DriveRequest::Position { centideg } => vec![Written::new(
            Register::PositionRef,
            "position setpoint",
            f64::from(centideg) / 100.0,
            "deg",
            i64::from(centideg),
        )],
        DriveRequest::Torque { counts } => vec![Written::new(
            Register::IqRef,
            "torque setpoint",
            f64::from(counts) / COUNTS_PER_AMP,
            "A",
            i64::from(counts),
        )],
        DriveRequest::ReadStatus => Vec::new(),
        DriveRequest::OverCurrent {
            limit_counts,
            stall_ms,
            save,
        } => vec![
            Written::new(
                Register::StalledCurr,
                "over-current limit",
                f64::from(limit_counts) / COUNTS_PER_AMP,
                "A",
                i64::from(limit_counts),
            ),
            Written::new(
                Register::StalledDurationMs,
                "stall time",
                f64::from(stall_ms),
                "ms",
                i64::from(stall_ms),
            ),
            Written::flag(Register::StalledCurrSaveFlag, save, "save to flash"),
        ],
        DriveRequest::SpeedRamp { alpha, save } => ramp_registers(
            alpha,
            save,
            [
                Register::SpeedTdRHigh,
                Register::SpeedTdRLow,
                Register::SpeedTdRSaveFlag,
            ],
        ),
        DriveRequest::PositionRamp { alpha, save } => ramp_registers(
            alpha,
            save,
            [
                Register::PositionTdRHigh,
                Register::PositionTdRLow,
                Register::PositionTdRSaveFlag,
            ],
        ),
        DriveRequest::LoadInertia { ratio, save } => vec![
            Written::new(
                Register::InertiaRatio,
                "load inertia ratio",
                f64::from(ratio),
                "x rotor",
                i64::from(ratio),
            ),
            Written::flag(Register::InertiaRatioSaveFlag, save, "save to flash"),
        ],
        DriveRequest::Rs485Control { enabled } => vec![Written::flag(
            Register::Use485Control,
            enabled,
            "RS-485 in control",
        )],
    }
}

fn ramp_registers(alpha: u32, save: bool, registers: [Register; 3]) -> Vec<Written> {
    let high = alpha >> 16;
    let low = alpha & 0xFFFF;
    vec![
        Written::new(
            registers[0],
            "ramp alpha, high 16 bits",
            f64::from(high),
            "",
            i64::from(high),
        ),
        Written::new(
            registers[1],
            "ramp alpha, low 16 bits",
            f64::from(low),
            "",
            i64::from(low),
        ),
        Written::flag(registers[2], save, "save to flash"),
    ]
}

/// The request in words, for the audit log.
pub fn describe(request: &DriveRequest) -> String {
    let parts: Vec<String> = written(request)
        .iter()
        .map(|w| {
            let sep = if w.unit.is_empty() { "" } else { " " };
            format!(
                "{} {}{sep}{} ({}={})",
                w.quantity, w.value, w.unit, w.register, w.raw
            )
        })
        .collect();
    if parts.is_empty() {
        request.name().to_string()
    } else {
        parts.join(", ")
    }
}

fn is_setpoint(request: &DriveRequest) -> bool {
    matches!(
        request,
        DriveRequest::Speed { .. } | DriveRequest::Position { .. } | DriveRequest::Torque { .. }
    )
}

/// True when the drive's polls have stopped getting answers.
pub fn is_offline(target: Target<'_>) -> bool {
    target
        .bus
        .drive(target.drive.unit)
        .is_some_and(|s| s.link == Link::Offline)
}

/// The options of a request made for `caller`.
fn options(caller: &Caller) -> JobOptions {
    JobOptions {
        priority: Priority::Command,
        source: caller.source,
        queue_timeout: None,
        max_attempts: None,
        origin: caller.origin.clone(),
    }
}

/// Writes the audit line of a write whose caller went away (the HTTP client
/// disconnected and its handler was dropped) before the drive answered: the
/// request may have reached the drive, and every write must be logged.
struct AbandonedWrite<'a> {
    who: &'a str,
    bus: &'a str,
    unit: u8,
    what: String,
    armed: bool,
}

impl Drop for AbandonedWrite<'_> {
    fn drop(&mut self) {
        if self.armed {
            let outcome: Result<String, &str> = Err(
                "the client went away before the drive answered; a request already on the wire was carried out, a queued one was dropped",
            );
            audit::write(self.who, self.bus, self.unit, &self.what, &outcome);
        }
    }
}

/// Sends `request` to the drive, waits for its confirmation, and logs it
/// (every write, confirmed or not, goes to the audit log with `caller.who`).
pub async fn send(
    caller: &Caller,
    target: Target<'_>,
    request: &DriveRequest,
) -> Result<DriveReply, Problem> {
    let unit = target.drive.unit;
    let offline = is_offline(target);
    let audit_unit = if request.is_broadcast() { 0 } else { unit };
    let mut guard = AbandonedWrite {
        who: &caller.who,
        bus: target.bus.name(),
        unit: audit_unit,
        what: describe(request),
        armed: request.is_write(),
    };
    let result = target.bus.execute(unit, request, options(caller)).await;
    if guard.armed {
        guard.armed = false;
        let outcome: Result<String, &BusError> = match &result {
            Ok(DriveReply::None) => Ok("sent as a broadcast (drives do not reply)".to_string()),
            Ok(_) => Ok("confirmed by the drive".to_string()),
            Err(e) => Err(e),
        };
        audit::write(
            &caller.who,
            target.bus.name(),
            audit_unit,
            &guard.what,
            &outcome,
        );
    }
    result.map_err(|e| {
        Problem::bus(
            &e,
            BusContext {
                drive: Some(&target.drive.name),
                offline,
                setpoint: is_setpoint(request),
            },
        )
    })
}

/// Reads the drive's status now (not from the poll cache).
pub async fn read_status(caller: &Caller, target: Target<'_>) -> Result<Status, Problem> {
    match send(caller, target, &DriveRequest::ReadStatus).await? {
        DriveReply::Status(s) => Ok(s),
        _ => Err(Problem::new(
            Kind::DriveUnconfirmed,
            "the drive's reply to a status read carried no status",
        )
        .for_drive(&target.drive.name)),
    }
}

/// Refuses a setpoint to a drive that is not active. The poll cache may
/// predate an activation sent a moment ago, so an inactive cached status is
/// confirmed with a fresh read before refusing.
pub async fn ensure_active(caller: &Caller, target: Target<'_>) -> Result<(), Problem> {
    let cached = target.bus.drive(target.drive.unit).and_then(|s| s.status);
    match cached {
        Some(s) if s.active() => return Ok(()),
        // Never polled yet: let the drive decide (it answers 0x04 if inactive).
        None => return Ok(()),
        Some(_) => {}
    }
    if read_status(caller, target).await?.active() {
        Ok(())
    } else {
        Err(Problem::new(
            Kind::DriveNotActive,
            format!(
                "drive \"{}\" is not active: it takes setpoints only when active; send the activate command first",
                target.drive.name
            ),
        )
        .for_drive(&target.drive.name))
    }
}

/// Refuses a save to flash while the motor turns (the manual requires
/// standstill), unless `force`; reads the drive now, since a save is rare
/// and the cache may be a poll old.
pub async fn ensure_still(caller: &Caller, target: Target<'_>, force: bool) -> Result<(), Problem> {
    let status = read_status(caller, target).await?;
    if status.speed_rpm == 0 {
        return Ok(());
    }
    if force {
        tracing::warn!(
            target: "drivegate::audit",
            who = %caller.who,
            drive = %target.drive.name,
            speed_rpm = status.speed_rpm,
            "saving to flash while the motor turns, as forced"
        );
        return Ok(());
    }
    Err(Problem::new(
        Kind::DriveMoving,
        format!(
            "drive \"{}\" turns at {} rpm: the manual allows saving to flash only at standstill; stop the motor first, or send \"force\": true",
            target.drive.name, status.speed_rpm
        ),
    )
    .for_drive(&target.drive.name))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::ConfigCommand;

    #[test]
    fn an_abandoned_write_is_still_audited() {
        #[derive(Clone, Default)]
        struct Buffer(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);
        impl std::io::Write for Buffer {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                self.0.lock().unwrap().extend_from_slice(b);
                Ok(b.len())
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let buffer = Buffer::default();
        let writer = buffer.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_writer(move || writer.clone())
            .with_ansi(false)
            .finish();
        tracing::subscriber::with_default(subscriber, || {
            let done = AbandonedWrite {
                who: "scada",
                bus: "line1",
                unit: 3,
                what: describe(&DriveRequest::Speed { rpm: 50 }),
                armed: false,
            };
            drop(done);
            let abandoned = AbandonedWrite {
                who: "scada",
                bus: "line1",
                unit: 3,
                what: describe(&DriveRequest::Speed { rpm: 60 }),
                armed: true,
            };
            drop(abandoned);
        });
        let text = String::from_utf8(buffer.0.lock().unwrap().clone()).unwrap();
        assert!(!text.contains("speed setpoint 50"), "{text}");
        assert!(
            text.contains("drivegate::audit")
                && text.contains("speed setpoint 60")
                && text.contains("went away"),
            "{text}"
        );
    }

    #[test]
    fn written_values_in_units_and_raw() {
        let w = written(&DriveRequest::Torque { counts: -64 });
        assert_eq!((w[0].value, w[0].raw, w[0].unit.as_str()), (-0.5, -64, "A"));
        assert_eq!(w[0].address, "0x000A");
        let w = written(&DriveRequest::SpeedRamp {
            alpha: 0x0001_86A0,
            save: true,
        });
        assert_eq!(
            w.iter().map(|w| w.raw).collect::<Vec<_>>(),
            vec![1, 0x86A0, 1]
        );
        assert_eq!(w[0].register, "SPEED_TD_R_HIGH");
        assert!(written(&DriveRequest::ReadStatus).is_empty());
        assert_eq!(
            describe(&DriveRequest::Position { centideg: 9000 }),
            "position setpoint 90 deg (POSITION_REF=9000)"
        );
        assert_eq!(
            describe(&DriveRequest::Config(ConfigCommand::EmergencyBrake)),
            "config command brake 5 (CONFIG=5)"
        );
    }
}
