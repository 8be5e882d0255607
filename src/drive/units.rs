//! Conversions between engineering units and the drive's register values,
//! each refusing values outside the manual's ranges with a [`RangeError`].
//!
//! Ramps (manual 1.9, 1.10) shape a setpoint as a bang-bang profile; from a
//! standing start the time to reach the target is
//! - speed mode, formula (2): `t = 2 * sqrt(r * n_ref / (9.55 * alpha))`,
//! - position mode, formula (3): `t = 2 * sqrt(pi * theta_ref / (180 * alpha))`,
//!
//! with `r` the gear ratio, `n_ref` in rpm and `theta_ref` in degrees at the
//! gearbox output. So alpha is the profile's peak second derivative: in
//! rad/s^3 at the motor shaft for speed, in rad/s^2 for position.

use super::range::RangeError;

/// Current counts per amp: counts = amps / 16 * 2048 (manual 1.6).
pub const COUNTS_PER_AMP: f64 = 2048.0 / 16.0;
/// The constant of formula (2): rpm per rad/s, as the manual rounds it.
pub const RPM_PER_RAD_S: f64 = 9.55;
/// Power-on default of both ramps' alpha.
pub const DEFAULT_RAMP_ALPHA: u32 = 500_000;

/// Speed setpoint range in rpm (manual 1.4).
pub const SPEED_RPM: (i64, i64) = (-2048, 2047);
/// Position setpoint range in 0.01 degree (manual 1.5).
pub const POSITION_CENTIDEG: (i64, i64) = (-18000, 18000);
/// Torque setpoint range in counts (manual 1.6).
pub const TORQUE_COUNTS: (i64, i64) = (-2048, 2047);
/// Over-current limit range in counts (manual 1.8).
pub const LIMIT_COUNTS: (i64, i64) = (0, 2047);
/// Stall time range in ms (manual 1.8).
pub const STALL_MS: (i64, i64) = (0, 60000);
/// Load inertia ratio range (manual 1.11).
pub const INERTIA_RATIO: (i64, i64) = (1, 65535);

/// Current counts to amps.
pub fn counts_to_amps(counts: i16) -> f64 {
    f64::from(counts) / COUNTS_PER_AMP
}

/// 0.01 degree to degrees.
pub fn centideg_to_degrees(centideg: i16) -> f64 {
    f64::from(centideg) / 100.0
}

/// Speed setpoint in rpm (rounded to the drive's 1 rpm) to SPEED_REF.
pub fn speed_setpoint(rpm: f64) -> Result<i16, RangeError> {
    let (min, max) = SPEED_RPM;
    RangeError::check(
        "speed setpoint",
        rpm,
        min as f64 - 0.5,
        max as f64 + 0.5,
        "rpm",
    )
    .map_err(|e| RangeError {
        min: min as f64,
        max: max as f64,
        ..e
    })?;
    let raw = rpm.round() as i64;
    Ok(RangeError::check_int("speed setpoint", raw, min, max, "rpm")? as i16)
}

/// Position setpoint in degrees (rounded to 0.01 degree) to POSITION_REF.
pub fn position_setpoint(degrees: f64) -> Result<i16, RangeError> {
    RangeError::check("position setpoint", degrees, -180.0, 180.0, "deg")?;
    let raw = (degrees * 100.0).round() as i64;
    let (min, max) = POSITION_CENTIDEG;
    Ok(raw.clamp(min, max) as i16)
}

/// Torque setpoint in amps (motor shaft) to IQ_REF counts.
pub fn torque_setpoint(amps: f64) -> Result<i16, RangeError> {
    let (min, max) = TORQUE_COUNTS;
    let raw = checked_counts("torque setpoint", amps, min, max)?;
    Ok(raw as i16)
}

/// Torque setpoint given directly in counts.
pub fn torque_setpoint_counts(counts: i64) -> Result<i16, RangeError> {
    let (min, max) = TORQUE_COUNTS;
    Ok(RangeError::check_int("torque setpoint", counts, min, max, "counts")? as i16)
}

/// Over-current limit in amps to STALLED_CURR counts.
pub fn current_limit(amps: f64) -> Result<u16, RangeError> {
    let (min, max) = LIMIT_COUNTS;
    Ok(checked_counts("over-current limit", amps, min, max)? as u16)
}

/// Over-current limit given directly in counts.
pub fn current_limit_counts(counts: i64) -> Result<u16, RangeError> {
    let (min, max) = LIMIT_COUNTS;
    Ok(RangeError::check_int("over-current limit", counts, min, max, "counts")? as u16)
}

/// Stall time in ms (manual 1.8).
pub fn stall_time_ms(ms: i64) -> Result<u16, RangeError> {
    let (min, max) = STALL_MS;
    Ok(RangeError::check_int("stall time", ms, min, max, "ms")? as u16)
}

/// Load inertia ratio (x rotor inertia, manual 1.11).
pub fn inertia_ratio(ratio: i64) -> Result<u16, RangeError> {
    let (min, max) = INERTIA_RATIO;
    Ok(RangeError::check_int("load inertia ratio", ratio, min, max, "")? as u16)
}

/// Amps to counts within `min..=max` counts, the error naming the range in amps.
fn checked_counts(
    quantity: &'static str,
    amps: f64,
    min: i64,
    max: i64,
) -> Result<i64, RangeError> {
    let (lo, hi) = (min as f64 / COUNTS_PER_AMP, max as f64 / COUNTS_PER_AMP);
    // Accept what rounds into range, refuse the rest naming the range in amps.
    let half = 0.5 / COUNTS_PER_AMP;
    RangeError::check(quantity, amps, lo - half, hi + half, "A").map_err(|e| RangeError {
        min: lo,
        max: hi,
        ..e
    })?;
    Ok(((amps * COUNTS_PER_AMP).round() as i64).clamp(min, max))
}

/// Gear ratios a drive may be configured with.
pub const GEAR_RATIO: (f64, f64) = (0.001, 10_000.0);

/// Formula (2): time in seconds for a speed ramp from standstill to `rpm`
/// with `alpha`; `None` when alpha is 0 (ramp off: the setpoint steps).
pub fn speed_ramp_time(alpha: u32, rpm: f64, gear_ratio: f64) -> Option<f64> {
    (alpha > 0).then(|| 2.0 * (gear_ratio * rpm.abs() / (RPM_PER_RAD_S * f64::from(alpha))).sqrt())
}

/// Formula (3): time in seconds for a position ramp from standstill over
/// `degrees`; `None` when alpha is 0.
pub fn position_ramp_time(alpha: u32, degrees: f64) -> Option<f64> {
    (alpha > 0)
        .then(|| 2.0 * (std::f64::consts::PI * degrees.abs() / (180.0 * f64::from(alpha))).sqrt())
}

/// Formula (2) solved for alpha: the speed ramp that takes `seconds` to reach
/// `rpm` from standstill with `gear_ratio`.
pub fn speed_ramp_alpha(seconds: f64, rpm: f64, gear_ratio: f64) -> Result<u32, RangeError> {
    RangeError::check("gear ratio", gear_ratio, GEAR_RATIO.0, GEAR_RATIO.1, "")?;
    RangeError::check(
        "ramp target speed",
        rpm.abs(),
        1.0,
        SPEED_RPM.1 as f64,
        "rpm",
    )?;
    let k = gear_ratio * rpm.abs() / RPM_PER_RAD_S; // motor rad/s
    solve_alpha("speed ramp time", seconds, k)
}

/// Formula (3) solved for alpha: the position ramp that takes `seconds` to
/// move `degrees` from standstill.
pub fn position_ramp_alpha(seconds: f64, degrees: f64) -> Result<u32, RangeError> {
    RangeError::check("ramp target angle", degrees.abs(), 0.01, 360.0, "deg")?;
    let k = std::f64::consts::PI * degrees.abs() / 180.0; // rad
    solve_alpha("position ramp time", seconds, k)
}

/// Solves `t = 2 sqrt(k / alpha)` for a u32 alpha >= 1, refusing times whose
/// alpha would not fit, with the valid time range in the error.
fn solve_alpha(quantity: &'static str, seconds: f64, k: f64) -> Result<u32, RangeError> {
    let t_min = 2.0 * (k / f64::from(u32::MAX)).sqrt();
    let t_max = 2.0 * k.sqrt();
    RangeError::check(quantity, seconds, t_min, t_max, "s")?;
    let alpha = (4.0 * k / (seconds * seconds)).round();
    Ok(alpha.clamp(1.0, f64::from(u32::MAX)) as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * b.abs()
    }

    #[test]
    fn manual_speed_ramp_examples() {
        // alpha 5000, 133 rpm, r 3.75 -> 0.2047 s; alpha 10 -> 4.5765 s.
        // The manual's figures were computed with 500 rpm at the motor
        // (133.33 rpm at the output); at 133 rpm they agree within 0.2 %.
        let t = speed_ramp_time(5000, 133.0, 3.75).unwrap();
        assert!(close(t, 0.2047, 0.002), "{t}");
        let t = speed_ramp_time(10, 133.0, 3.75).unwrap();
        assert!(close(t, 4.5765, 0.002), "{t}");
        let t = speed_ramp_time(10, 500.0 / 3.75, 3.75).unwrap();
        assert!(close(t, 4.5765, 0.0002), "{t}");
        assert_eq!(speed_ramp_time(0, 133.0, 3.75), None);
    }

    #[test]
    fn manual_position_ramp_examples() {
        let t = position_ramp_time(200, 180.0).unwrap();
        assert!(close(t, 0.2507, 0.0005), "{t}");
        let t = position_ramp_time(10, 180.0).unwrap();
        assert!(close(t, 1.121, 0.0005), "{t}");
    }

    #[test]
    fn ramp_alpha_solves_the_formulas() {
        assert_eq!(position_ramp_alpha(1.121, 180.0).unwrap(), 10);
        assert_eq!(speed_ramp_alpha(0.2047, 500.0 / 3.75, 3.75).unwrap(), 4998);
        let err = speed_ramp_alpha(100.0, 133.0, 3.75).unwrap_err();
        assert_eq!(err.quantity, "speed ramp time");
        assert!(close(err.max, 4.5765 * 10f64.sqrt(), 0.003), "{}", err.max);
        assert!(speed_ramp_alpha(0.0, 133.0, 3.75).is_err());
        assert!(speed_ramp_alpha(1.0, 133.0, 0.0).is_err());
    }

    #[test]
    fn setpoint_ranges() {
        assert_eq!(speed_setpoint(100.0), Ok(100));
        assert_eq!(speed_setpoint(-2048.0), Ok(-2048));
        assert_eq!(speed_setpoint(2047.4), Ok(2047));
        let err = speed_setpoint(2048.0).unwrap_err();
        assert_eq!(
            err.to_string(),
            "speed setpoint 2048 rpm is out of range: valid -2048 to 2047 rpm"
        );
        assert_eq!(position_setpoint(90.0), Ok(9000));
        assert_eq!(position_setpoint(-180.0), Ok(-18000));
        assert!(position_setpoint(180.01).is_err());
        assert_eq!(torque_setpoint(1.0), Ok(128));
        assert_eq!(torque_setpoint(-0.5), Ok(-64));
        assert_eq!(torque_setpoint(-16.0), Ok(-2048));
        let err = torque_setpoint(16.0).unwrap_err();
        assert_eq!(
            err.to_string(),
            "torque setpoint 16 A is out of range: valid -16 to 15.9922 A"
        );
        assert_eq!(current_limit(1.0), Ok(128));
        assert!(current_limit(-0.1).is_err());
        assert_eq!(stall_time_ms(60000), Ok(60000));
        assert!(stall_time_ms(60001).is_err());
        assert!(inertia_ratio(0).is_err());
        assert!(speed_setpoint(f64::NAN).is_err());
    }
}
