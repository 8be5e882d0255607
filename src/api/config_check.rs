//! `drivegate check-config`'s checks of a configuration text, in one
//! place: the reloader's before it applies a file, `check-config`'s, and
//! the console's editor's as an admin types. The text parses and holds
//! together (refusals at their line and column, in plain words), its
//! certificates and keys load, and its tokens' secrets resolve; what it
//! holds that is valid but probably a mistake is said beside
//! ([`crate::config::warnings`]).

use serde::Serialize;
use utoipa::ToSchema;

use super::auth::{TokenError, Tokens};
use crate::config::{Config, ConfigError};

/// A message at a place of the text.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct Remark {
    /// 1-based line (0: the file as a whole).
    pub line: usize,
    /// 1-based column (0: the line as a whole).
    pub column: usize,
    /// What is wrong, in check-config's words.
    pub message: String,
}

/// What the checks found in a text.
#[derive(Debug, Clone)]
pub struct Checked {
    /// The configuration, when the text passes.
    pub config: Option<Config>,
    /// Why it does not pass (the parser stops at the first).
    pub problems: Vec<Remark>,
    /// What is valid but probably a mistake.
    pub warnings: Vec<Remark>,
}

/// The checks of `check-config` on `text` (named `origin` in messages):
/// the configuration, or why not as `origin:line:column: why` (or
/// `origin: why` for a certificate or a token).
pub fn check(text: &str, origin: &str) -> Result<Config, String> {
    let config = Config::parse(text, origin).map_err(|e| e.to_string())?;
    check_tls(&config).map_err(|e| format!("{origin}: {e}"))?;
    Tokens::resolve(&config.http.tokens, config.http.token_guesses)
        .map_err(|e| format!("{origin}: [http]: {e}"))?;
    Ok(config)
}

/// The certificates and keys of every TLS listener (and the MQTT face's
/// CA and client certificate) load, as a start would load them.
pub fn check_tls(config: &Config) -> Result<(), String> {
    if let Some(files) = &config.http.tls {
        crate::tls::server_config(files, crate::tls::ClientAuth::IfConfigured, &[])
            .map_err(|e| format!("[http.tls]: {e}"))?;
    }
    if let Some(section) = &config.modbus_tcp.tls {
        crate::tls::server_config(&section.files(), crate::tls::ClientAuth::Required, &[])
            .map_err(|e| format!("[modbus_tcp.tls]: {e}"))?;
    }
    if let Some(mqtt) = &config.mqtt
        && mqtt.broker.tls
    {
        let identity = match (&mqtt.client_cert, &mqtt.client_key) {
            (Some(cert), Some(key)) => Some((cert.get_ref().as_path(), key.as_path())),
            _ => None,
        };
        crate::tls::client_config(mqtt.ca.as_deref(), identity)
            .map_err(|e| format!("[mqtt]: {e}"))?;
    }
    Ok(())
}

/// The same checks, each finding at its place in `text` (for an editor
/// that marks the line), with the warnings.
pub fn remarks(text: &str, origin: &str) -> Checked {
    let mut checked = Checked {
        config: None,
        problems: Vec::new(),
        warnings: Vec::new(),
    };
    let config = match Config::parse(text, origin) {
        Ok(config) => config,
        Err(
            ConfigError::Parse {
                line,
                column,
                message,
                ..
            }
            | ConfigError::Invalid {
                line,
                column,
                message,
                ..
            },
        ) => {
            checked.problems.push(Remark {
                line,
                column,
                message,
            });
            return checked;
        }
        Err(e) => {
            checked.problems.push(at_file(e.to_string()));
            return checked;
        }
    };
    checked.warnings = crate::config::warnings::warnings(&config, text, origin)
        .into_iter()
        .map(|w| placed(&w, origin))
        .collect();
    if let Err(e) = check_tls(&config) {
        let section = e.split(':').next().unwrap_or("");
        checked.problems.push(Remark {
            line: header_line(text, section),
            column: 0,
            message: e,
        });
    }
    if let Err(e) = Tokens::resolve(&config.http.tokens, config.http.token_guesses) {
        let name = match &e {
            TokenError::File { name, .. }
            | TokenError::Env { name, .. }
            | TokenError::Empty { name, .. } => name.clone(),
        };
        let line = crate::config::edit::token_lines(text)
            .into_iter()
            .find(|(n, _)| *n == name)
            .map_or(0, |(_, line)| line);
        checked.problems.push(Remark {
            line,
            column: 0,
            message: format!("[http]: {e}"),
        });
    }
    if checked.problems.is_empty() {
        checked.config = Some(config);
    }
    checked
}

/// A message of the whole file.
fn at_file(message: String) -> Remark {
    Remark {
        line: 0,
        column: 0,
        message,
    }
}

/// `origin:line:column: what` as a remark at its place.
fn placed(said: &str, origin: &str) -> Remark {
    let rest = said
        .strip_prefix(origin)
        .and_then(|r| r.strip_prefix(':'))
        .unwrap_or(said);
    let mut parts = rest.splitn(3, ':');
    let (line, column) = (parts.next(), parts.next());
    match (
        line.and_then(|l| l.parse().ok()),
        column.and_then(|c| c.parse().ok()),
        parts.next(),
    ) {
        (Some(line), Some(column), Some(message)) => Remark {
            line,
            column,
            message: message.trim_start().to_string(),
        },
        _ => at_file(said.to_string()),
    }
}

/// The line of the table header `[section]` (or `[[section]]`) in `text`,
/// 0 when there is none.
fn header_line(text: &str, section: &str) -> usize {
    let name = section.trim_matches(|c| c == '[' || c == ']');
    if name.is_empty() {
        return 0;
    }
    text.lines()
        .position(|l| {
            let l = l.trim_start();
            l.starts_with('[') && l.trim_start_matches('[').trim_start().starts_with(name)
        })
        .map_or(0, |i| i + 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_typo_is_found_at_its_line_and_column() {
        let text =
            "[http]\nlisten = \"127.0.0.1:8080\"\n\n[[bus]]\nname = \"line1\"\nprot = \"sim\"\n";
        let checked = remarks(text, "drivegate.toml");
        assert!(checked.config.is_none());
        let p = &checked.problems[0];
        assert_eq!((p.line, p.column), (6, 1), "{p:?}");
        assert!(p.message.contains("prot"), "{}", p.message);
        // The reloader's check says the same, with the file's name.
        let whole = check(text, "drivegate.toml").unwrap_err();
        assert!(whole.starts_with("drivegate.toml:6:1: "), "{whole}");
    }

    #[test]
    fn warnings_and_files_are_placed() {
        let text = "[[bus]]\nname = \"line1\"\nport = \"sim\"\nbaud = 11520\n";
        let checked = remarks(text, "plant.toml");
        assert!(checked.problems.is_empty(), "{:?}", checked.problems);
        assert!(checked.config.is_some());
        let w = &checked.warnings[0];
        assert_eq!(w.line, 4, "{w:?}");
        assert!(
            w.message.starts_with("bus \"line1\": baud = 11520"),
            "{}",
            w.message
        );

        let text = "[http]\nlisten = \"127.0.0.1:8080\"\n\n[http.tls]\ncert = \"/nonexistent/c.pem\"\nkey = \"/nonexistent/k.pem\"\n";
        let checked = remarks(text, "plant.toml");
        let p = &checked.problems[0];
        assert_eq!(p.line, 4, "{p:?}");
        assert!(p.message.starts_with("[http.tls]: "), "{}", p.message);

        let text =
            "[[http.token]]\nname = \"ops\"\nrole = \"admin\"\nfile = \"/nonexistent/ops.token\"\n";
        let p = &remarks(text, "plant.toml").problems[0];
        assert_eq!(p.line, 2, "{p:?}");
        assert!(
            p.message.contains("cannot read /nonexistent/ops.token"),
            "{}",
            p.message
        );
    }

    #[test]
    fn positions_are_read_back_from_the_warnings_words() {
        let r = placed("a.toml:12:5: it is odd: really", "a.toml");
        assert_eq!(
            (r.line, r.column, r.message.as_str()),
            (12, 5, "it is odd: really")
        );
        let r = placed("something else", "a.toml");
        assert_eq!((r.line, r.column), (0, 0));
        assert_eq!(
            header_line("[a]\n  [[ modbus_tcp.tls ]]\n", "[modbus_tcp.tls]"),
            2
        );
        assert_eq!(header_line("[a]\n", "[mqtt]"), 0);
    }
}
