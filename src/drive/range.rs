//! The error for a value outside what the drive accepts, naming the valid range.

use std::fmt;

/// A value outside the range the manual allows. The message names the range
/// and the unit, so an operator can correct the request without the manual.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeError {
    /// What was being set, e.g. "speed setpoint".
    pub quantity: &'static str,
    /// The value that was refused, in `unit`.
    pub value: f64,
    /// Lowest accepted value, in `unit`.
    pub min: f64,
    /// Highest accepted value, in `unit`.
    pub max: f64,
    /// Engineering unit of the three numbers ("rpm", "deg", "A", ...), may be empty.
    pub unit: &'static str,
}

impl RangeError {
    /// Checks `value` against `min..=max`; NaN and infinities are always refused.
    pub fn check(
        quantity: &'static str,
        value: f64,
        min: f64,
        max: f64,
        unit: &'static str,
    ) -> Result<f64, RangeError> {
        if value.is_finite() && value >= min && value <= max {
            Ok(value)
        } else {
            Err(RangeError {
                quantity,
                value,
                min,
                max,
                unit,
            })
        }
    }

    /// Checks an integer value against `min..=max`.
    pub fn check_int(
        quantity: &'static str,
        value: i64,
        min: i64,
        max: i64,
        unit: &'static str,
    ) -> Result<i64, RangeError> {
        if (min..=max).contains(&value) {
            Ok(value)
        } else {
            Err(RangeError {
                quantity,
                value: value as f64,
                min: min as f64,
                max: max as f64,
                unit,
            })
        }
    }
}

impl RangeError {
    /// What was asked for, in words ("speed setpoint 3000 rpm"): the
    /// audit's account of a refused write.
    pub fn attempted(&self) -> String {
        let sep = if self.unit.is_empty() { "" } else { " " };
        format!("{} {}{sep}{}", self.quantity, Num(self.value), self.unit)
    }
}

impl fmt::Display for RangeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let sep = if self.unit.is_empty() { "" } else { " " };
        write!(
            f,
            "{} {}{sep}{} is out of range: valid {} to {}{sep}{}",
            self.quantity,
            Num(self.value),
            self.unit,
            Num(self.min),
            Num(self.max),
            self.unit
        )
    }
}

impl std::error::Error for RangeError {}

/// Prints a number without trailing noise: integers as integers, others to 4 places.
struct Num(f64);

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = self.0;
        if v.is_finite() && v.fract() == 0.0 && v.abs() < 1e15 {
            write!(f, "{}", v as i64)
        } else if v.is_finite() {
            let s = format!("{v:.4}");
            let s = s.trim_end_matches('0').trim_end_matches('.');
            f.write_str(s)
        } else {
            write!(f, "{v}")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn message_names_the_range_and_unit() {
        let err = RangeError::check_int("speed setpoint", 3000, -2048, 2047, "rpm").unwrap_err();
        assert_eq!(
            err.to_string(),
            "speed setpoint 3000 rpm is out of range: valid -2048 to 2047 rpm"
        );
        let err = RangeError::check("torque", 20.0, -16.0, 15.9921875, "A").unwrap_err();
        assert_eq!(
            err.to_string(),
            "torque 20 A is out of range: valid -16 to 15.9922 A"
        );
        let err = RangeError::check_int("save flag", 2, 0, 1, "").unwrap_err();
        assert_eq!(err.to_string(), "save flag 2 is out of range: valid 0 to 1");
        assert_eq!(err.attempted(), "save flag 2");
        let err = RangeError::check("torque", 20.5, -16.0, 15.9921875, "A").unwrap_err();
        assert_eq!(err.attempted(), "torque 20.5 A");
    }

    #[test]
    fn nan_is_refused() {
        assert!(RangeError::check("x", f64::NAN, 0.0, 1.0, "").is_err());
        assert!(RangeError::check("x", f64::INFINITY, 0.0, 1.0, "").is_err());
        assert_eq!(RangeError::check("x", 0.5, 0.0, 1.0, ""), Ok(0.5));
    }
}
