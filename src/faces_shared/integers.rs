//! Integer fields of request bodies, read as JSON Schema counts integers:
//! `5` and `5.0` are the same integer (clients that compute in floating
//! point, JavaScript and Python among them, often send the latter), `5.5`
//! is not one. An integer too large for 64 bits is kept at the nearest
//! bound, so the range check after it answers 422 naming the valid range
//! rather than a parse error.

use std::fmt;

use serde::Deserializer;
use serde::de::{self, Visitor};

struct Integer;

impl Visitor<'_> for Integer {
    type Value = i64;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an integer")
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<i64, E> {
        Ok(v)
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<i64, E> {
        Ok(i64::try_from(v).unwrap_or(i64::MAX))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<i64, E> {
        if v.is_finite() && v.fract() == 0.0 {
            // `as` saturates at the bounds of i64.
            Ok(v as i64)
        } else {
            Err(E::invalid_type(de::Unexpected::Float(v), &self))
        }
    }
}

/// An integer field.
pub(crate) fn integer<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    d.deserialize_any(Integer)
}

/// An optional integer field (`null` or left out: `None`); use with
/// `#[serde(default)]`.
pub(crate) fn optional<'de, D: Deserializer<'de>>(d: D) -> Result<Option<i64>, D::Error> {
    struct Optional;

    impl<'de> Visitor<'de> for Optional {
        type Value = Option<i64>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("an integer or null")
        }

        fn visit_none<E: de::Error>(self) -> Result<Option<i64>, E> {
            Ok(None)
        }

        fn visit_unit<E: de::Error>(self) -> Result<Option<i64>, E> {
            Ok(None)
        }

        fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Option<i64>, D::Error> {
            integer(d).map(Some)
        }
    }

    d.deserialize_option(Optional)
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    #[derive(Debug, Deserialize, PartialEq)]
    struct Body {
        #[serde(deserialize_with = "super::integer")]
        n: i64,
        #[serde(default, deserialize_with = "super::optional")]
        m: Option<i64>,
    }

    fn parse(text: &str) -> Result<Body, String> {
        serde_json::from_str(text).map_err(|e| e.to_string())
    }

    #[test]
    fn whole_numbers_in_any_notation_are_integers() {
        assert_eq!(parse(r#"{"n": 5}"#), Ok(Body { n: 5, m: None }));
        assert_eq!(
            parse(r#"{"n": 5.0, "m": -3.0}"#),
            Ok(Body { n: 5, m: Some(-3) })
        );
        assert_eq!(
            parse(r#"{"n": 1e3, "m": null}"#),
            Ok(Body { n: 1000, m: None })
        );
    }

    #[test]
    fn fractions_and_other_types_are_refused() {
        let e = parse(r#"{"n": 5.5}"#).unwrap_err();
        assert!(e.contains("expected an integer"), "{e}");
        let e = parse(r#"{"n": 1, "m": 0.25}"#).unwrap_err();
        assert!(e.contains("expected an integer"), "{e}");
        assert!(parse(r#"{"n": "5"}"#).is_err());
        assert!(parse(r#"{"n": null}"#).is_err());
        assert!(parse(r#"{"m": 1}"#).is_err());
    }

    #[test]
    fn huge_integers_stay_at_the_bounds_for_the_range_check() {
        assert_eq!(parse(r#"{"n": 18446744073709551615}"#).unwrap().n, i64::MAX);
        assert_eq!(parse(r#"{"n": 1e300}"#).unwrap().n, i64::MAX);
        assert_eq!(parse(r#"{"n": -1e300}"#).unwrap().n, i64::MIN);
    }
}
