//! Deserializers that refuse out-of-range values while parsing, so the error
//! carries the value's line and column.

use serde::{Deserialize, Deserializer, de::Error};

/// An integer in `MIN..=MAX`.
pub(crate) fn int_in<'de, D, T, const MIN: i64, const MAX: i64>(d: D) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
    T: TryFrom<i64>,
{
    let v = i64::deserialize(d)?;
    if !(MIN..=MAX).contains(&v) {
        return Err(D::Error::custom(format!(
            "{v} is out of range: valid {MIN} to {MAX}"
        )));
    }
    T::try_from(v)
        .map_err(|_| D::Error::custom(format!("{v} is out of range: valid {MIN} to {MAX}")))
}

/// An optional integer in `MIN..=MAX`.
pub(super) fn opt_int_in<'de, D, T, const MIN: i64, const MAX: i64>(
    d: D,
) -> Result<Option<T>, D::Error>
where
    D: Deserializer<'de>,
    T: TryFrom<i64>,
{
    int_in::<D, T, MIN, MAX>(d).map(Some)
}

/// A gear ratio: finite, above zero, at most 10000.
pub(super) fn gear_ratio<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    let v = f64::deserialize(d)?;
    let (min, max) = crate::drive::units::GEAR_RATIO;
    if !(v.is_finite() && (min..=max).contains(&v)) {
        return Err(D::Error::custom(format!(
            "gear ratio {v} is out of range: valid {min} to {max}"
        )));
    }
    Ok(v)
}

/// A bus or drive name: letters, digits, `-`, `_`, `.`, not only digits
/// (a number in an API path means a unit address).
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(try_from = "String")]
pub struct Name(String);

impl Name {
    /// The name.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for Name {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl TryFrom<String> for Name {
    type Error = String;

    fn try_from(v: String) -> Result<Self, String> {
        let ok_chars = v
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
        if v.is_empty() || v.len() > 64 || !ok_chars {
            return Err(format!(
                "name \"{v}\" must be 1 to 64 letters, digits, '-', '_' or '.'"
            ));
        }
        if v.chars().all(|c| c.is_ascii_digit()) {
            return Err(format!(
                "name \"{v}\" must not be only digits (a number in the API means a unit address)"
            ));
        }
        Ok(Name(v))
    }
}

/// A drive's unit address, 1 to 255 (the manual's address range).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(try_from = "i64")]
pub struct UnitAddress(pub u8);

impl TryFrom<i64> for UnitAddress {
    type Error = String;

    fn try_from(v: i64) -> Result<Self, String> {
        match u8::try_from(v) {
            Ok(u) if u >= 1 => Ok(UnitAddress(u)),
            _ => Err(format!(
                "unit {v} is out of range: valid 1 to 255 (0 is the broadcast address)"
            )),
        }
    }
}
