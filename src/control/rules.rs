//! The rules a write must pass before it is sent, as one pure function:
//! [`decide`] takes what the write means, what comes with it and what the
//! core knows of the drives, and answers send, refuse (and why), or "read
//! this first". The same for every face; [`super::write`] gathers the facts
//! it asks for (a status read costs bus time, so only when a rule needs
//! it, and never for a caller the role already refuses).
//!
//! In order:
//! 0. what the write does is known: a write the core cannot decode (a
//!    function code no register table describes, a mask write keeping bits
//!    of a value nobody read) is refused for every role, unless the face
//!    lets an admin send its function code unchecked (`[modbus_tcp]
//!    raw_functions`), and then never to unit 0, where every device on the
//!    bus would take it;
//! 1. the role: the caller's role includes the one the write needs;
//! 2. the lease: a lease asked for is within `[safety] lease_min_ms` to
//!    `lease_max_ms`;
//! 3. an address broadcast: every drive that hears it takes the address,
//!    so it goes only with the caller's confirmation that one drive is
//!    connected to the bus (HTTP and the stream: `only_drive_on_bus`; a
//!    Modbus TCP client has no way to confirm, so it cannot broadcast one);
//! 4. a setpoint to one drive: the drive is active (as it would answer
//!    itself);
//! 5. a write that needs standstill: every drive it reaches stands still,
//!    unless the face's override (`force`) says to write anyway, which is
//!    audited for each drive that turned.

use std::time::Duration;

use super::caller::Caller;
use super::outcome::{Refusal, Rule};
use super::policy::{Meaning, Role, Undecoded};
use super::request::{ControlRequest, Target};

/// The shortest and longest lease a setpoint may ask for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeaseBounds {
    /// `[safety] lease_min_ms`.
    pub min: Duration,
    /// `[safety] lease_max_ms`.
    pub max: Duration,
}

impl LeaseBounds {
    /// Refuses a lease length outside the bounds, naming them.
    pub fn check(&self, length: Duration) -> Result<(), Refusal> {
        if (self.min..=self.max).contains(&length) {
            return Ok(());
        }
        let (asked, min, max) = (millis(length), millis(self.min), millis(self.max));
        Err(Refusal {
            rule: Rule::LeaseLength { asked, min, max },
            detail: format!("lease = {asked} ms is out of range: valid {min} to {max} ms"),
        })
    }
}

fn millis(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// Whether the drive a setpoint goes to is active, as far as the core
/// knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activity {
    /// Active (by the poll, or by a fresh read).
    Active,
    /// Not active, confirmed by a fresh read.
    Inactive,
    /// Never polled, or not configured: the drive decides.
    Unknown,
}

/// A drive a still-check read, and how fast it turned.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Speed {
    /// The drive in words: `drive "lift"` or `unit 7 on bus line1`.
    pub name: String,
    /// Its speed, rpm.
    pub rpm: i16,
}

/// What the core knows when it decides; the facts that cost a bus read
/// are `None` until [`decide`] asks for them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Facts {
    /// The target in words: `drive "lift"` or `unit 7 on bus line1`.
    pub name: String,
    /// The bus's name, for messages.
    pub bus: String,
    /// Configured drives on the target's bus.
    pub drives_on_bus: usize,
    /// The lease bounds.
    pub lease_bounds: LeaseBounds,
    /// For a setpoint to one drive: whether it is active.
    pub active: Option<Activity>,
    /// For a write that needs standstill: every drive it reaches that
    /// answered a status read.
    pub speeds: Option<Vec<Speed>>,
}

/// A fact [`decide`] needs before it can decide.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Need {
    /// Whether the target drive is active.
    Active,
    /// The speed of every drive the write reaches.
    Speeds,
}

/// What [`decide`] says of a write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decision {
    /// Send it. `forced`: the drives that turned, written to anyway as
    /// the caller's override allowed (each is audited).
    Send {
        /// Drives that turned.
        forced: Vec<Speed>,
    },
    /// Gather this fact and ask again.
    Read(Need),
}

/// Decides on `request` (meaning `meaning`) from `caller` to `target`,
/// with what is known in `facts`. Pure: no I/O, no clock.
pub fn decide(
    caller: &Caller,
    meaning: &Meaning,
    request: &ControlRequest,
    target: Target,
    facts: &Facts,
) -> Result<Decision, Refusal> {
    admit(caller, meaning, request, target)?;
    if meaning.setpoint.is_some()
        && let Some(length) = request.lease
    {
        facts.lease_bounds.check(length)?;
    }
    if meaning.address && target.unit == 0 && !request.single_drive {
        return Err(Refusal {
            rule: Rule::SharedBusAddress,
            detail: format!(
                "address setting is a broadcast: every drive that hears it takes the new address (bus {} has {} configured); disconnect every other drive from this bus and confirm that only one is connected",
                facts.bus, facts.drives_on_bus
            ),
        });
    }
    // A setpoint to a drive that is not active: the drive would refuse it
    // (0x04); refused here, nothing goes on the wire. Only a whole message
    // with valid values: the drive checks the values first (0x03), and its
    // answer is the one to give.
    if meaning.setpoint.is_some() && target.unit != 0 && request.write.is_message() {
        match facts.active {
            None => return Ok(Decision::Read(Need::Active)),
            Some(Activity::Inactive) => {
                return Err(Refusal {
                    rule: Rule::NotActive,
                    detail: format!(
                        "{} is not active: it takes setpoints only when active; send the activate command first",
                        facts.name
                    ),
                });
            }
            Some(Activity::Active | Activity::Unknown) => {}
        }
    }
    let mut forced = Vec::new();
    if let Some(still) = meaning.still {
        let Some(speeds) = &facts.speeds else {
            return Ok(Decision::Read(Need::Speeds));
        };
        for speed in speeds.iter().filter(|s| s.rpm != 0) {
            if !request.force {
                return Err(Refusal {
                    rule: Rule::Moving {
                        still,
                        speed_rpm: speed.rpm,
                    },
                    detail: format!(
                        "{} turns at {} rpm: {} is refused while the motor turns ({}); stop the motor first",
                        speed.name,
                        speed.rpm,
                        still.what(),
                        still.why()
                    ),
                });
            }
            forced.push(speed.clone());
        }
    }
    Ok(Decision::Send { forced })
}

/// The checks that cost nothing: a write the core cannot decode, then the
/// role. Run first, so that a caller they refuse costs no bus time.
pub fn admit(
    caller: &Caller,
    meaning: &Meaning,
    request: &ControlRequest,
    target: Target,
) -> Result<(), Refusal> {
    match meaning.undecoded {
        None => {}
        Some(why @ Undecoded::MaskedValue { .. }) => {
            return Err(Refusal {
                rule: Rule::NotDecoded,
                detail: why.what(),
            });
        }
        Some(why @ Undecoded::Function { .. }) if !request.unchecked => {
            return Err(Refusal {
                rule: Rule::NotDecoded,
                detail: format!(
                    "{}; it is refused for every role unless the listener lets admins send it unchecked (Modbus TCP: [modbus_tcp] raw_functions)",
                    why.what()
                ),
            });
        }
        Some(why @ Undecoded::Function { .. }) if target.unit == 0 => {
            return Err(Refusal {
                rule: Rule::NotDecoded,
                detail: format!(
                    "{}; sent unchecked only to one unit, never as a broadcast (unit 0), which every device on the bus would take",
                    why.what()
                ),
            });
        }
        Some(Undecoded::Function { .. }) => {}
    }
    role(caller, meaning.needs)
}

/// Refuses `caller` unless its role includes `needed`.
pub fn role(caller: &Caller, needed: Role) -> Result<(), Refusal> {
    if caller.role.allows(needed) {
        return Ok(());
    }
    Err(Refusal {
        rule: Rule::Role {
            needed,
            has: caller.role,
        },
        detail: format!(
            "this needs the {} role; {} has the {} role",
            needed.name(),
            caller.who,
            caller.role.name()
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::SourceId;
    use crate::control::Face;
    use crate::control::policy::{StillReason, of_request};
    use crate::control::request::Write;
    use crate::drive::registers::Register;
    use crate::drive::writes::PduMeaning;
    use crate::drive::{ConfigCommand, DriveRequest};

    fn caller(role: Role) -> Caller {
        Caller::new(Face::Http, "t", role, SourceId::new_unique())
    }

    fn unit(unit: u8) -> Target {
        Target {
            bus: 0,
            unit,
            drive: (unit != 0).then_some(0),
        }
    }

    fn facts() -> Facts {
        Facts {
            name: "drive \"lift\"".to_string(),
            bus: "line1".to_string(),
            drives_on_bus: 4,
            lease_bounds: LeaseBounds {
                min: Duration::from_millis(100),
                max: Duration::from_millis(60_000),
            },
            active: None,
            speeds: None,
        }
    }

    fn turning(rpm: i16) -> Option<Vec<Speed>> {
        Some(vec![Speed {
            name: "drive \"lift\"".to_string(),
            rpm,
        }])
    }

    fn ask(
        role: Role,
        request: &ControlRequest,
        target: Target,
        facts: &Facts,
    ) -> Result<Decision, Refusal> {
        decide(
            &caller(role),
            &request.write.meaning(),
            request,
            target,
            facts,
        )
    }

    const SEND: Result<Decision, Refusal> = Ok(Decision::Send { forced: Vec::new() });

    #[test]
    fn the_role_comes_from_the_meaning_of_the_write() {
        let setpoint = ControlRequest::drive(DriveRequest::Speed { rpm: 10 });
        let mut known = facts();
        known.active = Some(Activity::Active);
        let r = ask(Role::Viewer, &setpoint, unit(2), &known).unwrap_err();
        assert_eq!(
            r.rule,
            Rule::Role {
                needed: Role::Operator,
                has: Role::Viewer
            }
        );
        assert!(r.detail.contains("needs the operator role"), "{}", r.detail);
        assert_eq!(ask(Role::Operator, &setpoint, unit(2), &known), SEND);
        let reset = ControlRequest::drive(DriveRequest::Config(ConfigCommand::FactoryReset));
        let r = ask(Role::Operator, &reset, unit(2), &known).unwrap_err();
        assert!(matches!(
            r.rule,
            Rule::Role {
                needed: Role::Admin,
                ..
            }
        ));
        // The role is checked before anything that costs a read.
        let r = ask(Role::Viewer, &setpoint, unit(2), &facts()).unwrap_err();
        assert!(matches!(r.rule, Rule::Role { .. }));
    }

    #[test]
    fn a_lease_must_be_within_the_bounds() {
        let mut known = facts();
        known.active = Some(Activity::Active);
        let with = |ms| {
            ControlRequest::drive(DriveRequest::Speed { rpm: 10 })
                .with_lease(Some(Duration::from_millis(ms)))
        };
        let r = ask(Role::Operator, &with(50), unit(2), &known).unwrap_err();
        assert_eq!(
            r.rule,
            Rule::LeaseLength {
                asked: 50,
                min: 100,
                max: 60_000
            }
        );
        assert!(r.detail.contains("valid 100 to 60000 ms"), "{}", r.detail);
        assert!(ask(Role::Operator, &with(60_001), unit(2), &known).is_err());
        assert_eq!(ask(Role::Operator, &with(100), unit(2), &known), SEND);
        assert_eq!(ask(Role::Operator, &with(60_000), unit(2), &known), SEND);
    }

    #[test]
    fn an_address_broadcast_needs_the_callers_confirmation() {
        let address = ControlRequest::drive(DriveRequest::SetAddress { address: 9 });
        for drives_on_bus in [0, 1, 4] {
            let mut known = facts();
            known.drives_on_bus = drives_on_bus;
            let r = ask(Role::Admin, &address, unit(0), &known).unwrap_err();
            assert_eq!(r.rule, Rule::SharedBusAddress);
            assert!(
                r.detail
                    .contains(&format!("bus line1 has {drives_on_bus} configured")),
                "{}",
                r.detail
            );
            // Confirmed, it goes on to the still-check.
            let confirmed = address.clone().single_drive(true);
            assert_eq!(
                ask(Role::Admin, &confirmed, unit(0), &known),
                Ok(Decision::Read(Need::Speeds))
            );
        }
        // To one unit it is not a broadcast: only the drive there hears it.
        assert_eq!(
            ask(Role::Admin, &address, unit(3), &facts()),
            Ok(Decision::Read(Need::Speeds))
        );
    }

    #[test]
    fn a_setpoint_needs_an_active_drive() {
        let setpoint = ControlRequest::drive(DriveRequest::Position { centideg: 100 });
        let mut known = facts();
        assert_eq!(
            ask(Role::Operator, &setpoint, unit(2), &known),
            Ok(Decision::Read(Need::Active))
        );
        known.active = Some(Activity::Inactive);
        let r = ask(Role::Operator, &setpoint, unit(2), &known).unwrap_err();
        assert_eq!(r.rule, Rule::NotActive);
        assert!(
            r.detail.starts_with("drive \"lift\" is not active"),
            "{}",
            r.detail
        );
        known.active = Some(Activity::Unknown);
        assert_eq!(ask(Role::Operator, &setpoint, unit(2), &known), SEND);
        // A broadcast, or a part of a message, is the drives' to refuse.
        assert_eq!(ask(Role::Operator, &setpoint, unit(0), &facts()), SEND);
        let half = ControlRequest::new(Write::Pdu {
            pdu: Vec::new(),
            sent: None,
            meaning: PduMeaning::Registers(vec![
                (Register::SpeedRef, 16),
                (Register::PositionRef, 0),
            ]),
        });
        assert!(half.write.meaning().setpoint.is_some());
        assert_eq!(ask(Role::Operator, &half, unit(2), &facts()), SEND);
    }

    #[test]
    fn writes_that_need_standstill_wait_for_it_or_the_override() {
        let save = ControlRequest::drive(DriveRequest::LoadInertia {
            ratio: 3,
            save: true,
        });
        let mut known = facts();
        assert_eq!(
            ask(Role::Admin, &save, unit(2), &known),
            Ok(Decision::Read(Need::Speeds))
        );
        known.speeds = turning(120);
        let r = ask(Role::Admin, &save, unit(2), &known).unwrap_err();
        assert_eq!(
            r.rule,
            Rule::Moving {
                still: StillReason::Save,
                speed_rpm: 120
            }
        );
        assert!(
            r.detail
                .contains("drive \"lift\" turns at 120 rpm: a save to flash"),
            "{}",
            r.detail
        );
        let forced = save.clone().forced(true);
        assert_eq!(
            ask(Role::Admin, &forced, unit(2), &known),
            Ok(Decision::Send {
                forced: turning(120).unwrap()
            })
        );
        known.speeds = turning(0);
        assert_eq!(ask(Role::Admin, &save, unit(2), &known), SEND);
        // Without the save flag it is a setting like any other.
        let no_save = ControlRequest::drive(DriveRequest::LoadInertia {
            ratio: 3,
            save: false,
        });
        assert_eq!(ask(Role::Admin, &no_save, unit(2), &facts()), SEND);
    }

    #[test]
    fn what_the_core_cannot_decode_is_refused_for_every_role() {
        let coil = ControlRequest::new(Write::Pdu {
            pdu: vec![0x05, 0x00, 0x01, 0xFF, 0x00],
            meaning: PduMeaning::NotDecoded { function: 0x05 },
            sent: None,
        });
        for role in [Role::Viewer, Role::Operator, Role::Admin] {
            let r = ask(role, &coil, unit(2), &facts()).unwrap_err();
            assert_eq!(r.rule, Rule::NotDecoded, "{role:?}");
            assert!(r.detail.contains("raw_functions"), "{}", r.detail);
        }
        // Let through by the face: an admin's, to one unit only.
        let unchecked = coil.clone().unchecked(true);
        assert_eq!(ask(Role::Admin, &unchecked, unit(2), &facts()), SEND);
        let r = ask(Role::Operator, &unchecked, unit(2), &facts()).unwrap_err();
        assert!(matches!(r.rule, Rule::Role { .. }));
        let r = ask(Role::Admin, &unchecked, unit(0), &facts()).unwrap_err();
        assert_eq!(r.rule, Rule::NotDecoded);
        assert!(r.detail.contains("never as a broadcast"), "{}", r.detail);
        // A mask write keeping bits of a value nobody read: never.
        let masked = ControlRequest::new(Write::Pdu {
            pdu: vec![0x16, 0x00, 0x02, 0xFF, 0xF0, 0x00, 0x06],
            meaning: PduMeaning::Masked {
                register: Register::Config,
                and: 0xFFF0,
                or: 6,
            },
            sent: None,
        })
        .unchecked(true);
        let r = ask(Role::Admin, &masked, unit(2), &facts()).unwrap_err();
        assert_eq!(r.rule, Rule::NotDecoded);
        assert!(r.detail.contains("mask write of CONFIG"), "{}", r.detail);
    }

    #[test]
    fn a_stop_survives_its_caller() {
        for (request, survives) in [
            (DriveRequest::Config(ConfigCommand::EmergencyBrake), true),
            (DriveRequest::Config(ConfigCommand::Deactivate), true),
            (DriveRequest::Speed { rpm: 0 }, false),
            (DriveRequest::Config(ConfigCommand::Activate), false),
        ] {
            assert_eq!(
                of_request(&request).survives_caller(),
                survives,
                "{request:?}"
            );
        }
    }
}
