//! What a write puts in the drive's registers, in engineering units and
//! raw: the words of the audit log, the replies of the REST API and the
//! events, the same whichever face sent the write.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::drive::units::COUNTS_PER_AMP;
use crate::drive::writes::PduMeaning;
use crate::drive::{DriveRequest, Register};
use crate::modbus::function::label;

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
    pub(crate) fn new(
        register: Register,
        quantity: &str,
        value: f64,
        unit: &str,
        raw: i64,
    ) -> Self {
        Written {
            register: register.name().to_string(),
            address: format!("0x{:04X}", register.address()),
            quantity: quantity.to_string(),
            value,
            unit: unit.to_string(),
            raw,
        }
    }

    pub(crate) fn flag(register: Register, on: bool, quantity: &str) -> Self {
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

/// A Modbus write PDU in words: the manual's message or the registers it
/// writes, when the register table explains it, and always the raw PDU as
/// the client sent it, with what was sent instead when the drive has not
/// its function (`sent`). A function code the core cannot decode is
/// "not checked": if it goes at all, it goes as it came.
pub fn describe_pdu(pdu: &[u8], meaning: &PduMeaning, sent: Option<&[u8]>) -> String {
    let function = pdu.first().copied().unwrap_or(0);
    let raw = match sent {
        Some(sent) => format!("{}, sent as {}", hex(pdu), hex(sent)),
        None => hex(pdu),
    };
    match meaning {
        PduMeaning::Message(request) => format!("{} [{raw}]", describe(request)),
        PduMeaning::Registers(writes) => {
            let parts: Vec<String> = writes
                .iter()
                .map(|(r, v)| format!("{}={}", r.name(), r.signed_value(*v)))
                .collect();
            format!("{} [{raw}]", parts.join(", "))
        }
        PduMeaning::Masked { register, and, or } => {
            format!("{} AND 0x{and:04X} OR 0x{or:04X} [{raw}]", register.name())
        }
        PduMeaning::Unknown => format!("Modbus 0x{function:02X} {} [{raw}]", label(function)),
        PduMeaning::NotDecoded { .. } => format!(
            "Modbus 0x{function:02X} {}, not checked [{raw}]",
            crate::modbus::function::name(function)
        ),
    }
}

/// The PDU as hex bytes, for logs.
pub fn hex(pdu: &[u8]) -> String {
    pdu.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::ConfigCommand;

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

    #[test]
    fn pdus_in_words() {
        let brake = [0x06, 0x00, 0x02, 0x00, 0x05];
        assert_eq!(
            describe_pdu(&brake, &crate::drive::writes::decode(&brake), None),
            "config command brake 5 (CONFIG=5) [06 00 02 00 05]"
        );
        let save = [0x06, 0x00, 0x1C, 0x00, 0x01];
        assert_eq!(
            describe_pdu(&save, &crate::drive::writes::decode(&save), None),
            "SPEED_TD_R_SAVE_FLAG=1 [06 00 1C 00 01]"
        );
        let meter = [0x06, 0x00, 0x01, 0x00, 0x02];
        assert_eq!(
            describe_pdu(&meter, &PduMeaning::Unknown, None),
            "Modbus 0x06 write_single_register [06 00 01 00 02]"
        );
        let coil = [0x05, 0x00, 0x01, 0xFF, 0x00];
        assert_eq!(
            describe_pdu(&coil, &PduMeaning::NotDecoded { function: 5 }, None),
            "Modbus 0x05 Write Single Coil, not checked [05 00 01 FF 00]"
        );
        let reset = [0x16, 0x00, 0x02, 0x00, 0x00, 0x00, 0x06];
        assert_eq!(
            describe_pdu(
                &reset,
                &crate::drive::writes::decode(&reset),
                Some(&[0x06, 0x00, 0x02, 0x00, 0x06])
            ),
            "config command factory-reset 6 (CONFIG=6) [16 00 02 00 00 00 06, sent as 06 00 02 00 06]"
        );
    }
}
