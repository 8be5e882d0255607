//! `[http]` section: the listener, the API tokens and their roles, request
//! and connection limits, the stream's per-client buffer and the lease a
//! setpoint gets when it asks for none. The bounds of a lease are the
//! control core's, the same for every face (`[safety] lease_min_ms`,
//! `lease_max_ms`).
//!
//! Values are checked while parsing (through [`RawHttpConfig`]), so a bad
//! value is reported with the line of the `[http]` table. Token secrets are
//! not read here: `file` and `env` are resolved when the API starts (see
//! `crate::api::auth::Tokens::resolve`), so `check-config` never needs them.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use serde::{Deserialize, Deserializer};

use super::role::Role;

/// Where a token's secret comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TokenSource {
    /// The SHA-256 of the token (`sha256sum` of it, without the newline):
    /// the config file then holds no secret.
    Sha256([u8; 32]),
    /// A file holding the token (trailing whitespace ignored), e.g. a
    /// systemd credential.
    File(PathBuf),
    /// An environment variable holding the token.
    Env(String),
}

/// One `[[http.token]]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TokenConfig {
    /// Name written to the audit log for every write made with it.
    pub name: String,
    /// What it may do.
    pub role: Role,
    /// Where its secret is.
    pub source: TokenSource,
}

/// The HTTP listener (REST, WebSocket, metrics, health, docs).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(try_from = "RawHttpConfig")]
pub struct HttpConfig {
    /// Address and port to listen on. With no tokens configured the API
    /// binds the loopback address of the same family instead.
    pub listen: SocketAddr,
    /// API tokens; empty means no authentication, loopback only.
    pub tokens: Vec<TokenConfig>,
    /// Largest request body (and WebSocket message) accepted, bytes.
    pub max_body_bytes: usize,
    /// Connections served at once; more are answered 503 and closed.
    pub max_connections: usize,
    /// A hard cap on the connections one address (an IPv6 host by its /64)
    /// may hold at once; more from it are answered 503 and closed. Absent:
    /// none, an address shares every free slot, and near the limit the
    /// heaviest address gives way first (`crate::connections::budget`).
    pub max_connections_per_address: Option<usize>,
    /// A connection must send a whole request head within this long (of
    /// its opening, or of the previous answer on a kept-alive connection),
    /// else it is closed: idle and slow connections give their slots back.
    pub header_timeout: Duration,
    /// A connection with no byte read or written for this long is closed
    /// (stream clients are pinged well within it).
    pub idle_timeout: Duration,
    /// A request's body must arrive within this long of its head: slower
    /// clients are answered 408.
    pub read_timeout: Duration,
    /// Kernel send buffer per connection, bytes (0: the system's
    /// autotuning). It bounds how far behind a slow stream client can fall
    /// before it is skipped and told so.
    pub send_buffer_bytes: usize,
    /// Stream messages waiting per WebSocket client before updates are
    /// skipped (and the client told how many).
    pub stream_buffer: usize,
    /// Lease given to setpoints that ask for none (`None`: no lease);
    /// within `[safety] lease_min_ms` to `lease_max_ms`.
    pub lease_default: Option<Duration>,
    /// Host names and addresses the API answers to besides loopback and
    /// the listen address (see [`super::guard`]), normalised.
    pub allowed_hosts: Vec<String>,
    /// Browser origins whose pages may change things and open streams
    /// besides the daemon's own, normalised.
    pub allowed_origins: Vec<String>,
    /// Unknown tokens from one address within a minute that pause it for
    /// a minute (see [`super::throttle`]).
    pub token_guesses: u32,
    /// `[http.tls]`: serve HTTPS only, with these files.
    pub tls: Option<crate::tls::TlsFiles>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        // The raw defaults are valid by construction (tested below).
        match HttpConfig::try_from(RawHttpConfig::default()) {
            Ok(c) => c,
            Err(_) => HttpConfig {
                listen: default_listen(),
                tokens: Vec::new(),
                max_body_bytes: 65_536,
                max_connections: 128,
                max_connections_per_address: None,
                header_timeout: Duration::from_millis(5000),
                idle_timeout: Duration::from_secs(120),
                read_timeout: Duration::from_secs(30),
                send_buffer_bytes: 65_536,
                stream_buffer: 256,
                lease_default: None,
                allowed_hosts: Vec::new(),
                allowed_origins: Vec::new(),
                token_guesses: 10,
                tls: None,
            },
        }
    }
}

fn default_listen() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 8080))
}

/// `[http]` as written, before its values are checked.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct RawHttpConfig {
    listen: SocketAddr,
    token: Vec<RawToken>,
    #[serde(deserialize_with = "max_body_bytes")]
    max_body_bytes: i64,
    #[serde(deserialize_with = "max_connections")]
    max_connections: i64,
    /// Absent: no hard cap (fair shares).
    #[serde(deserialize_with = "max_connections_per_address")]
    max_connections_per_address: Option<i64>,
    #[serde(deserialize_with = "header_timeout_ms")]
    header_timeout_ms: i64,
    #[serde(deserialize_with = "idle_timeout_s")]
    idle_timeout_s: i64,
    #[serde(deserialize_with = "read_timeout_s")]
    read_timeout_s: i64,
    #[serde(deserialize_with = "send_buffer_bytes")]
    send_buffer_bytes: i64,
    #[serde(deserialize_with = "stream_buffer")]
    stream_buffer: i64,
    /// Moved to `[safety]`: refused here with where it went.
    lease_min_ms: Option<i64>,
    /// Moved to `[safety]`: refused here with where it went.
    lease_max_ms: Option<i64>,
    #[serde(deserialize_with = "lease_default_ms")]
    lease_default_ms: i64,
    allowed_hosts: Vec<String>,
    allowed_origins: Vec<String>,
    #[serde(deserialize_with = "token_guesses")]
    token_guesses: i64,
    tls: Option<crate::tls::TlsFiles>,
}

/// `[http] key` in `min..=max` (or 0, with `or_zero` saying what 0 is),
/// refused at its value's line with the range.
fn field<'de, D: Deserializer<'de>>(
    d: D,
    key: &str,
    (min, max): (i64, i64),
    or_zero: &str,
) -> Result<i64, D::Error> {
    let v = i64::deserialize(d)?;
    if (!or_zero.is_empty() && v == 0) || (min..=max).contains(&v) {
        return Ok(v);
    }
    Err(serde::de::Error::custom(format!(
        "[http] {key} = {v} is out of range: valid {min} to {max}{or_zero}"
    )))
}

fn max_body_bytes<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "max_body_bytes", (256, 16 << 20), "")
}
fn max_connections<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "max_connections", (1, 65_536), "")
}
fn max_connections_per_address<'de, D: Deserializer<'de>>(d: D) -> Result<Option<i64>, D::Error> {
    field(d, "max_connections_per_address", (1, 65_536), "").map(Some)
}
fn header_timeout_ms<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "header_timeout_ms", (100, 600_000), "")
}
fn idle_timeout_s<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "idle_timeout_s", (1, 86_400), "")
}
fn read_timeout_s<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "read_timeout_s", (1, 3_600), "")
}
fn send_buffer_bytes<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(
        d,
        "send_buffer_bytes",
        (4096, 16 << 20),
        " (or 0 for the system's autotuning)",
    )
}
fn stream_buffer<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "stream_buffer", (1, 65_536), "")
}
fn lease_default_ms<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(
        d,
        "lease_default_ms",
        (10, 86_400_000),
        " (or 0 for no default lease)",
    )
}
fn token_guesses<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    field(d, "token_guesses", (1, 1_000_000), "")
}

impl Default for RawHttpConfig {
    fn default() -> Self {
        Self {
            listen: default_listen(),
            token: Vec::new(),
            max_body_bytes: 65_536,
            max_connections: 128,
            max_connections_per_address: None,
            header_timeout_ms: 5000,
            idle_timeout_s: 120,
            read_timeout_s: 30,
            send_buffer_bytes: 65_536,
            stream_buffer: 256,
            lease_min_ms: None,
            lease_max_ms: None,
            lease_default_ms: 0,
            allowed_hosts: Vec::new(),
            allowed_origins: Vec::new(),
            token_guesses: 10,
            tls: None,
        }
    }
}

/// `[[http.token]]` as written.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
struct RawToken {
    name: String,
    role: Role,
    sha256: Option<String>,
    file: Option<PathBuf>,
    env: Option<String>,
}

fn in_range(key: &str, v: i64, min: i64, max: i64) -> Result<i64, String> {
    if (min..=max).contains(&v) {
        Ok(v)
    } else {
        Err(format!(
            "[http] {key} = {v} is out of range: valid {min} to {max}"
        ))
    }
}

fn as_usize(key: &str, v: i64, min: i64, max: i64) -> Result<usize, String> {
    let v = in_range(key, v, min, max)?;
    usize::try_from(v).map_err(|_| format!("[http] {key} = {v} does not fit this machine"))
}

fn ms(v: i64) -> Duration {
    Duration::from_millis(v.unsigned_abs())
}

impl TryFrom<RawHttpConfig> for HttpConfig {
    type Error = String;

    fn try_from(raw: RawHttpConfig) -> Result<Self, String> {
        let max_body_bytes = as_usize("max_body_bytes", raw.max_body_bytes, 256, 16 << 20)?;
        let max_connections = as_usize("max_connections", raw.max_connections, 1, 65_536)?;
        let max_connections_per_address = match raw.max_connections_per_address {
            None => None,
            Some(v) => Some(
                as_usize(
                    "max_connections_per_address",
                    v,
                    1,
                    i64::try_from(max_connections).unwrap_or(i64::MAX),
                )
                .map_err(|e| format!("{e} (at most max_connections)"))?,
            ),
        };
        let header_timeout_ms = in_range("header_timeout_ms", raw.header_timeout_ms, 100, 600_000)?;
        let idle_timeout_s = in_range("idle_timeout_s", raw.idle_timeout_s, 1, 86_400)?;
        let read_timeout_s = in_range("read_timeout_s", raw.read_timeout_s, 1, 3_600)?;
        let send_buffer_bytes = if raw.send_buffer_bytes == 0 {
            0
        } else {
            as_usize("send_buffer_bytes", raw.send_buffer_bytes, 4096, 16 << 20)
                .map_err(|e| format!("{e} (or 0 for the system's autotuning)"))?
        };
        let stream_buffer = as_usize("stream_buffer", raw.stream_buffer, 1, 65_536)?;
        for (key, given) in [
            ("lease_min_ms", raw.lease_min_ms),
            ("lease_max_ms", raw.lease_max_ms),
        ] {
            if given.is_some() {
                return Err(format!(
                    "[http] {key} has moved to [safety] {key}: the bounds of a lease are the control core's, the same for every face"
                ));
            }
        }
        // Within the lease bounds of [safety]: checked with the whole file.
        let lease_default = if raw.lease_default_ms == 0 {
            None
        } else {
            let v = in_range("lease_default_ms", raw.lease_default_ms, 10, 86_400_000)
                .map_err(|e| format!("{e} (or 0 for no default lease)"))?;
            Some(ms(v))
        };
        let mut tokens: Vec<TokenConfig> = Vec::with_capacity(raw.token.len());
        for t in raw.token {
            let token = TokenConfig::try_from(t)?;
            if tokens.iter().any(|other| other.name == token.name) {
                return Err(format!(
                    "[[http.token]] name \"{}\" is used twice: names must be unique (they identify writers in the audit log)",
                    token.name
                ));
            }
            tokens.push(token);
        }
        Ok(HttpConfig {
            listen: raw.listen,
            tokens,
            max_body_bytes,
            max_connections,
            max_connections_per_address,
            header_timeout: ms(header_timeout_ms),
            idle_timeout: Duration::from_secs(idle_timeout_s.unsigned_abs()),
            read_timeout: Duration::from_secs(read_timeout_s.unsigned_abs()),
            send_buffer_bytes,
            stream_buffer,
            lease_default,
            allowed_hosts: raw
                .allowed_hosts
                .iter()
                .map(|h| super::origins::parse_allowed_host(h))
                .collect::<Result<_, _>>()?,
            allowed_origins: raw
                .allowed_origins
                .iter()
                .map(|o| super::origins::parse_allowed_origin(o))
                .collect::<Result<_, _>>()?,
            token_guesses: u32::try_from(in_range(
                "token_guesses",
                raw.token_guesses,
                1,
                1_000_000,
            )?)
            .unwrap_or(10),
            tls: raw.tls,
        })
    }
}

impl TryFrom<RawToken> for TokenConfig {
    type Error = String;

    fn try_from(raw: RawToken) -> Result<Self, String> {
        let name = raw.name;
        let name_ok = !name.is_empty()
            && name.len() <= 64
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
        if !name_ok {
            return Err(format!(
                "[[http.token]] name \"{name}\" must be 1 to 64 letters, digits, '-', '_' or '.'"
            ));
        }
        let given: Vec<&str> = [
            raw.sha256.as_ref().map(|_| "sha256"),
            raw.file.as_ref().map(|_| "file"),
            raw.env.as_ref().map(|_| "env"),
        ]
        .into_iter()
        .flatten()
        .collect();
        if given.len() != 1 {
            return Err(format!(
                "[[http.token]] \"{name}\": give exactly one of sha256, file or env (found {})",
                if given.is_empty() {
                    "none".to_string()
                } else {
                    given.join(" and ")
                }
            ));
        }
        let source = match (raw.sha256, raw.file, raw.env) {
            (Some(hex), _, _) => TokenSource::Sha256(parse_sha256(&hex).ok_or_else(|| {
                format!(
                    "[[http.token]] \"{name}\": sha256 must be 64 hexadecimal digits (the output of `printf %s TOKEN | sha256sum`)"
                )
            })?),
            (_, Some(path), _) => TokenSource::File(path),
            (_, _, Some(var)) if !var.is_empty() => TokenSource::Env(var),
            _ => {
                return Err(format!(
                    "[[http.token]] \"{name}\": env must name an environment variable"
                ));
            }
        };
        Ok(TokenConfig {
            name,
            role: raw.role,
            source,
        })
    }
}

/// 64 hex digits to 32 bytes.
pub fn parse_sha256(hex: &str) -> Option<[u8; 32]> {
    let hex = hex.trim();
    if hex.len() != 64 || !hex.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<HttpConfig, String> {
        #[derive(Deserialize)]
        struct Doc {
            #[serde(default)]
            http: HttpConfig,
        }
        toml::from_str::<Doc>(text)
            .map(|d| d.http)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_are_valid() {
        let c = HttpConfig::try_from(RawHttpConfig::default()).unwrap();
        assert_eq!(c, HttpConfig::default());
        assert!(c.tokens.is_empty());
        assert_eq!(c.lease_default, None);
        assert_eq!(parse("").unwrap(), c);
    }

    #[test]
    fn tokens_need_exactly_one_source() {
        let ok = parse(
            r#"
            [http]
            [[http.token]]
            name = "scada"
            role = "operator"
            sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
            [[http.token]]
            name = "commissioning"
            role = "admin"
            file = "/etc/drivegate/admin.token"
            [[http.token]]
            name = "dashboard"
            role = "viewer"
            env = "DRIVEGATE_DASHBOARD_TOKEN"
            "#,
        )
        .unwrap();
        assert_eq!(ok.tokens.len(), 3);
        assert_eq!(ok.tokens[0].role, Role::Operator);
        assert!(
            matches!(ok.tokens[2].source, TokenSource::Env(ref v) if v == "DRIVEGATE_DASHBOARD_TOKEN")
        );

        let both =
            parse("[[http.token]]\nname = \"x\"\nrole = \"admin\"\nfile = \"/a\"\nenv = \"B\"\n")
                .unwrap_err();
        assert!(
            both.contains("exactly one of sha256, file or env (found file and env)"),
            "{both}"
        );
        let none = parse("[[http.token]]\nname = \"x\"\nrole = \"admin\"\n").unwrap_err();
        assert!(none.contains("(found none)"), "{none}");
        let bad = parse("[[http.token]]\nname = \"x\"\nrole = \"admin\"\nsha256 = \"abc\"\n")
            .unwrap_err();
        assert!(bad.contains("64 hexadecimal digits"), "{bad}");
        let role =
            parse("[[http.token]]\nname = \"x\"\nrole = \"root\"\nenv = \"T\"\n").unwrap_err();
        assert!(role.contains("viewer") && role.contains("admin"), "{role}");
        let twice = parse(
            "[[http.token]]\nname = \"x\"\nrole = \"admin\"\nenv = \"A\"\n[[http.token]]\nname = \"x\"\nrole = \"viewer\"\nenv = \"B\"\n",
        )
        .unwrap_err();
        assert!(twice.contains("used twice"), "{twice}");
    }

    #[test]
    fn limits_are_checked_with_their_range() {
        let e = parse("[http]\nmax_body_bytes = 10\n").unwrap_err();
        assert!(
            e.contains("max_body_bytes = 10 is out of range: valid 256 to"),
            "{e}"
        );
        let e = parse("[http]\nlease_max_ms = 100\n").unwrap_err();
        assert!(
            e.contains("[http] lease_max_ms has moved to [safety] lease_max_ms"),
            "{e}"
        );
        let e = parse("[http]\nlease_default_ms = 5\n").unwrap_err();
        assert!(e.contains("or 0 for no default lease"), "{e}");
        let e = parse("[http]\nsend_buffer_bytes = 100\n").unwrap_err();
        assert!(e.contains("autotuning"), "{e}");
        let e = parse("[http]\nmax_conections = 5\n").unwrap_err();
        assert!(e.contains("max_conections"), "{e}");
        let e =
            parse("[http]\nmax_connections = 8\nmax_connections_per_address = 9\n").unwrap_err();
        assert!(
            e.contains("max_connections_per_address = 9 is out of range: valid 1 to 8"),
            "{e}"
        );
        let e = parse("[http]\nheader_timeout_ms = 10\n").unwrap_err();
        assert!(e.contains("valid 100 to 600000"), "{e}");
        // No hard cap unless one is set: addresses share the free slots.
        let c = parse("[http]\nmax_connections = 10\n").unwrap();
        assert_eq!(c.max_connections_per_address, None);
        let c = parse("[http]\nmax_connections = 10\nmax_connections_per_address = 3\n").unwrap();
        assert_eq!(c.max_connections_per_address, Some(3));
        let c = parse("[http]\nlease_default_ms = 500\nsend_buffer_bytes = 0\n").unwrap();
        assert_eq!(c.lease_default, Some(Duration::from_millis(500)));
        assert_eq!(c.send_buffer_bytes, 0);
    }

    #[test]
    fn the_documented_token_examples_are_valid() {
        let reference = include_str!("../../config/drivegate.toml");
        let examples: Vec<&str> = reference
            .lines()
            .skip_while(|l| *l != "# [[http.token]]")
            .take_while(|l| l.starts_with('#'))
            .map(|l| l.trim_start_matches('#').trim_start())
            .collect();
        let c = parse(&examples.join("\n")).unwrap();
        let roles: Vec<Role> = c.tokens.iter().map(|t| t.role).collect();
        assert_eq!(roles, [Role::Viewer, Role::Operator, Role::Admin]);
    }

    #[test]
    fn sha256_hex() {
        let d = parse_sha256("9F86D081884C7D659A2FEAA0C55AD015A3BF4F1B2B0B822CD15D6C15B0F00A08")
            .unwrap();
        assert_eq!(d[0], 0x9f);
        assert_eq!(d[31], 0x08);
        assert!(
            parse_sha256("zz86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08")
                .is_none()
        );
    }
}
