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
    /// A CA (PEM, one or more certificates) that vouches for users: a user
    /// certificate it signed is trusted, and its role extension
    /// ([`super::ROLE_EXTENSION`]) is its role, as for Modbus/TCP Security.
    pub user_ca: Option<PathBuf>,
    /// User certificates' roles by thumbprint or subject (a certificate
    /// trusted as a user: in `users/trusted/certs`, or signed by `user_ca`).
    #[serde(rename = "user_certificate")]
    pub user_certificates: Vec<UserCertificate>,
    /// Subscriptions of one session.
    #[serde(deserialize_with = "int_in::<_, _, 1, 100>")]
    pub max_subscriptions_per_session: usize,
    /// Monitored items of one session.
    #[serde(deserialize_with = "int_in::<_, _, 1, 100_000>")]
    pub max_monitored_items_per_session: usize,
    /// Monitored items of all sessions.
    #[serde(deserialize_with = "int_in::<_, _, 1, 1_000_000>")]
    pub max_monitored_items: usize,
    /// The queue of a monitored item of a value, at most (the stack's
    /// default, 10).
    #[serde(deserialize_with = "int_in::<_, _, 1, 10_000>")]
    pub max_queue_size: usize,
    /// The queue of a monitored item of events, at most: a
    /// `ConditionRefresh` sends every retained alarm at once.
    #[serde(deserialize_with = "int_in::<_, _, 1, 10_000>")]
    pub max_event_queue_size: usize,
    /// The queues of every monitored item added together, at most: the
    /// notifications that can wait for clients' Publish requests at once.
    #[serde(deserialize_with = "int_in::<_, _, 100, 10_000_000>")]
    pub max_queued_values: usize,
}

/// A role given to a user certificate (`[[opcua.user_certificate]]`): by
/// its thumbprint, or by its subject.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(try_from = "UserCertificateKeys")]
pub struct UserCertificate {
    /// The certificate's SHA-1 or SHA-256 fingerprint in hex (colons
    /// allowed), as `openssl x509 -fingerprint` prints it.
    #[serde(default, deserialize_with = "thumbprint")]
    pub thumbprint: Option<Vec<u8>>,
    /// Its subject, `CN=olivia, O=plant`: every attribute named must be
    /// the certificate's, in any order.
    pub subject: Option<Vec<(String, String)>>,
    /// The role.
    pub role: super::Role,
}

/// `[[opcua.user_certificate]]` as written, before the check that it names
/// a certificate one way.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct UserCertificateKeys {
    #[serde(default, deserialize_with = "thumbprint")]
    thumbprint: Option<Vec<u8>>,
    #[serde(default, deserialize_with = "subject")]
    subject: Option<Vec<(String, String)>>,
    role: super::Role,
}

impl TryFrom<UserCertificateKeys> for UserCertificate {
    type Error = String;

    fn try_from(k: UserCertificateKeys) -> Result<Self, String> {
        if k.thumbprint.is_some() == k.subject.is_some() {
            return Err(
                "[[opcua.user_certificate]]: give either thumbprint or subject (not both, not \
                 neither), with a role"
                    .to_string(),
            );
        }
        Ok(UserCertificate {
            thumbprint: k.thumbprint,
            subject: k.subject,
            role: k.role,
        })
    }
}

impl UserCertificate {
    /// Whether this entry names the certificate with `sha1` and `sha256`
    /// fingerprints and `subject` (its attributes, short names).
    pub fn names(&self, sha1: &[u8], sha256: &[u8], subject: &[(String, String)]) -> bool {
        if let Some(t) = &self.thumbprint {
            return t == sha1 || t == sha256;
        }
        self.subject.as_ref().is_some_and(|wanted| {
            wanted.iter().all(|w| {
                subject
                    .iter()
                    .any(|s| s.0.eq_ignore_ascii_case(&w.0) && s.1 == w.1)
            })
        })
    }
}

/// A fingerprint in hex, colons allowed: 20 bytes (SHA-1) or 32 (SHA-256).
fn thumbprint<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Vec<u8>>, D::Error> {
    let text = String::deserialize(d)?;
    let hex: String = text
        .trim()
        .trim_start_matches("SHA1 Fingerprint=")
        .trim_start_matches("sha256 Fingerprint=")
        .chars()
        .filter(|c| *c != ':')
        .collect();
    let bytes = (0..hex.len())
        .step_by(2)
        .map(|i| {
            hex.get(i..i + 2)
                .and_then(|b| u8::from_str_radix(b, 16).ok())
        })
        .collect::<Option<Vec<u8>>>();
    match bytes {
        Some(b) if hex.len().is_multiple_of(2) && (b.len() == 20 || b.len() == 32) => Ok(Some(b)),
        _ => Err(de::Error::custom(format!(
            "thumbprint \"{text}\": expected the certificate's SHA-1 or SHA-256 fingerprint in \
             hex (40 or 64 digits, colons allowed), as `openssl x509 -noout -fingerprint -sha1 \
             -in cert.pem` prints it"
        ))),
    }
}

/// A subject, `CN=olivia, O=plant`: attribute=value pairs.
fn subject<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Vec<(String, String)>>, D::Error> {
    let text = String::deserialize(d)?;
    let pairs = text
        .split([',', '/'])
        .map(str::trim)
        .filter(|p| !p.is_empty())
        .map(|p| {
            let (k, v) = p.split_once('=')?;
            let (k, v) = (k.trim(), v.trim());
            (!k.is_empty() && !v.is_empty()).then(|| (k.to_string(), v.to_string()))
        })
        .collect::<Option<Vec<_>>>();
    match pairs {
        Some(p) if !p.is_empty() => Ok(Some(p)),
        _ => Err(de::Error::custom(format!(
            "subject \"{text}\": expected attribute=value pairs, e.g. \"CN=olivia, O=plant\""
        ))),
    }
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
            user_ca: None,
            user_certificates: Vec::new(),
            max_subscriptions_per_session: 10,
            max_monitored_items_per_session: 1000,
            max_monitored_items: 10_000,
            max_queue_size: 10,
            max_event_queue_size: 1000,
            max_queued_values: 100_000,
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

    #[test]
    fn the_caps_have_the_stacks_defaults_and_their_ranges() {
        let c = parse("").unwrap().opcua.unwrap();
        assert_eq!(
            (
                c.max_subscriptions_per_session,
                c.max_monitored_items_per_session,
                c.max_monitored_items,
                c.max_queue_size,
                c.max_event_queue_size,
                c.max_queued_values
            ),
            (10, 1000, 10_000, 10, 1000, 100_000)
        );
        for (key, bad, range) in [
            ("max_subscriptions_per_session", "0", "valid 1 to 100"),
            (
                "max_monitored_items_per_session",
                "100001",
                "valid 1 to 100000",
            ),
            ("max_monitored_items", "0", "valid 1 to 1000000"),
            ("max_queue_size", "0", "valid 1 to 10000"),
            ("max_event_queue_size", "10001", "valid 1 to 10000"),
            ("max_queued_values", "99", "valid 100 to 10000000"),
        ] {
            let e = parse(&format!("{key} = {bad}")).unwrap_err();
            assert!(
                e.contains(range) && e.contains("test.toml:2:"),
                "{key}: {e}"
            );
        }
        assert_eq!(
            parse("max_queue_size = 100")
                .unwrap()
                .opcua
                .unwrap()
                .max_queue_size,
            100
        );
    }

    #[test]
    fn user_certificates_are_named_by_thumbprint_or_subject() {
        let toml = |entry: &str| {
            Config::parse(
                &format!(
                    "[opcua]\nuser_ca = \"/etc/ca.pem\"\n[[opcua.user_certificate]]\n{entry}\n"
                ),
                "test.toml",
            )
            .map_err(|e| e.to_string())
        };
        let c = toml("thumbprint = \"SHA1 Fingerprint=3A:7F:00:11:22:33:44:55:66:77:88:99:AA:BB:CC:DD:EE:FF:01:C2\"\nrole = \"operator\"")
            .unwrap()
            .opcua
            .unwrap();
        let u = &c.user_certificates[0];
        assert_eq!(u.role, crate::config::Role::Operator);
        let sha1 = u.thumbprint.clone().unwrap();
        assert_eq!((sha1.len(), sha1[0], sha1[19]), (20, 0x3a, 0xc2));
        assert!(u.names(&sha1, &[0; 32], &[]));
        let c = toml("subject = \"O=plant, CN=vera\"\nrole = \"viewer\"")
            .unwrap()
            .opcua
            .unwrap();
        let u = &c.user_certificates[0];
        let subject = |pairs: &[(&str, &str)]| -> Vec<(String, String)> {
            pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect()
        };
        assert!(u.names(
            &[0; 20],
            &[0; 32],
            &subject(&[("CN", "vera"), ("O", "plant"), ("C", "FR")])
        ));
        assert!(!u.names(&[0; 20], &[0; 32], &subject(&[("CN", "vera")])));
        assert!(!u.names(
            &[0; 20],
            &[0; 32],
            &subject(&[("CN", "vera2"), ("O", "plant")])
        ));
        let e = toml("thumbprint = \"3A:7F\"\nrole = \"admin\"").unwrap_err();
        assert!(
            e.contains("40 or 64 digits") && e.contains("test.toml:4:"),
            "{e}"
        );
        let e = toml("role = \"admin\"").unwrap_err();
        assert!(e.contains("either thumbprint or subject"), "{e}");
        let e = toml("subject = \"vera\"\nrole = \"admin\"").unwrap_err();
        assert!(e.contains("attribute=value"), "{e}");
    }
}
