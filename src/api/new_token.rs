//! `drivegate token new`: a fresh API token and the `[[http.token]]` lines
//! that configure it, so nobody has to hash a token by hand.
//!
//! The token is 32 bytes from the operating system's random source (256
//! bits: guessing is out of the question, and a SHA-256 of it is as good as
//! a password hash), written as 64 lowercase hex digits: URL-safe, no
//! quoting in a shell or a header. Only its digest goes into the
//! configuration; the token itself is printed once.

use rand::TryRngCore;
use rand::rngs::OsRng;
use serde::Deserialize;
use sha2::{Digest, Sha256};

use crate::config::HttpConfig;
use crate::control::Role;

/// Bytes of randomness in a token.
pub const TOKEN_BYTES: usize = 32;

/// What the first token changes, said by `token new` (the reload that
/// adds it says it again): without tokens the API is for this machine
/// only and every client on it is admin; with one, nobody is without a
/// token.
pub const FIRST_TOKEN_NOTE: &str = "\
If it is the configuration's first token: from that reload on, every client
needs a token, on this machine (loopback) too. Until then, clients on this
machine are admin without one; after it, the console asks for a token and
curl needs -H \"Authorization: Bearer TOKEN\".";

/// The advice `token new` adds for a token that is not an admin's.
pub const MAKE_AN_ADMIN: &str = "\
Make an admin token for yourself too, before the reload, or no client keeps
the admin's controls (scans, ramps, saves to flash, reloads from the console
or the API; systemctl reload needs no token):
  drivegate token new --name NAME --role admin";

/// A token just made, with the configuration lines that accept it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NewToken {
    /// The secret, to hand to the client once.
    pub token: String,
    /// The `[[http.token]]` table to paste into the configuration.
    pub config: String,
}

/// Why no token was made.
#[derive(Debug, thiserror::Error)]
pub enum NewTokenError {
    /// The name or role is not one the daemon accepts (its own words).
    #[error("{0}")]
    Invalid(String),
    /// The system's random source failed.
    #[error("cannot read the system's random source: {0}")]
    Random(String),
}

/// Makes a token for `name` with `role` ("viewer", "operator", "admin")
/// from the system's random source.
pub fn generate(name: &str, role: &str) -> Result<NewToken, NewTokenError> {
    let mut secret = [0u8; TOKEN_BYTES];
    OsRng
        .try_fill_bytes(&mut secret)
        .map_err(|e| NewTokenError::Random(e.to_string()))?;
    from_secret(name, role, &secret)
}

/// The token and its lines for given random bytes (the pure part of
/// [`generate`]). The lines are checked with the daemon's own `[http]`
/// parser before they are returned, so what is printed is what it accepts.
pub fn from_secret(name: &str, role: &str, secret: &[u8]) -> Result<NewToken, NewTokenError> {
    let token = hex(secret);
    let digest = hex(&Sha256::digest(token.as_bytes()));
    // Names are letters, digits, '-', '_' and '.' (checked below), roles a
    // lowercase word: neither needs escaping, but a bad one must not make
    // the TOML say something else than intended.
    let quoted = |s: &str| toml::Value::String(s.to_string()).to_string();
    let config = format!(
        "[[http.token]]\nname = {}\nrole = {}\nsha256 = \"{digest}\"\n",
        quoted(name),
        quoted(role)
    );
    check(&config)?;
    Ok(NewToken { token, config })
}

/// Parses `lines` as the daemon parses `[http]`.
fn check(lines: &str) -> Result<(), NewTokenError> {
    #[derive(Deserialize)]
    struct Doc {
        http: HttpConfig,
    }
    let doc: Doc = toml::from_str(lines).map_err(|e| {
        let message = e.message().to_string();
        if message.contains("unknown variant") {
            let roles = [Role::Viewer, Role::Operator, Role::Admin].map(Role::name);
            NewTokenError::Invalid(format!("role must be one of {}", roles.join(", ")))
        } else {
            NewTokenError::Invalid(message)
        }
    })?;
    if doc.http.tokens.len() == 1 {
        Ok(())
    } else {
        Err(NewTokenError::Invalid("not one token".to_string()))
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::http::TokenSource;

    #[test]
    fn the_lines_hold_the_digest_of_the_token() {
        // SHA-256 of 64 "00" pairs, as `printf %s 00..00 | sha256sum` says.
        let made = from_secret("scada", "operator", &[0u8; 32]).unwrap();
        assert_eq!(made.token, "0".repeat(64));
        assert_eq!(
            made.config,
            "[[http.token]]\nname = \"scada\"\nrole = \"operator\"\n\
             sha256 = \"60e05bd1b195af2f94112fa7197a5c88289058840ce7c6df9693756bc6250f55\"\n"
        );
    }

    #[test]
    fn the_daemon_reads_the_lines_back_as_that_token() {
        let made = generate("dash.board_1", "viewer").unwrap();
        #[derive(Deserialize)]
        struct Doc {
            http: HttpConfig,
        }
        let doc: Doc = toml::from_str(&made.config).unwrap();
        let token = &doc.http.tokens[0];
        assert_eq!(token.name, "dash.board_1");
        assert_eq!(token.role, Role::Viewer);
        let expected: [u8; 32] = Sha256::digest(made.token.as_bytes()).into();
        assert_eq!(token.source, TokenSource::Sha256(expected));
    }

    #[test]
    fn two_tokens_differ_and_are_url_safe() {
        let a = generate("a", "admin").unwrap().token;
        let b = generate("a", "admin").unwrap().token;
        assert_ne!(a, b);
        assert_eq!(a.len(), 2 * TOKEN_BYTES);
        assert!(a.bytes().all(|c| c.is_ascii_hexdigit()));
    }

    #[test]
    fn a_bad_name_or_role_is_refused_in_the_daemons_words() {
        let e = from_secret("scada plc", "operator", &[1; 32]).unwrap_err();
        assert!(e.to_string().contains("1 to 64 letters"), "{e}");
        let e = from_secret("x\"\nrole = \"admin", "viewer", &[1; 32]).unwrap_err();
        assert!(e.to_string().contains("1 to 64 letters"), "{e}");
        let e = from_secret("scada", "root", &[1; 32]).unwrap_err();
        assert_eq!(e.to_string(), "role must be one of viewer, operator, admin");
    }
}
