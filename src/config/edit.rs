//! Changes written into the configuration file itself, keeping its
//! comments, order and layout (`toml_edit`): the console's "add to
//! configuration" after a scan, an API token made or revoked. Pure: text
//! in, text out; the daemon's reloader writes and reloads it
//! (`crate::daemon::reloader`).

use toml_edit::{ArrayOfTables, DocumentMut, Item, Table, value};

/// SHA-256 of a configuration file's text, in hex: what a client that read
/// it sends back with its change, so a change made meanwhile on disk is
/// not overwritten.
pub fn sha256_hex(text: &str) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(text.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A drive to add: its unit address and its name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NewDrive {
    /// Unit address on the bus, 1 to 255.
    pub unit: u8,
    /// Name, unique over all buses.
    pub name: String,
}

/// The `[[bus.drive]]` tables of `drives`, as they are added (what the
/// console shows before writing).
pub fn drive_tables(drives: &[NewDrive]) -> String {
    drives
        .iter()
        .map(|d| {
            format!(
                "[[bus.drive]]\nunit = {}\nname = {}\n",
                d.unit,
                toml_edit::Value::from(d.name.as_str())
            )
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// `text` with `drives` added at the end of bus `bus`'s drives, every
/// other line as it was. Refused, in words, when the text is not TOML,
/// the bus is not in it, or a unit or name is already there (the check
/// of the whole file comes after, as for any reload).
pub fn add_drives(text: &str, bus: &str, drives: &[NewDrive]) -> Result<String, String> {
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| format!("the configuration file is not valid TOML: {e}"))?;
    let buses = doc
        .get_mut("bus")
        .and_then(Item::as_array_of_tables_mut)
        .ok_or_else(|| format!("the configuration file has no [[bus]] named \"{bus}\""))?;
    let table = buses
        .iter_mut()
        .find(|t| t.get("name").and_then(Item::as_str) == Some(bus))
        .ok_or_else(|| format!("the configuration file has no [[bus]] named \"{bus}\""))?;
    if !table.contains_key("drive") {
        table.insert("drive", Item::ArrayOfTables(ArrayOfTables::new()));
    }
    let list = table
        .get_mut("drive")
        .and_then(Item::as_array_of_tables_mut)
        .ok_or_else(|| format!("bus \"{bus}\": drive is not a list of [[bus.drive]] tables"))?;
    for d in drives {
        let taken = list.iter().any(|t| {
            t.get("unit").and_then(Item::as_integer) == Some(i64::from(d.unit))
                || t.get("name").and_then(Item::as_str) == Some(d.name.as_str())
        });
        if taken {
            return Err(format!(
                "bus \"{bus}\" already has a drive at unit {} or named \"{}\"",
                d.unit, d.name
            ));
        }
        let mut entry = Table::new();
        entry.insert("unit", value(i64::from(d.unit)));
        entry.insert("name", value(d.name.as_str()));
        list.push(entry);
    }
    Ok(doc.to_string())
}

/// `text` with a `[[http.token]]` for `name` with `role` and the SHA-256
/// (hex) of its secret, after the file's other tokens (or at its end).
/// Refused, in words, when the text is not TOML or a token of that name
/// is there already (the check of the whole file comes after).
pub fn add_token(text: &str, name: &str, role: &str, sha256: &str) -> Result<String, String> {
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| format!("the configuration file is not valid TOML: {e}"))?;
    if !doc.contains_key("http") {
        let mut http = Table::new();
        http.set_implicit(true);
        doc.insert("http", Item::Table(http));
    }
    let http = doc
        .get_mut("http")
        .and_then(Item::as_table_mut)
        .ok_or("the configuration file's http is not a [http] table")?;
    if !http.contains_key("token") {
        http.insert("token", Item::ArrayOfTables(ArrayOfTables::new()));
    }
    let list = http
        .get_mut("token")
        .and_then(Item::as_array_of_tables_mut)
        .ok_or("the configuration file's http.token is not a list of [[http.token]] tables")?;
    if list
        .iter()
        .any(|t| t.get("name").and_then(Item::as_str) == Some(name))
    {
        return Err(format!(
            "the configuration file has a token named \"{name}\" already: choose another name, or revoke that one first"
        ));
    }
    let mut entry = Table::new();
    entry.insert("name", value(name));
    entry.insert("role", value(role));
    entry.insert("sha256", value(sha256));
    list.push(entry);
    Ok(doc.to_string())
}

/// `text` without the `[[http.token]]` named `name`, every other line as
/// it was (the comments inside that table go with it).
pub fn remove_token(text: &str, name: &str) -> Result<String, String> {
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| format!("the configuration file is not valid TOML: {e}"))?;
    let list = doc
        .get_mut("http")
        .and_then(Item::as_table_mut)
        .and_then(|h| h.get_mut("token"))
        .and_then(Item::as_array_of_tables_mut);
    let Some(list) = list else {
        return Err(format!(
            "the configuration file has no token named \"{name}\""
        ));
    };
    let at = list
        .iter()
        .position(|t| t.get("name").and_then(Item::as_str) == Some(name))
        .ok_or_else(|| format!("the configuration file has no token named \"{name}\""))?;
    list.remove(at);
    if list.is_empty()
        && let Some(http) = doc.get_mut("http").and_then(Item::as_table_mut)
    {
        http.remove("token");
    }
    Ok(doc.to_string())
}

/// The line of each `[[http.token]]`'s `name` in `text`, by name (where
/// the tokens page says a token is defined). Empty when the text is not
/// TOML.
pub fn token_lines(text: &str) -> Vec<(String, usize)> {
    #[derive(serde::Deserialize)]
    struct File {
        http: Option<Http>,
    }
    #[derive(serde::Deserialize)]
    struct Http {
        #[serde(default)]
        token: Vec<Token>,
    }
    #[derive(serde::Deserialize)]
    struct Token {
        name: toml::Spanned<String>,
    }
    let Ok(file) = toml::from_str::<File>(text) else {
        return Vec::new();
    };
    file.http
        .map(|h| h.token)
        .unwrap_or_default()
        .into_iter()
        .map(|t| {
            let line = text[..t.name.span().start.min(text.len())]
                .matches('\n')
                .count()
                + 1;
            (t.name.into_inner(), line)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    const FILE: &str = r#"# The line's configuration.
[http]
listen = "127.0.0.1:8080"   # loopback only

# Line 1: the adapter on the left.
[[bus]]
name = "line1"
port = "sim"

[[bus.drive]]
unit = 1
name = "conveyor"  # the belt

# Line 2, still empty.
[[bus]]
name = "line2"
port = "sim"

[safety]
on_shutdown = "zero-speed"
"#;

    fn drive(unit: u8, name: &str) -> NewDrive {
        NewDrive {
            unit,
            name: name.to_string(),
        }
    }

    #[test]
    fn drives_are_added_to_their_bus_keeping_every_comment() {
        let out = add_drives(FILE, "line1", &[drive(2, "lift"), drive(3, "press")]).unwrap();
        for line in FILE.lines().filter(|l| l.contains('#')) {
            assert!(out.contains(line), "lost {line:?} in\n{out}");
        }
        let config = Config::parse(&out, "edited").unwrap();
        let units: Vec<(u8, &str)> = config.buses[0]
            .drives
            .iter()
            .map(|d| (d.unit(), d.name()))
            .collect();
        assert_eq!(units, vec![(1, "conveyor"), (2, "lift"), (3, "press")]);
        assert!(config.buses[1].drives.is_empty());
        // Only additions: every line of the file is still there, in order.
        let mut rest = out.lines();
        for line in FILE.lines() {
            assert!(
                rest.any(|l| l == line),
                "{line:?} moved or changed in\n{out}"
            );
        }
    }

    #[test]
    fn a_bus_without_drives_gets_its_first() {
        let out = add_drives(FILE, "line2", &[drive(1, "saw")]).unwrap();
        let config = Config::parse(&out, "edited").unwrap();
        assert_eq!(config.buses[1].drives[0].name(), "saw");
        assert_eq!(config.buses[0].drives.len(), 1);
    }

    #[test]
    fn refusals_say_why() {
        assert_eq!(
            add_drives(FILE, "line9", &[drive(2, "x")]).unwrap_err(),
            "the configuration file has no [[bus]] named \"line9\""
        );
        assert_eq!(
            add_drives(FILE, "line1", &[drive(1, "other")]).unwrap_err(),
            "bus \"line1\" already has a drive at unit 1 or named \"other\""
        );
        assert!(add_drives("[[bus]\n", "line1", &[]).is_err());
    }

    #[test]
    fn the_tables_shown_are_the_tables_written() {
        let shown = drive_tables(&[drive(4, "feeder"), drive(5, "odd \"name\"")]);
        assert_eq!(
            shown,
            "[[bus.drive]]\nunit = 4\nname = \"feeder\"\n\n[[bus.drive]]\nunit = 5\nname = 'odd \"name\"'\n"
        );
    }

    #[test]
    fn tokens_are_added_after_the_others_and_removed_alone() {
        let digest = "ab".repeat(32);
        let out = add_token(FILE, "scada", "operator", &digest).unwrap();
        let config = Config::parse(&out, "edited").unwrap();
        assert_eq!(config.http.tokens.len(), 1);
        assert_eq!(config.http.tokens[0].name, "scada");
        for line in FILE.lines() {
            assert!(out.contains(line), "lost {line:?} in\n{out}");
        }
        let two = add_token(&out, "ops", "admin", &"cd".repeat(32)).unwrap();
        let names: Vec<(String, usize)> = token_lines(&two);
        assert_eq!(names.len(), 2);
        assert_eq!((names[0].0.as_str(), names[1].0.as_str()), ("scada", "ops"));
        assert!(names[0].1 < names[1].1);
        assert_eq!(
            add_token(&two, "ops", "viewer", &digest).unwrap_err(),
            "the configuration file has a token named \"ops\" already: choose another name, or revoke that one first"
        );
        let one = remove_token(&two, "scada").unwrap();
        let config = Config::parse(&one, "edited").unwrap();
        let left: Vec<&str> = config.http.tokens.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(left, ["ops"]);
        // The last one removed: the file is as it was.
        let none = remove_token(&one, "ops").unwrap();
        assert_eq!(Config::parse(&none, "edited").unwrap().http.tokens.len(), 0);
        assert!(remove_token(&none, "ops").is_err());
        for line in FILE.lines() {
            assert!(none.contains(line), "lost {line:?} in\n{none}");
        }
    }

    #[test]
    fn a_file_without_http_gets_its_first_token() {
        let out = add_token(
            "[[bus]]\nname = \"a\"\nport = \"sim\"\n",
            "x",
            "viewer",
            &"00".repeat(32),
        )
        .unwrap();
        let config = Config::parse(&out, "edited").unwrap();
        assert_eq!(config.http.tokens[0].name, "x");
        assert_eq!(config.buses.len(), 1);
    }
}
