//! Which frames a monitor client wants: by unit, function, outcome and
//! source. Parsed from the short lists a query string carries
//! (`unit=1,3-4&function=0x06,16&outcome=timeout,crc_error&source=modbus-tcp`),
//! refusing anything else with a message that lists what is accepted.

use super::record::{FrameOutcome, FrameRecord};
use crate::bus::origin::KINDS;

/// A frame filter; an empty list lets everything through.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FrameFilter {
    /// Units (of the transaction).
    pub units: Vec<u8>,
    /// Function codes (without the exception bit).
    pub functions: Vec<u8>,
    /// Outcomes, as [`FrameOutcome::name`].
    pub outcomes: Vec<FrameOutcome>,
    /// Only frames of a retry (attempt 2 and later).
    pub retries_only: bool,
    /// Source kinds, as [`crate::bus::Origin::kind`].
    pub sources: Vec<&'static str>,
    /// The client behind the source: a token name, a client or Modbus TCP
    /// peer address, a lease's owner.
    pub who: Option<String>,
}

/// Filter texts, as a query string carries them.
#[derive(Debug, Clone, Default)]
pub struct FilterText<'a> {
    /// `unit`: `1,3-4`.
    pub units: Option<&'a str>,
    /// `function`: `3,0x06,16`.
    pub functions: Option<&'a str>,
    /// `outcome`: `timeout,crc_error,retry`.
    pub outcomes: Option<&'a str>,
    /// `source`: `modbus-tcp,http`.
    pub sources: Option<&'a str>,
    /// `who`: `scada`.
    pub who: Option<&'a str>,
}

fn items(list: Option<&str>) -> impl Iterator<Item = &str> {
    list.unwrap_or("")
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
}

fn number(s: &str) -> Option<u64> {
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(hex) => u64::from_str_radix(hex, 16).ok(),
        None => s.parse().ok(),
    }
}

impl FrameFilter {
    /// Parses the filter texts; the error says what is accepted.
    pub fn parse(text: &FilterText<'_>) -> Result<Self, String> {
        let mut filter = FrameFilter::default();
        for item in items(text.units) {
            let (first, last) = item.split_once('-').unwrap_or((item, item));
            let range = number(first.trim())
                .zip(number(last.trim()))
                .filter(|&(a, b)| a <= b && b <= 255);
            let Some((a, b)) = range else {
                return Err(format!(
                    "unit filter \"{item}\" is not a unit 0..255 or a range like 3-7"
                ));
            };
            filter.units.extend((a..=b).map(|u| u as u8));
        }
        for item in items(text.functions) {
            match number(item).filter(|&f| (1..=0x7F).contains(&f)) {
                Some(f) => filter.functions.push(f as u8),
                None => {
                    return Err(format!(
                        "function filter \"{item}\" is not a function code 1..127 (decimal or 0x..)"
                    ));
                }
            }
        }
        for item in items(text.outcomes) {
            if item == "retry" {
                filter.retries_only = true;
                continue;
            }
            match FrameOutcome::from_name(item) {
                Some(o) => filter.outcomes.push(o),
                None => {
                    let names: Vec<&str> = FrameOutcome::ALL.iter().map(|o| o.name()).collect();
                    return Err(format!(
                        "outcome filter \"{item}\" is not one of {}, retry",
                        names.join(", ")
                    ));
                }
            }
        }
        for item in items(text.sources) {
            match KINDS.iter().find(|k| **k == item) {
                Some(k) => filter.sources.push(k),
                None => {
                    return Err(format!(
                        "source filter \"{item}\" is not one of {}",
                        KINDS.join(", ")
                    ));
                }
            }
        }
        filter.who = text
            .who
            .map(str::trim)
            .filter(|w| !w.is_empty())
            .map(str::to_string);
        Ok(filter)
    }

    /// True when `record` passes.
    pub fn accepts(&self, record: &FrameRecord) -> bool {
        (self.units.is_empty() || self.units.contains(&record.unit))
            && (self.functions.is_empty()
                || record
                    .function()
                    .is_some_and(|f| self.functions.contains(&f)))
            && (self.outcomes.is_empty() || self.outcomes.contains(&record.outcome))
            && (!self.retries_only || record.attempt > 1)
            && (self.sources.is_empty() || self.sources.contains(&record.origin.kind()))
            && self
                .who
                .as_ref()
                .is_none_or(|w| record.origin.who().is_some_and(|o| o == *w))
    }

    /// True when it lets everything through.
    pub fn is_empty(&self) -> bool {
        *self == FrameFilter::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::Origin;
    use crate::monitor::record::Direction;

    fn record(unit: u8, function: u8, outcome: FrameOutcome, origin: Origin) -> FrameRecord {
        let mut r = FrameRecord {
            unit,
            outcome,
            origin,
            attempt: 1,
            ..FrameRecord::default()
        };
        r.set_bytes(&[unit, function, 0, 0]);
        r
    }

    #[test]
    fn parses_and_filters() {
        let f = FrameFilter::parse(&FilterText {
            units: Some("1, 3-4"),
            functions: Some("0x06,16"),
            outcomes: None,
            sources: Some("modbus-tcp"),
            who: None,
        })
        .unwrap();
        assert_eq!(f.units, [1, 3, 4]);
        assert_eq!(f.functions, [6, 16]);
        let tcp = Origin::modbus_tcp("127.0.0.1:5000".parse().unwrap(), 1);
        assert!(f.accepts(&record(3, 6, FrameOutcome::Sent, tcp.clone())));
        assert!(!f.accepts(&record(2, 6, FrameOutcome::Sent, tcp.clone())));
        assert!(!f.accepts(&record(3, 3, FrameOutcome::Sent, tcp.clone())));
        assert!(!f.accepts(&record(3, 6, FrameOutcome::Sent, Origin::Poller)));
        let who = FrameFilter::parse(&FilterText {
            who: Some("127.0.0.1:5000"),
            ..Default::default()
        })
        .unwrap();
        assert!(who.accepts(&record(3, 6, FrameOutcome::Sent, tcp)));
        assert!(!who.accepts(&record(3, 6, FrameOutcome::Sent, Origin::Poller)));
    }

    #[test]
    fn outcomes_and_retries() {
        let f = FrameFilter::parse(&FilterText {
            outcomes: Some("timeout,retry"),
            ..Default::default()
        })
        .unwrap();
        let mut r = record(1, 3, FrameOutcome::Timeout, Origin::Poller);
        r.direction = Direction::Reply;
        assert!(!f.accepts(&r), "a first attempt is not a retry");
        r.attempt = 2;
        assert!(f.accepts(&r));
        assert!(
            FrameFilter::parse(&FilterText::default())
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn refuses_with_what_is_accepted() {
        let e = FrameFilter::parse(&FilterText {
            outcomes: Some("lost"),
            ..Default::default()
        })
        .unwrap_err();
        assert!(e.contains("crc_error") && e.contains("retry"), "{e}");
        let e = FrameFilter::parse(&FilterText {
            units: Some("9-3"),
            ..Default::default()
        })
        .unwrap_err();
        assert!(e.contains("0..255"), "{e}");
        let e = FrameFilter::parse(&FilterText {
            sources: Some("plc"),
            ..Default::default()
        })
        .unwrap_err();
        assert!(e.contains("modbus-tcp"), "{e}");
        assert!(
            FrameFilter::parse(&FilterText {
                functions: Some("0x80"),
                ..Default::default()
            })
            .is_err()
        );
    }
}
