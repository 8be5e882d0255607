//! `[opcua]` section: the OPC UA server face (`crate::opcua`): where it
//! listens, its certificates' directory, the security of its endpoints,
//! what an anonymous session may do, and how long a silent client's
//! session (and the lease of its setpoints) lasts. Plain data. Absent: no
//! OPC UA.

use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;
use serde::de::{self, Deserializer};
use toml::Spanned;

use super::safety::StopAction;
use super::values::int_in;

/// The OPC UA server.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OpcUaConfig {
    /// Address and port of `opc.tcp` (4840 is OPC UA's port).
    pub listen: SocketAddr,
    /// The certificates, in the layout of OPC UA Part 12 (`own/`,
    /// `private/`, `trusted/certs`, `rejected/certs`, `issuers/certs`);
    /// absent: `opcua-pki` in `[safety] state_dir` ([`Self::pki_dir`]).
    pub pki_dir: Option<PathBuf>,
    /// The endpoints: one per security policy, each signing and
    /// encrypting, and `none` for one without either. Read it with
    /// [`OpcUaConfig::endpoints`].
    security: Endpoints,
    /// Lets the `none` endpoint listen on an address other than loopback.
    pub allow_none_on_network: bool,
    /// What a session without a user may do: read (`viewer`) or nothing
    /// (`none`: anonymous sessions are refused).
    #[serde(deserialize_with = "anonymous")]
    pub anonymous: Anonymous,
    /// The longest session timeout a client may ask for, ms: a client
    /// silent for its session's timeout has its session closed, and the
    /// leases its setpoints and modes took end with `comm_loss_action`.
    #[serde(deserialize_with = "int_in::<_, _, 1000, 60_000>")]
    pub session_timeout_max_ms: u64,
    /// What the end of such a lease sends: `zero-speed` (the default),
    /// `brake`, or `none` (the end is shown and audited, nothing is sent).
    pub comm_loss_action: StopAction,
    /// Sessions at once. An address shares every free one; near the limit
    /// the heaviest address is refused, and once full a quiet session of
    /// the heaviest is closed for a client of a lighter address
    /// (`crate::connections::budget`).
    #[serde(deserialize_with = "int_in::<_, _, 1, 1000>")]
    pub max_sessions: usize,
    /// A hard cap on the sessions of one client address; absent: none.
    pub max_sessions_per_address: Option<super::modbus_tcp::ConnectionCount>,
    /// Connections (each a secure channel) at once, shared like the
    /// sessions.
    #[serde(deserialize_with = "int_in::<_, _, 1, 4096>")]
    pub max_connections: usize,
    /// A hard cap on the connections of one client address; absent: none.
    pub max_connections_per_address: Option<super::modbus_tcp::ConnectionCount>,
}

impl Default for OpcUaConfig {
    fn default() -> Self {
        OpcUaConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 4840)),
            pki_dir: None,
            security: Endpoints(Spanned::new(
                0..0,
                Security::DEFAULT
                    .iter()
                    .map(|s| Spanned::new(0..0, *s))
                    .collect(),
            )),
            allow_none_on_network: false,
            anonymous: Anonymous::Viewer,
            session_timeout_max_ms: 30_000,
            comm_loss_action: StopAction::ZeroSpeed,
            max_sessions: 20,
            max_sessions_per_address: None,
            max_connections: 64,
            max_connections_per_address: None,
        }
    }
}

/// The security of one endpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Security {
    /// No signature, no encryption (passwords are still encrypted).
    None,
    /// Basic256Sha256, signed and encrypted.
    Basic256sha256,
    /// Aes128_Sha256_RsaOaep, signed and encrypted.
    Aes128Sha256Rsaoaep,
    /// Aes256_Sha256_RsaPss, signed and encrypted.
    Aes256Sha256Rsapss,
}

impl Security {
    /// The endpoints of a section that does not say.
    pub const DEFAULT: [Security; 3] = [
        Security::Basic256sha256,
        Security::Aes128Sha256Rsaoaep,
        Security::Aes256Sha256Rsapss,
    ];

    /// Its name in the file.
    pub fn name(self) -> &'static str {
        match self {
            Security::None => "none",
            Security::Basic256sha256 => "basic256sha256",
            Security::Aes128Sha256Rsaoaep => "aes128-sha256-rsaoaep",
            Security::Aes256Sha256Rsapss => "aes256-sha256-rsapss",
        }
    }
}

impl fmt::Display for Security {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// `security` with where the file says each (for errors pointing at
/// them); compared and shown by its values only.
#[derive(Clone, Deserialize)]
#[serde(transparent)]
struct Endpoints(Spanned<Vec<Spanned<Security>>>);

impl Endpoints {
    fn values(&self) -> Vec<Security> {
        self.0.get_ref().iter().map(|s| *s.get_ref()).collect()
    }
}

impl PartialEq for Endpoints {
    fn eq(&self, other: &Self) -> bool {
        self.values() == other.values()
    }
}

impl fmt::Debug for Endpoints {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.values().fmt(f)
    }
}

/// What an anonymous session may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Anonymous {
    /// Nothing: anonymous sessions are refused.
    None,
    /// Read and subscribe, as a viewer.
    Viewer,
}

/// `anonymous`: `viewer` or `none`; a role that could move a motor is
/// refused with why.
fn anonymous<'de, D: Deserializer<'de>>(d: D) -> Result<Anonymous, D::Error> {
    match String::deserialize(d)?.as_str() {
        "viewer" => Ok(Anonymous::Viewer),
        "none" => Ok(Anonymous::None),
        role @ ("operator" | "admin") => Err(de::Error::custom(format!(
            "anonymous = \"{role}\" would let anyone who reaches the port move the motors: \
             anonymous sessions may be \"viewer\" (read only) or \"none\"; sign in with an \
             [[http.token]]'s name and token, or a user certificate, to write"
        ))),
        other => Err(de::Error::custom(format!(
            "anonymous = \"{other}\": expected \"viewer\" or \"none\""
        ))),
    }
}

impl OpcUaConfig {
    /// Where the certificates are: `pki_dir`, else `opcua-pki` in the
    /// state directory `state_dir` (`[safety]`'s), else none (the face
    /// then keeps them in a temporary directory for the process's life).
    pub fn pki_dir(&self, state_dir: Option<&Path>) -> Option<PathBuf> {
        self.pki_dir
            .clone()
            .or_else(|| state_dir.map(|d| d.join("opcua-pki")))
    }

    /// The security of each endpoint, in the order of the file.
    pub fn endpoints(&self) -> Vec<Security> {
        self.security.values()
    }

    /// The longest session timeout a client may ask for.
    pub fn session_timeout_max(&self) -> Duration {
        Duration::from_millis(self.session_timeout_max_ms)
    }

    /// Checks across keys: at least one endpoint, none twice, and `none`
    /// only on a loopback listener unless `allow_none_on_network`.
    pub(super) fn validate(&self) -> Result<(), (std::ops::Range<usize>, String)> {
        let security = self.security.0.get_ref();
        if security.is_empty() {
            return Err((
                self.security.0.span(),
                "[opcua] security is empty: list at least one of \"basic256sha256\", \
                 \"aes128-sha256-rsaoaep\", \"aes256-sha256-rsapss\" (or \"none\")"
                    .to_string(),
            ));
        }
        for (i, s) in security.iter().enumerate() {
            if security[..i].iter().any(|o| o.get_ref() == s.get_ref()) {
                return Err((
                    s.span(),
                    format!("[opcua] security lists \"{}\" twice", s.get_ref()),
                ));
            }
            if *s.get_ref() == Security::None
                && !self.listen.ip().is_loopback()
                && !self.allow_none_on_network
            {
                return Err((
                    s.span(),
                    format!(
                        "[opcua] security \"none\" on {}: an endpoint without signature or \
                         encryption lets anyone on the network read and change what a session \
                         sends; it is for loopback listeners (a local tool). Remove \"none\", \
                         listen on 127.0.0.1, or set allow_none_on_network = true",
                        self.listen
                    ),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    fn parse(section: &str) -> Result<Config, String> {
        Config::parse(&format!("[opcua]\n{section}"), "test.toml").map_err(|e| e.to_string())
    }

    #[test]
    fn the_defaults_are_the_issue_of_a_plant_on_loopback() {
        let c = parse("").unwrap().opcua.unwrap();
        assert_eq!(c, OpcUaConfig::default());
        assert_eq!(c.listen.to_string(), "127.0.0.1:4840");
        assert_eq!(c.endpoints(), Security::DEFAULT);
        assert_eq!(c.anonymous, Anonymous::Viewer);
        assert_eq!(c.session_timeout_max(), Duration::from_secs(30));
        assert_eq!(
            c.pki_dir(Some(Path::new("/var/lib/drivegate"))),
            Some(PathBuf::from("/var/lib/drivegate/opcua-pki"))
        );
        assert_eq!(c.pki_dir(None), None);
        assert!(Config::parse("", "t").unwrap().opcua.is_none());
    }

    #[test]
    fn none_is_for_loopback_unless_allowed() {
        assert!(parse("security = [\"none\", \"basic256sha256\"]").is_ok());
        let e = parse("listen = \"0.0.0.0:4840\"\nsecurity = [\"basic256sha256\", \"none\"]")
            .unwrap_err();
        assert!(e.contains("test.toml:3:"), "{e}");
        assert!(e.contains("allow_none_on_network"), "{e}");
        assert!(
            parse("listen = \"0.0.0.0:4840\"\nsecurity = [\"none\"]\nallow_none_on_network = true")
                .is_ok()
        );
    }

    #[test]
    fn mistakes_are_named_where_they_are() {
        let e = parse("security = []").unwrap_err();
        assert!(
            e.contains("at least one") && e.contains("test.toml:2:"),
            "{e}"
        );
        let e = parse("security = [\"basic256sha256\", \"basic256sha256\"]").unwrap_err();
        assert!(e.contains("twice") && e.contains("test.toml:2:"), "{e}");
        let e = parse("security = [\"basic128rsa15\"]").unwrap_err();
        assert!(e.contains("test.toml:2:"), "{e}");
        let e = parse("anonymous = \"operator\"").unwrap_err();
        assert!(
            e.contains("move the motors") && e.contains("test.toml:2:"),
            "{e}"
        );
        let e = parse("session_timeout_max_ms = 500").unwrap_err();
        assert!(e.contains("valid 1000 to 60000"), "{e}");
        let e = parse("comm_loss_action = \"stop\"").unwrap_err();
        assert!(e.contains("test.toml:2:"), "{e}");
    }
}
