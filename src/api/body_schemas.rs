//! The OpenAPI schemas of the request bodies whose rules a derive cannot
//! state: one setpoint out of four, one current limit out of two, a ramp
//! given by alpha or by a time and a step. Each is a `oneOf` of complete
//! objects, one per choice: the chosen fields required, the others of the
//! group left out (or `null`, which the body reads as left out).
//!
//! The ranges come from the constants the checks use ([`units`]), with the
//! rounding the checks allow (a speed of 2047.4 rpm rounds into range,
//! 2047.5 does not), so that a value the document accepts is accepted by
//! the daemon and a value it refuses is refused: clients and API testers
//! generating requests from the document meet no surprises. Ranges that
//! depend on the configuration (lease lengths) are set in the served
//! document by [`super::openapi::document_for`]; the reachable ramp times
//! depend on the step and the gear ratio and are checked, with a 422
//! naming them, only by the daemon.

use std::borrow::Cow;

use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{
    AdditionalProperties, ObjectBuilder, OneOfBuilder, Schema, SchemaType, Type,
};
use utoipa::{PartialSchema, ToSchema};

use super::setpoints::SetpointBody;
use super::settings::{PositionRampBody, ProtectionBody, SpeedRampBody};
use crate::drive::units;

/// Half a count of current in amps: what rounds to the nearest count.
const HALF_COUNT_A: f64 = 0.5 / units::COUNTS_PER_AMP;

/// Accepted speed setpoints, rpm, both bounds excluded: the value is
/// rounded to whole rpm, and -2048.5 or 2047.5 round out of range.
pub const SPEED_RPM_EXCLUSIVE: (f64, f64) = (
    units::SPEED_RPM.0 as f64 - 0.5,
    units::SPEED_RPM.1 as f64 + 0.5,
);

/// Accepted torque setpoints, amps, both bounds included (rounded to the
/// nearest count).
pub const TORQUE_A: (f64, f64) = (
    units::TORQUE_COUNTS.0 as f64 / units::COUNTS_PER_AMP - HALF_COUNT_A,
    units::TORQUE_COUNTS.1 as f64 / units::COUNTS_PER_AMP + HALF_COUNT_A,
);

/// Accepted current limits, amps, both bounds included.
pub const LIMIT_A: (f64, f64) = (
    units::LIMIT_COUNTS.0 as f64 / units::COUNTS_PER_AMP - HALF_COUNT_A,
    units::LIMIT_COUNTS.1 as f64 / units::COUNTS_PER_AMP + HALF_COUNT_A,
);

/// Accepted position setpoints, degrees.
pub const POSITION_DEG: (f64, f64) = (
    units::POSITION_CENTIDEG.0 as f64 / 100.0,
    units::POSITION_CENTIDEG.1 as f64 / 100.0,
);

fn typed(ty: Type, nullable: bool, description: &str) -> ObjectBuilder {
    let schema_type: SchemaType = if nullable {
        [ty, Type::Null].into_iter().collect()
    } else {
        ty.into()
    };
    ObjectBuilder::new()
        .schema_type(schema_type)
        .description(Some(description))
}

fn number(nullable: bool, description: &str, (min, max): (f64, f64)) -> ObjectBuilder {
    typed(Type::Number, nullable, description)
        .minimum(Some(min))
        .maximum(Some(max))
}

fn integer(nullable: bool, description: &str, (min, max): (i64, i64)) -> ObjectBuilder {
    typed(Type::Integer, nullable, description)
        .minimum(Some(min as f64))
        .maximum(Some(max as f64))
}

fn absent(description: &str) -> ObjectBuilder {
    typed(Type::Null, false, description)
}

fn flag(description: &str) -> ObjectBuilder {
    typed(Type::Boolean, false, description)
}

/// One choice: a closed object with these properties, `required` among them.
fn choice(title: &str, properties: Vec<(&str, ObjectBuilder)>, required: &[&str]) -> ObjectBuilder {
    let mut object = ObjectBuilder::new()
        .title(Some(title))
        .additional_properties(Some(AdditionalProperties::<Schema>::FreeForm(false)));
    for (name, schema) in properties {
        object = object.property(name, schema);
    }
    for name in required {
        object = object.required(*name);
    }
    object
}

fn one_of(description: &str, choices: Vec<ObjectBuilder>) -> RefOr<Schema> {
    let mut one_of = OneOfBuilder::new().description(Some(description));
    for c in choices {
        one_of = one_of.item(c);
    }
    RefOr::T(Schema::OneOf(one_of.build()))
}

/// A lease length; its bounds are the configuration's, set in the served
/// document by [`super::openapi::document_for`].
fn lease(description: &str) -> ObjectBuilder {
    typed(Type::Integer, true, description)
}

const SPEED: &str = "Speed at the gearbox output, rpm (-2048..2047, rounded to 1 rpm).";
const POSITION: &str = "Position at the gearbox output, degrees (-180..180, rounded to 0.01).";
const TORQUE_AMPS: &str = "Motor current, amps (-16..15.99, rounded to 1/128 A).";
const TORQUE_COUNTS: &str = "Motor current, raw counts (-2048..2047; 1 A = 128).";
const LEASE: &str = "Stop the motor (`[safety] on_lease_expiry`) unless the setpoint is repeated or the lease renewed within this many ms (`[safety] lease_min_ms` to `lease_max_ms`).";
const OTHER_SETPOINT: &str = "Only one setpoint per request.";

impl PartialSchema for SetpointBody {
    fn schema() -> RefOr<Schema> {
        let setpoint = |title: &str, given: &str| {
            let field = |name: &str| -> ObjectBuilder {
                match (name == given, name) {
                    (true, "speed_rpm") => typed(Type::Number, false, SPEED)
                        .exclusive_minimum(Some(SPEED_RPM_EXCLUSIVE.0))
                        .exclusive_maximum(Some(SPEED_RPM_EXCLUSIVE.1)),
                    (true, "position_deg") => number(false, POSITION, POSITION_DEG),
                    (true, "torque_a") => number(false, TORQUE_AMPS, TORQUE_A),
                    (true, _) => integer(false, TORQUE_COUNTS, units::TORQUE_COUNTS),
                    (false, _) => absent(OTHER_SETPOINT),
                }
            };
            let names = ["speed_rpm", "position_deg", "torque_a", "torque_counts"];
            let mut properties: Vec<(&str, ObjectBuilder)> =
                names.iter().map(|n| (*n, field(n))).collect();
            properties.push(("lease_ms", lease(LEASE)));
            choice(title, properties, &[given])
        };
        one_of(
            "`PUT .../setpoint` body: exactly one setpoint (`speed_rpm`, `position_deg`, `torque_a` or `torque_counts`), and optionally a lease.",
            vec![
                setpoint("speed", "speed_rpm"),
                setpoint("position", "position_deg"),
                setpoint("torque in amps", "torque_a"),
                setpoint("torque in counts", "torque_counts"),
            ],
        )
    }
}

impl ToSchema for SetpointBody {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("SetpointBody")
    }
}

const STALL: &str = "How long the current may stay over the limit before the drive stalls the motor, ms (0..60000).";
const SAVE: &str = "Also write to flash (motor must stand still).";
const FORCE: &str = "Save even while the motor turns.";

impl PartialSchema for ProtectionBody {
    fn schema() -> RefOr<Schema> {
        let limit = |title: &str, amps: bool| {
            let (a, counts) = if amps {
                (
                    number(false, "Current limit, amps (0..15.99).", LIMIT_A),
                    absent("Give `limit_a` or `limit_counts`, not both."),
                )
            } else {
                (
                    absent("Give `limit_a` or `limit_counts`, not both."),
                    integer(
                        false,
                        "Current limit, raw counts (0..2047; 1 A = 128).",
                        units::LIMIT_COUNTS,
                    ),
                )
            };
            choice(
                title,
                vec![
                    ("limit_a", a),
                    ("limit_counts", counts),
                    ("stall_ms", integer(false, STALL, units::STALL_MS)),
                    ("save", flag(SAVE)),
                    ("force", flag(FORCE)),
                ],
                &[if amps { "limit_a" } else { "limit_counts" }, "stall_ms"],
            )
        };
        one_of(
            "`PUT .../protection` body: the current limit (`limit_a` or `limit_counts`) and the stall time.",
            vec![
                limit("limit in amps", true),
                limit("limit in counts", false),
            ],
        )
    }
}

impl ToSchema for ProtectionBody {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("ProtectionBody")
    }
}

const ALPHA: &str = "Ramp alpha (0 = ramp off; larger = faster; power-on default 500000).";
const ALPHA_RANGE: (i64, i64) = (0, u32::MAX as i64);

/// The two choices of a ramp body: by alpha, or by a time for a step.
fn ramp(
    description: &str,
    step: &'static str,
    step_schema: fn(bool) -> ObjectBuilder,
    time: &str,
) -> RefOr<Schema> {
    let by_alpha = choice(
        "by alpha",
        vec![
            ("alpha", integer(false, ALPHA, ALPHA_RANGE)),
            ("time_s", absent("Give `alpha` or `time_s`, not both.")),
            (step, step_schema(true)),
            ("save", flag(SAVE)),
            ("force", flag(FORCE)),
        ],
        &["alpha"],
    );
    let by_time = choice(
        "by time",
        vec![
            ("alpha", absent("Give `alpha` or `time_s`, not both.")),
            (
                "time_s",
                typed(Type::Number, false, time).exclusive_minimum(Some(0.0)),
            ),
            (step, step_schema(false)),
            ("save", flag(SAVE)),
            ("force", flag(FORCE)),
        ],
        &["time_s", step],
    );
    one_of(description, vec![by_alpha, by_time])
}

impl PartialSchema for SpeedRampBody {
    fn schema() -> RefOr<Schema> {
        ramp(
            "`PUT .../ramps/speed` body: `alpha`, or `time_s` with `step_rpm`. The times a ramp can take depend on the step and the drive's gear ratio; one out of reach is refused with 422 naming them.",
            "step_rpm",
            |nullable| {
                let max = units::SPEED_RPM.1 as f64;
                number(
                    nullable,
                    "The speed step `time_s` is for, rpm at the gearbox output (1..2047 either way).",
                    (-max, max),
                )
            },
            "Time to reach `step_rpm` from standstill, seconds: alpha is solved with the manual's formula (2) and the drive's gear ratio.",
        )
    }
}

impl ToSchema for SpeedRampBody {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("SpeedRampBody")
    }
}

impl PartialSchema for PositionRampBody {
    fn schema() -> RefOr<Schema> {
        ramp(
            "`PUT .../ramps/position` body: `alpha`, or `time_s` with `step_deg`. The times a ramp can take depend on the step; one out of reach is refused with 422 naming them.",
            "step_deg",
            |nullable| {
                number(
                    nullable,
                    "The move `time_s` is for, degrees at the gearbox output (0.01..360 either way).",
                    (-360.0, 360.0),
                )
            },
            "Time to move `step_deg` from standstill, seconds: alpha is solved with the manual's formula (3).",
        )
    }
}

impl ToSchema for PositionRampBody {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("PositionRampBody")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::RangeError;

    /// The bounds in the document are where the checks change their answer.
    #[test]
    fn bounds_agree_with_the_checks() {
        let nudge = 1e-9;
        let (lo, hi) = SPEED_RPM_EXCLUSIVE;
        assert!(units::speed_setpoint(lo).is_err() && units::speed_setpoint(hi).is_err());
        assert!(units::speed_setpoint(lo + nudge).is_ok());
        assert!(units::speed_setpoint(hi - nudge).is_ok());
        for (bounds, check) in [
            (
                TORQUE_A,
                units::torque_setpoint as fn(f64) -> Result<i16, RangeError>,
            ),
            (POSITION_DEG, units::position_setpoint),
        ] {
            let (lo, hi) = bounds;
            assert!(check(lo).is_ok() && check(hi).is_ok(), "{bounds:?}");
            assert!(
                check(lo - nudge).is_err() && check(hi + nudge).is_err(),
                "{bounds:?}"
            );
        }
        let (lo, hi) = LIMIT_A;
        assert!(units::current_limit(lo).is_ok() && units::current_limit(hi).is_ok());
        assert!(units::current_limit(lo - nudge).is_err());
        assert!(units::current_limit(hi + nudge).is_err());
    }

    fn json<T: PartialSchema>() -> serde_json::Value {
        serde_json::to_value(T::schema()).unwrap()
    }

    #[test]
    fn each_choice_requires_its_field_and_shuts_out_the_others() {
        let setpoint = json::<SetpointBody>();
        let choices = setpoint["oneOf"].as_array().unwrap();
        assert_eq!(choices.len(), 4);
        for (choice, field) in
            choices
                .iter()
                .zip(["speed_rpm", "position_deg", "torque_a", "torque_counts"])
        {
            assert_eq!(choice["required"], serde_json::json!([field]));
            assert_eq!(choice["additionalProperties"], false);
            for other in ["speed_rpm", "position_deg", "torque_a", "torque_counts"] {
                let ty = &choice["properties"][other]["type"];
                assert_eq!(other == field, ty != "null", "{field}: {other} is {ty}");
            }
        }
        let ramp = json::<SpeedRampBody>();
        assert_eq!(
            ramp["oneOf"][1]["required"],
            serde_json::json!(["time_s", "step_rpm"])
        );
        assert_eq!(
            ramp["oneOf"][0]["properties"]["alpha"]["maximum"],
            4294967295.0
        );
        let protection = json::<ProtectionBody>();
        assert_eq!(
            protection["oneOf"][1]["required"],
            serde_json::json!(["limit_counts", "stall_ms"])
        );
    }
}
