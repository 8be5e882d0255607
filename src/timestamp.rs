//! Wall-clock times as the daemon shows them: RFC 3339, UTC, milliseconds
//! (`2026-11-22T03:39:12.345Z`), or microseconds for the wire's times. A
//! leaf: the observers and the faces format times alike without one
//! importing the other.

use std::time::{SystemTime, UNIX_EPOCH};

/// Formats `t` as RFC 3339 in UTC with milliseconds; times before 1970 are
/// shown as the epoch (a drive cannot have been seen then).
pub(crate) fn rfc3339(t: SystemTime) -> String {
    let since = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    let (date, millis) = (date_time(since.as_secs()), since.subsec_millis());
    format!("{date}.{millis:03}Z")
}

/// Formats `t` as RFC 3339 in UTC with microseconds
/// (`2026-11-22T03:39:12.345678Z`): the bus monitor's and the scope's
/// times, where a frame lasts a fraction of a millisecond.
pub(crate) fn rfc3339_micros(t: SystemTime) -> String {
    let since = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    let (date, micros) = (date_time(since.as_secs()), since.subsec_micros());
    format!("{date}.{micros:06}Z")
}

/// `YYYY-MM-DDTHH:MM:SS` of `secs` since the epoch.
fn date_time(secs: u64) -> String {
    let days = i64::try_from(secs / 86_400).unwrap_or(0);
    let rem = secs % 86_400;
    let (y, m, d) = civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}",
        rem / 3600,
        (rem / 60) % 60,
        rem % 60
    )
}

/// Reads an RFC 3339 time (`2026-11-22T03:39:12.345Z`, or with an offset
/// `+01:00`; `t` or a space for `T`), or a number of milliseconds since
/// the Unix epoch. `None`: neither.
pub(crate) fn parse_time(text: &str) -> Option<SystemTime> {
    use std::time::Duration;
    let text = text.trim();
    if !text.is_empty() && text.bytes().all(|b| b.is_ascii_digit()) {
        return UNIX_EPOCH.checked_add(Duration::from_millis(text.parse().ok()?));
    }
    let b = text.as_bytes();
    let num = |from: usize, len: usize| -> Option<i64> {
        let part = text.get(from..from + len)?;
        part.bytes()
            .all(|c| c.is_ascii_digit())
            .then(|| part.parse().ok())?
    };
    if b.len() < 20 || b[4] != b'-' || b[7] != b'-' || !matches!(b[10], b'T' | b't' | b' ') {
        return None;
    }
    if b[13] != b':' || b[16] != b':' {
        return None;
    }
    let (y, mo, d) = (num(0, 4)?, num(5, 2)?, num(8, 2)?);
    let (h, mi, sec) = (num(11, 2)?, num(14, 2)?, num(17, 2)?);
    if !(1..=12).contains(&mo) || !(1..=31).contains(&d) || h > 23 || mi > 59 || sec > 60 {
        return None;
    }
    let mut at = 19;
    let mut nanos = 0i64;
    if b.get(at) == Some(&b'.') {
        let digits = b
            .get(at + 1..)?
            .iter()
            .take_while(|c| c.is_ascii_digit())
            .count();
        if digits == 0 {
            return None;
        }
        let frac = text.get(at + 1..at + 1 + digits.min(9))?;
        nanos = frac.parse::<i64>().ok()? * 10i64.pow(9 - frac.len() as u32);
        at += 1 + digits;
    }
    let offset_s = match text.get(at..)? {
        "Z" | "z" => 0,
        rest if rest.len() == 6
            && matches!(rest.as_bytes()[0], b'+' | b'-')
            && rest.as_bytes()[3] == b':' =>
        {
            let (oh, om) = (num(at + 1, 2)?, num(at + 4, 2)?);
            let sign = if rest.starts_with('-') { -1 } else { 1 };
            sign * (oh * 3600 + om * 60)
        }
        _ => return None,
    };
    let secs =
        days_from_civil(y, mo as u32, d as u32) * 86_400 + h * 3600 + mi * 60 + sec - offset_s;
    let total = Duration::from_nanos(u64::try_from(nanos).ok()?);
    UNIX_EPOCH
        .checked_add(Duration::from_secs(u64::try_from(secs).ok()?))?
        .checked_add(total)
}

/// (year, month, day) to days since 1970-01-01 (H. Hinnant's algorithm).
fn days_from_civil(y: i64, m: u32, d: u32) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y.rem_euclid(400);
    let mp = i64::from((m + 9) % 12);
    let doy = (153 * mp + 2) / 5 + i64::from(d) - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// Days since 1970-01-01 to (year, month, day) in the proleptic Gregorian
/// calendar (H. Hinnant's algorithm).
fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn formats_known_instants() {
        assert_eq!(rfc3339(UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
        let t = UNIX_EPOCH + Duration::from_millis(951_782_400_123); // leap day 2000
        assert_eq!(rfc3339(t), "2000-02-29T00:00:00.123Z");
        let t = UNIX_EPOCH + Duration::from_micros(951_782_400_123_456);
        assert_eq!(rfc3339_micros(t), "2000-02-29T00:00:00.123456Z");
        let t = UNIX_EPOCH + Duration::from_secs(1_795_318_752);
        assert_eq!(rfc3339(t), "2026-11-22T03:39:12.000Z");
        let t = UNIX_EPOCH + Duration::from_secs(4_107_542_399);
        assert_eq!(rfc3339(t), "2100-02-28T23:59:59.000Z");
    }

    #[test]
    fn reads_back_what_it_writes_and_offsets_and_milliseconds() {
        for ms in [0u64, 951_782_400_123, 1_795_318_752_000, 4_107_542_399_999] {
            let t = UNIX_EPOCH + Duration::from_millis(ms);
            assert_eq!(parse_time(&rfc3339(t)), Some(t), "{ms}");
            assert_eq!(parse_time(&ms.to_string()), Some(t));
        }
        assert_eq!(
            parse_time("2026-11-22T04:39:12+01:00"),
            parse_time("2026-11-22T03:39:12Z")
        );
        assert_eq!(
            parse_time("2026-11-22 03:39:12.5z"),
            Some(UNIX_EPOCH + Duration::from_millis(1_795_318_752_500))
        );
        for bad in [
            "",
            "yesterday",
            "2026-11-22",
            "2026-13-01T00:00:00Z",
            "2026-11-22T03:39:12",
            "-5",
            "2026-11-22T03:39:12.Z",
        ] {
            assert_eq!(parse_time(bad), None, "{bad}");
        }
    }
}
