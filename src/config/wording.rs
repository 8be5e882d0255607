//! The TOML parser's messages for the common mistakes of a hand-written
//! file, in plain words with the right form: `[bus]` for `[[bus]]` (and the
//! reverse), an address without its IP (`listen = "8080"`), numbers and
//! `true`/`false` in quotes, text without them, one value where a list is
//! wanted. Pure: the text, where the parser stopped and what it said.
//!
//! The parser's words ("invalid type: map, expected a sequence") are right
//! but speak of serde's types; a plant engineer reads "write `[[bus]]`".
//! What is not recognised here keeps the parser's message.

/// Tables that are lists, written `[[name]]` once per entry, each with
/// what one entry is; every other table is a single section (`[name]`).
pub(super) const LISTS: [(&str, &str); 7] = [
    ("bus", "bus (serial adapter)"),
    ("bus.drive", "drive of the bus"),
    ("http.token", "token"),
    ("modbus_tcp.clients", "client network"),
    ("modbus_tcp.unit_map", "range of units"),
    ("modbus_tcp.polled_copy", "bus"),
    ("opcua.user_certificate", "user certificate's role"),
];

/// `raw`, the parser's message for the error at byte `offset` of `text`,
/// in plain words where it is one of the common mistakes; else `raw`.
pub(super) fn plain(text: &str, offset: usize, raw: &str) -> String {
    let at = At::new(text, offset);
    header(&at, raw)
        .or_else(|| address(&at, raw))
        .or_else(|| quoted(&at, raw))
        .or_else(|| unquoted(&at, raw))
        .unwrap_or_else(|| raw.to_string())
}

/// What surrounds the error: the table header above it, the key of its
/// line, and the value written there.
struct At<'a> {
    /// The last header at or above the error: its name, and whether it
    /// has two brackets.
    header: Option<(&'a str, bool)>,
    /// The key of the error's line, when the error is in its value.
    key: Option<&'a str>,
    /// The value as written, from the error to the end of its line,
    /// without a trailing comment.
    value: &'a str,
}

impl<'a> At<'a> {
    fn new(text: &'a str, offset: usize) -> Self {
        let offset = text.floor_char_boundary(offset.min(text.len()));
        let line_start = text[..offset].rfind('\n').map_or(0, |i| i + 1);
        let line_end = text[offset..].find('\n').map_or(text.len(), |i| offset + i);
        let line = &text[line_start..line_end];
        let key = line
            .find('=')
            .filter(|&eq| line_start + eq < offset)
            .map(|eq| line[..eq].trim())
            .filter(|k| !k.is_empty() && !k.starts_with('['));
        let header = text[..line_end]
            .lines()
            .rev()
            .map(str::trim)
            .find(|l| l.starts_with('['))
            .and_then(header_name);
        Self {
            header,
            key,
            value: value_text(&text[offset..line_end]),
        }
    }

    /// `key = value` as the line should read, or the value alone.
    fn write(&self, value: &str) -> String {
        match self.key {
            Some(key) => format!("{key} = {value}"),
            None => value.to_string(),
        }
    }
}

/// The name of a `[name]` or `[[name]]` header line, and whether it has
/// two brackets.
fn header_name(line: &str) -> Option<(&str, bool)> {
    let line = line.split('#').next().unwrap_or("").trim();
    if let Some(inner) = line.strip_prefix("[[").and_then(|l| l.strip_suffix("]]")) {
        return Some((inner.trim(), true));
    }
    let inner = line.strip_prefix('[')?.strip_suffix(']')?;
    Some((inner.trim(), false))
}

/// A value's text: a quoted string whole, anything else up to a comment.
fn value_text(rest: &str) -> &str {
    let rest = rest.trim_start();
    if let Some(body) = rest.strip_prefix('"') {
        return body.find('"').map_or(rest, |end| &rest[..end + 2]);
    }
    rest.split('#').next().unwrap_or("").trim_end()
}

/// `[bus]` for `[[bus]]`, and `[[http]]` for `[http]`.
fn header(at: &At<'_>, raw: &str) -> Option<String> {
    let (name, double) = at.header?;
    let list = LISTS.iter().find(|(n, _)| *n == name);
    match (list, double) {
        (Some((_, what)), false) if raw.contains("expected a sequence") => Some(format!(
            "[{name}] must be written [[{name}]] (two brackets): it starts one entry of a list, \
             and each {what} has its own [[{name}]]"
        )),
        (None, true) if !raw.starts_with("unknown field") => Some(format!(
            "[[{name}]] must be written [{name}] (one pair of brackets): there is one [{name}] \
             section, not a list of them (two brackets are for [[bus]], [[bus.drive]], \
             [[http.token]] and the lists of [modbus_tcp])"
        )),
        _ => None,
    }
}

/// `listen = "8080"` and other addresses without an IP address.
fn address(at: &At<'_>, raw: &str) -> Option<String> {
    if raw != "invalid socket address syntax" {
        return None;
    }
    let given = at.value.trim_matches('"');
    let port = given
        .rsplit(':')
        .next()
        .filter(|p| !p.is_empty() && p.len() <= 5 && p.bytes().all(|b| b.is_ascii_digit()));
    let port = port.unwrap_or(match at.header {
        Some(("modbus_tcp", _)) => "502",
        Some(("modbus_tcp.tls", _)) => "802",
        _ => "8080",
    });
    if given.matches(':').count() > 1 && !given.starts_with('[') {
        return Some(format!(
            "{} is not an address and port: an IPv6 address goes in brackets, e.g. {} \
             (every interface) or {}",
            at.write(at.value),
            at.write(&format!("\"[::]:{port}\"")),
            at.write(&format!("\"[::1]:{port}\"")),
        ));
    }
    let why = if given.bytes().all(|b| b.is_ascii_digit()) || given.starts_with(':') {
        "is a port without an address".to_string()
    } else if !given.contains(':') {
        "has no port".to_string()
    } else {
        "is not an IP address and port (a host name is not taken here)".to_string()
    };
    Some(format!(
        "{} {why}: write {} (every network interface) or {} (this machine only), or the IP \
         address of one interface with the port",
        at.write(at.value),
        at.write(&format!("\"0.0.0.0:{port}\"")),
        at.write(&format!("\"127.0.0.1:{port}\"")),
    ))
}

/// Numbers, `true`/`false` and lists written in quotes.
fn quoted(at: &At<'_>, raw: &str) -> Option<String> {
    let rest = raw.strip_prefix("invalid type: string \"")?;
    let (given, expected) = rest.rsplit_once("\", expected ")?;
    let written = at.write(&format!("\"{given}\""));
    if is_number_type(expected) {
        let number = given.trim().replace(',', ".");
        return Some(if number.parse::<f64>().is_ok() {
            format!(
                "{written}: numbers are written without quotes: {}",
                at.write(&number)
            )
        } else {
            format!("{written}: a number is wanted here, written without quotes")
        });
    }
    if expected == "a boolean" {
        return Some(match given {
            "true" | "false" => format!(
                "{written}: true and false are written without quotes: {}",
                at.write(given)
            ),
            _ => format!("{written}: true or false is wanted here, written without quotes"),
        });
    }
    if expected == "a sequence" {
        return Some(format!(
            "{written}: a list is wanted here, in square brackets: {}",
            at.write(&format!("[\"{given}\"]"))
        ));
    }
    None
}

/// Text written without quotes, and numbers where text is wanted.
fn unquoted(at: &At<'_>, raw: &str) -> Option<String> {
    if raw.contains("string values must be quoted") {
        let word = at.value;
        return Some(format!(
            "{}: text is written in quotes: {}",
            at.write(word),
            at.write(&format!("\"{word}\""))
        ));
    }
    let rest = raw
        .strip_prefix("invalid type: integer `")
        .or_else(|| raw.strip_prefix("invalid type: floating point `"))?;
    let (given, expected) = rest.split_once("`, expected ")?;
    if expected == "a string" {
        return Some(format!(
            "{}: this is text, written in quotes: {}",
            at.write(given),
            at.write(&format!("\"{given}\""))
        ));
    }
    if is_integer_type(expected) {
        return Some(format!(
            "{}: a whole number is wanted here, without a decimal point{}",
            at.write(given),
            given
                .strip_suffix(".0")
                .map(|whole| format!(": {}", at.write(whole)))
                .unwrap_or_default()
        ));
    }
    None
}

fn is_integer_type(expected: &str) -> bool {
    matches!(
        expected,
        "i8" | "i16" | "i32" | "i64" | "u8" | "u16" | "u32" | "u64" | "usize" | "isize"
    )
}

fn is_number_type(expected: &str) -> bool {
    is_integer_type(expected) || matches!(expected, "f32" | "f64")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain message for `raw` at the first `mark` in `text`.
    fn at(text: &str, mark: &str, raw: &str) -> String {
        plain(text, text.find(mark).unwrap(), raw)
    }

    #[test]
    fn a_list_written_as_a_table_and_the_reverse() {
        let text = "[bus]\nname = \"line1\"\n";
        assert_eq!(
            at(text, "[bus]", "invalid type: map, expected a sequence"),
            "[bus] must be written [[bus]] (two brackets): it starts one entry of a list, \
             and each bus (serial adapter) has its own [[bus]]"
        );
        let text = "[[bus]]\nname = \"a\"\n[bus.drive]  # the conveyor\nunit = 1\n";
        assert!(
            at(
                text,
                "[bus.drive]",
                "invalid type: map, expected a sequence"
            )
            .starts_with("[bus.drive] must be written [[bus.drive]]")
        );
        // A single section as a list: serde reads the list's table as the
        // section's first field, and says something else entirely.
        let text = "[[safety]]\non_shutdown = \"brake\"\n";
        let raw = "unknown variant `on_shutdown`, expected one of `none`, `zero-speed`, `brake`";
        assert!(
            at(text, "on_shutdown", raw)
                .starts_with("[[safety]] must be written [safety] (one pair of brackets)")
        );
        // A section inside a list entry is a single one.
        let text = "[[bus]]\nname = \"a\"\n[[bus.rs485]]\n";
        assert!(
            at(
                text,
                "[[bus.rs485]]",
                "invalid type: map, expected a boolean"
            )
            .starts_with("[[bus.rs485]] must be written [bus.rs485]")
        );
        // A key the code does not know keeps the list of those it does.
        let raw = "unknown field `zz`, expected one of `a`, `b`";
        assert_eq!(at("[[bus]]\nzz = 1\n", "zz", raw), raw);
    }

    #[test]
    fn an_address_gets_its_right_form() {
        let raw = "invalid socket address syntax";
        assert_eq!(
            at("[http]\nlisten = \"8080\"\n", "\"8080\"", raw),
            "listen = \"8080\" is a port without an address: write listen = \"0.0.0.0:8080\" \
             (every network interface) or listen = \"127.0.0.1:8080\" (this machine only), \
             or the IP address of one interface with the port"
        );
        let text = "[modbus_tcp]\nlisten = \"localhost:1502\"  # the PLCs\n";
        let e = at(text, "\"localhost", raw);
        assert!(
            e.starts_with("listen = \"localhost:1502\" is not an IP address and port")
                && e.contains("listen = \"0.0.0.0:1502\""),
            "{e}"
        );
        let e = at("[modbus_tcp]\nlisten = \"10.0.0.5\"\n", "\"10", raw);
        assert!(
            e.contains("has no port") && e.contains("\"127.0.0.1:502\""),
            "{e}"
        );
        let e = at("[http]\nlisten = \"::1:8080\"\n", "\"::", raw);
        assert!(e.contains("IPv6 address goes in brackets"), "{e}");
    }

    #[test]
    fn numbers_and_booleans_in_quotes_and_text_without() {
        let text = "[[bus]]\nbaud = \"115200\"\n";
        assert_eq!(
            at(
                text,
                "\"115200\"",
                "invalid type: string \"115200\", expected i64"
            ),
            "baud = \"115200\": numbers are written without quotes: baud = 115200"
        );
        let text = "[[bus.drive]]\ngear_ratio = \"3,75\"\n";
        assert_eq!(
            at(
                text,
                "\"3,75\"",
                "invalid type: string \"3,75\", expected f64"
            ),
            "gear_ratio = \"3,75\": numbers are written without quotes: gear_ratio = 3.75"
        );
        let text = "[modbus_tcp]\nenabled = \"true\"\n";
        assert_eq!(
            at(
                text,
                "\"true\"",
                "invalid type: string \"true\", expected a boolean"
            ),
            "enabled = \"true\": true and false are written without quotes: enabled = true"
        );
        let text = "[safety]\non_shutdown = brake   # stop everything\n";
        assert_eq!(
            at(
                text,
                "brake ",
                "string values must be quoted, expected literal string"
            ),
            "on_shutdown = brake: text is written in quotes: on_shutdown = \"brake\""
        );
        let text = "[[bus]]\nport = 5\n";
        assert_eq!(
            at(text, "5", "invalid type: integer `5`, expected a string"),
            "port = 5: this is text, written in quotes: port = \"5\""
        );
        let text = "[modbus_tcp]\nallowed_networks = \"10.0.0.0/8\"\n";
        assert_eq!(
            at(
                text,
                "\"10",
                "invalid type: string \"10.0.0.0/8\", expected a sequence"
            ),
            "allowed_networks = \"10.0.0.0/8\": a list is wanted here, in square brackets: \
             allowed_networks = [\"10.0.0.0/8\"]"
        );
        let text = "[[bus]]\nbaud = 115200.0\n";
        assert_eq!(
            at(
                text,
                "115200.0",
                "invalid type: floating point `115200.0`, expected i64"
            ),
            "baud = 115200.0: a whole number is wanted here, without a decimal point: baud = 115200"
        );
    }

    #[test]
    fn other_messages_are_kept() {
        let raw = "unit 0 is out of range: valid 1 to 255 (0 is the broadcast address)";
        assert_eq!(at("[[bus.drive]]\nunit = 0\n", "0", raw), raw);
    }
}
