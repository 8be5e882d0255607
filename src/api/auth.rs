//! Bearer tokens: resolved once at start (hash, file or environment), and
//! checked on every request in constant time (by [`super::caller`], which
//! turns a request into the caller it comes from).
//!
//! Only SHA-256 digests are kept in memory after start; a presented token is
//! hashed and compared with every configured digest without an early exit,
//! so the time taken says nothing about how close a guess was. An address
//! that presents too many unknown tokens is paused ([`super::throttle`]).
//!
//! Where a token may be: `Authorization: Bearer <token>` on every route;
//! on the WebSocket routes also the subprotocol
//! `drivegate.bearer.<base64url of the token>`
//! (offered beside [`SUBPROTOCOL`], the only one answered, so the token is
//! never echoed) and, discouraged, `?access_token=` in the URL.

use std::sync::{Arc, Mutex};

use axum::http::header::{AUTHORIZATION, SEC_WEBSOCKET_PROTOCOL};
use axum::http::request::Parts;
use sha2::{Digest, Sha256};

use super::throttle::SignIns;
use crate::config::http::{TokenConfig, TokenSource};
use crate::control::Role;

/// The WebSocket subprotocol of drivegate's streams: the one the daemon
/// answers when a client offers it.
pub const SUBPROTOCOL: &str = "drivegate";

/// Prefix of the subprotocol that carries a token (browsers cannot set
/// headers on a WebSocket, but they can offer subprotocols).
pub const BEARER_PROTOCOL_PREFIX: &str = "drivegate.bearer.";

/// One usable token.
#[derive(Clone)]
struct Entry {
    name: Arc<str>,
    role: Role,
    digest: [u8; 32],
}

/// The configured tokens, as digests, and the failures of each address.
/// A reload replaces the tokens ([`Tokens::replace`]) of every clone at
/// once; the failures are kept.
#[derive(Clone, Default)]
pub struct Tokens {
    entries: Arc<std::sync::RwLock<Arc<Vec<Entry>>>>,
    /// The running configuration, whose tokens replace these when a
    /// reload changes it.
    follower: Option<Arc<crate::control::reload::ConfigFollower>>,
    throttle: Arc<Mutex<SignIns>>,
    /// When each token (by digest, so a token made again under the same
    /// name starts afresh) was last presented, since the listener started.
    used: Arc<Mutex<std::collections::HashMap<[u8; 32], std::time::SystemTime>>>,
}

impl std::fmt::Debug for Tokens {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Names and roles only: never the digests.
        f.debug_list()
            .entries(self.entries().iter().map(|e| (&*e.name, e.role.name())))
            .finish()
    }
}

/// Why a configured token cannot be used; the daemon then refuses to start
/// rather than run with fewer (or no) checks than configured.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    /// The token file cannot be read.
    #[error("API token \"{name}\": cannot read {path}: {source}")]
    File {
        /// Token name.
        name: String,
        /// The file.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// The environment variable is not set (or not UTF-8).
    #[error("API token \"{name}\": environment variable {var} is not set")]
    Env {
        /// Token name.
        name: String,
        /// The variable.
        var: String,
    },
    /// The file or variable is empty.
    #[error("API token \"{name}\": {origin} is empty")]
    Empty {
        /// Token name.
        name: String,
        /// Where it was read from.
        origin: String,
    },
}

impl Tokens {
    /// Reads every token's secret and keeps its digest; an address is paused
    /// after `guesses` unknown tokens within a minute.
    pub fn resolve(configs: &[TokenConfig], guesses: u32) -> Result<Tokens, TokenError> {
        let mut entries = Vec::with_capacity(configs.len());
        for t in configs {
            let digest = match &t.source {
                TokenSource::Sha256(d) => *d,
                TokenSource::File(path) => {
                    let text =
                        std::fs::read_to_string(path).map_err(|source| TokenError::File {
                            name: t.name.clone(),
                            path: path.display().to_string(),
                            source,
                        })?;
                    warn_if_world_readable(&t.name, path);
                    digest_of_secret(&t.name, text.trim(), || path.display().to_string())?
                }
                TokenSource::Env(var) => {
                    let value = std::env::var(var).map_err(|_| TokenError::Env {
                        name: t.name.clone(),
                        var: var.clone(),
                    })?;
                    digest_of_secret(&t.name, value.trim(), || format!("${var}"))?
                }
            };
            entries.push(Entry {
                name: t.name.as_str().into(),
                role: t.role,
                digest,
            });
        }
        Ok(Tokens {
            entries: Arc::new(std::sync::RwLock::new(Arc::new(entries))),
            follower: None,
            throttle: Arc::new(Mutex::new(SignIns::new(guesses))),
            used: Arc::default(),
        })
    }

    /// From now on, the tokens of each configuration a reload applies
    /// replace these, from the next request on.
    pub fn follow(mut self, control: &crate::control::Control) -> Self {
        self.follower = Some(Arc::new(crate::control::reload::ConfigFollower::new(
            control,
        )));
        self
    }

    fn entries(&self) -> Arc<Vec<Entry>> {
        if let Some(config) = self.follower.as_ref().and_then(|f| f.changed()) {
            self.reloaded(&config);
        }
        self.entries
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Takes the tokens of a reloaded configuration (the reloader checked
    /// that they resolve).
    fn reloaded(&self, config: &crate::config::Config) {
        let new = match Tokens::resolve(&config.http.tokens, config.http.token_guesses) {
            Ok(new) => new,
            Err(e) => {
                tracing::warn!("API tokens not reloaded, the old ones stay: {e}");
                return;
            }
        };
        let mut entries = self.entries.write().unwrap_or_else(|p| p.into_inner());
        let fresh = new.entries();
        if fresh.is_empty() && !entries.is_empty() {
            // Without tokens every client is admin: safe only on loopback,
            // where the reload reopens the listener (`crate::daemon::supervisor`); this
            // one keeps its tokens until it closes.
            tracing::info!(
                "every API token was removed: this listener keeps the old ones until the reload has reopened the API on loopback"
            );
            return;
        }
        *entries = fresh;
        tracing::info!(tokens = entries.len(), "API tokens reloaded");
    }

    /// The failures of each address that presented unknown tokens.
    pub fn throttle(&self) -> std::sync::MutexGuard<'_, SignIns> {
        self.throttle.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// True when no token is configured (no authentication, loopback only).
    pub fn is_empty(&self) -> bool {
        self.entries().is_empty()
    }

    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.entries().len()
    }

    /// The name and role of the token `presented`, if it is one of ours.
    pub fn check(&self, presented: &str) -> Option<(Arc<str>, Role)> {
        let digest: [u8; 32] = Sha256::digest(presented.as_bytes()).into();
        let mut found = None;
        for entry in self.entries().iter() {
            if constant_time_eq(&entry.digest, &digest) {
                found = Some((entry.name.clone(), entry.role));
            }
        }
        if found.is_some() {
            self.used
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(digest, std::time::SystemTime::now());
        }
        found
    }

    /// When each token in use was last presented (by name), since this
    /// listener started; a token not presented since is absent.
    pub fn last_used(&self) -> std::collections::HashMap<String, std::time::SystemTime> {
        let used = self.used.lock().unwrap_or_else(|p| p.into_inner()).clone();
        self.entries()
            .iter()
            .filter_map(|e| used.get(&e.digest).map(|at| (e.name.to_string(), *at)))
            .collect()
    }
}

fn digest_of_secret(
    name: &str,
    secret: &str,
    origin: impl FnOnce() -> String,
) -> Result<[u8; 32], TokenError> {
    if secret.is_empty() {
        return Err(TokenError::Empty {
            name: name.to_string(),
            origin: origin(),
        });
    }
    Ok(Sha256::digest(secret.as_bytes()).into())
}

fn warn_if_world_readable(name: &str, path: &std::path::Path) {
    use std::os::unix::fs::PermissionsExt;
    if let Ok(meta) = std::fs::metadata(path)
        && meta.permissions().mode() & 0o004 != 0
    {
        tracing::warn!(
            token = name,
            file = %path.display(),
            "the API token file is readable by every user: chmod o-r it"
        );
    }
}

/// Compares two digests in time independent of where they differ.
fn constant_time_eq(a: &[u8; 32], b: &[u8; 32]) -> bool {
    let diff = a
        .iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y));
    std::hint::black_box(diff) == 0
}

/// The token a request presents: `Authorization: Bearer <token>`, and on a
/// WebSocket route (`websocket`) also the subprotocol or `?access_token=`.
pub fn presented(parts: &Parts, websocket: bool) -> Option<String> {
    bearer(parts).or_else(|| {
        websocket
            .then(|| protocol_token(parts).or_else(|| query_token(parts.uri.query().unwrap_or(""))))
            .flatten()
    })
}

/// The token in a `drivegate.bearer.<base64url of the token>` subprotocol
/// (subprotocol names allow only a few characters, tokens may have any).
fn protocol_token(parts: &Parts) -> Option<String> {
    parts
        .headers
        .get_all(SEC_WEBSOCKET_PROTOCOL)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .find_map(|p| p.trim().strip_prefix(BEARER_PROTOCOL_PREFIX))
        .and_then(base64url_decode)
        .and_then(|bytes| String::from_utf8(bytes).ok())
        .filter(|t| !t.is_empty())
}

/// Decodes unpadded (or padded) base64url.
fn base64url_decode(text: &str) -> Option<Vec<u8>> {
    let text = text.trim_end_matches('=');
    let mut out = Vec::with_capacity(text.len() * 3 / 4);
    let mut acc = 0u32;
    let mut bits = 0u32;
    for c in text.bytes() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'-' => 62,
            b'_' => 63,
            _ => return None,
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    // Leftover bits must be zero padding (and fewer than a character).
    (bits < 6 && acc == 0).then_some(out)
}

/// True when a request's offered subprotocols include [`SUBPROTOCOL`].
pub fn offers_subprotocol(headers: &axum::http::HeaderMap) -> bool {
    headers
        .get_all(SEC_WEBSOCKET_PROTOCOL)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|p| p.trim() == SUBPROTOCOL)
}

fn bearer(parts: &Parts) -> Option<String> {
    let value = parts.headers.get(AUTHORIZATION)?.to_str().ok()?;
    let (scheme, token) = value.split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| token.trim().to_string())
        .filter(|t| !t.is_empty())
}

fn query_token(query: &str) -> Option<String> {
    query.split('&').find_map(|pair| {
        let (key, value) = pair.split_once('=')?;
        (key == "access_token")
            .then(|| percent_decode(value))
            .flatten()
    })
}

/// Decodes `%XX` escapes and `+` of a query value.
fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'%' => {
                let hex = s.get(i + 1..i + 3)?;
                out.push(u8::from_str_radix(hex, 16).ok()?);
                i += 3;
            }
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            b => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8(out).ok().filter(|t| !t.is_empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn token(name: &str, role: Role, source: TokenSource) -> TokenConfig {
        TokenConfig {
            name: name.to_string(),
            role,
            source,
        }
    }

    #[test]
    fn tokens_from_hash_and_file() {
        let mut file = tempfile::NamedTempFile::new().unwrap();
        std::io::Write::write_all(&mut file, b"s3cret-admin\n").unwrap();
        let hash: [u8; 32] = Sha256::digest(b"op-token").into();
        let tokens = Tokens::resolve(
            &[
                token("scada", Role::Operator, TokenSource::Sha256(hash)),
                token(
                    "admin",
                    Role::Admin,
                    TokenSource::File(file.path().to_path_buf()),
                ),
            ],
            10,
        )
        .unwrap();
        assert_eq!(tokens.len(), 2);
        let (name, role) = tokens.check("op-token").unwrap();
        assert_eq!((&*name, role), ("scada", Role::Operator));
        let (name, role) = tokens.check("s3cret-admin").unwrap();
        assert_eq!((&*name, role), ("admin", Role::Admin));
        assert!(tokens.check("s3cret-admin\n").is_none());
        assert!(tokens.check("").is_none());
        assert!(!format!("{tokens:?}").contains("s3cret"));
    }

    #[test]
    fn unusable_tokens_stop_the_start() {
        let missing = Tokens::resolve(
            &[token(
                "x",
                Role::Viewer,
                TokenSource::File("/nonexistent/drivegate.token".into()),
            )],
            10,
        )
        .unwrap_err();
        assert!(
            missing
                .to_string()
                .contains("cannot read /nonexistent/drivegate.token")
        );
        let unset = Tokens::resolve(
            &[token(
                "x",
                Role::Viewer,
                TokenSource::Env("DRIVEGATE_SURELY_UNSET_VARIABLE".into()),
            )],
            10,
        )
        .unwrap_err();
        assert!(unset.to_string().contains("is not set"));
        let empty = tempfile::NamedTempFile::new().unwrap();
        let e = Tokens::resolve(
            &[token(
                "x",
                Role::Viewer,
                TokenSource::File(empty.path().to_path_buf()),
            )],
            10,
        )
        .unwrap_err();
        assert!(e.to_string().contains("is empty"));
    }

    #[test]
    fn query_tokens_are_decoded() {
        assert_eq!(
            query_token("drives=all&access_token=a%2Bb+c").as_deref(),
            Some("a+b c")
        );
        assert_eq!(query_token("access_token="), None);
        assert_eq!(query_token("access_token=%zz"), None);
        assert_eq!(query_token("x=1"), None);
    }

    #[test]
    fn subprotocol_tokens_are_found() {
        let request = |value: &str| {
            let (parts, ()) = axum::http::Request::builder()
                .header(SEC_WEBSOCKET_PROTOCOL, value)
                .body(())
                .unwrap()
                .into_parts();
            parts
        };
        // base64url("s3cret/+é") without padding.
        let p = request("drivegate, drivegate.bearer.czNjcmV0LyvDqQ");
        assert_eq!(protocol_token(&p).as_deref(), Some("s3cret/+é"));
        assert_eq!(base64url_decode("YWI").unwrap(), b"ab");
        assert_eq!(base64url_decode("YWJj").unwrap(), b"abc");
        assert_eq!(base64url_decode("YQ==").unwrap(), b"a");
        assert_eq!(base64url_decode("YR"), None);
        assert_eq!(base64url_decode("a+b/"), None);
        assert!(offers_subprotocol(&p.headers));
        let p = request("drivegate.bearer.");
        assert_eq!(protocol_token(&p), None);
        assert_eq!(
            protocol_token(&request("drivegate.bearer.not base64")),
            None
        );
        assert!(!offers_subprotocol(&p.headers));
        assert_eq!(protocol_token(&request("chat, superchat")), None);
    }

    #[test]
    fn digests_compare_whole() {
        let a = [7u8; 32];
        let mut b = a;
        assert!(constant_time_eq(&a, &b));
        b[31] ^= 1;
        assert!(!constant_time_eq(&a, &b));
    }
}
