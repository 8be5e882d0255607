//! Who a session is: the face's `AuthManager`. It checks what only the
//! face can (a password against its token's digest, a user certificate's
//! trust) and asks the core for the role ([`crate::control::identity`]):
//!
//! - **User name and password**: the name of an `[[http.token]]` and that
//!   token (one credential store for every face), checked against the
//!   running configuration at each activation, in constant time; its role
//!   is read again at each request, so a reload that changes or removes
//!   the token applies from the next one. The password must not cross the
//!   network in clear: on an endpoint without security it is accepted only
//!   encrypted with the server's key (the user token policy says so); a
//!   clear one is refused and audited.
//! - **X.509 user certificate**: trusted when it is in
//!   `users/trusted/certs` (its role then from `[[opcua.user_certificate]]`
//!   only) or signed by `[opcua] user_ca` (its role from
//!   `[[opcua.user_certificate]]`, else its role extension). An
//!   application certificate trusted in `trusted/certs` opens a secure
//!   channel and makes no user.
//! - **Anonymous**: a viewer, or refused (`[opcua] anonymous`).
//!
//! Failed sign-ins are counted per client address and per address and user
//! name ([`crate::control::throttle`]): a name that gets `[http]
//! token_guesses` wrong passwords within a minute from one address is
//! refused from that address until the minute is over, and the address
//! after three times as many, whatever the names; the same name still signs
//! in from another address. The crate hands a client only
//! `BadIdentityTokenRejected`; the reason is logged, and counted.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use async_trait::async_trait;
use opcua::crypto::{SecurityPolicy, Thumbprint};
use opcua::server::ServerEndpoint;
use opcua::server::address_space::AccessLevel;
use opcua::server::authenticator::{
    AuthManager, CoreServerPermissions, Password, SignIn, UserToken, user_pass_security_policy_id,
};
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};
use sha2::{Digest, Sha256};
use tokio::sync::watch;

use super::pki::{Pki, read_certs};
use super::spec::{Source, path_of, split_drive_path, variable_at};
use crate::config::http::{TokenConfig, TokenSource};
use crate::config::opcua::Anonymous;
use crate::config::{Config, OpcUaConfig, Role};
use crate::control::Face;
use crate::control::identity::{Credential, Vouched, hex, identify};
use crate::control::policy::{Operation, for_settings};
use crate::control::throttle::SignIns;
use crate::metrics::Metrics;

/// Who a session is, as the core needs it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    /// The token's name, the certificate's CN, or `anonymous`.
    pub user: Arc<str>,
    /// Its role now; `None`: it has none any more (its token was removed).
    pub role: Option<Role>,
}

/// The face's authenticator.
pub struct Users {
    config: watch::Receiver<Option<Arc<Config>>>,
    anonymous: Anonymous,
    pki: Pki,
    /// `[opcua] user_ca`.
    user_ca: Option<PathBuf>,
    /// Certificate users by token: who and role, decided at sign-in.
    certificates: Mutex<HashMap<String, (Arc<str>, Role)>>,
    guesses: Mutex<SignIns>,
    metrics: Arc<Metrics>,
}

/// The prefix of a user-name session's token.
const USER: &str = "user:";
/// The prefix of a certificate session's token.
const CERTIFICATE: &str = "x509:";

/// The client's address of `sign_in` (unspecified when the crate did not
/// know it).
fn address(sign_in: &SignIn) -> IpAddr {
    sign_in
        .peer_address
        .map_or(IpAddr::V4(Ipv4Addr::UNSPECIFIED), |a| a.ip())
}

/// The client of `sign_in` in words, for the log.
fn client(sign_in: &SignIn) -> String {
    sign_in
        .peer_address
        .map_or_else(|| "an unknown address".to_string(), |a| a.to_string())
}

impl Users {
    /// The authenticator of a face started with `section`, reading the
    /// tokens and roles from `config` (the running configuration) and the
    /// trust of user certificates from `pki`.
    pub fn new(
        config: watch::Receiver<Option<Arc<Config>>>,
        section: &OpcUaConfig,
        pki: Pki,
        metrics: Arc<Metrics>,
    ) -> Self {
        let allowed = config
            .borrow()
            .as_ref()
            .map_or(10, |c| c.http.token_guesses);
        if section.user_ca.is_none() && !read_certs(&pki.issuers()).is_empty() {
            tracing::warn!(
                target: "drivegate::opcua",
                dir = %pki.issuers().display(),
                "OPC UA: the CAs in issuers/certs no longer make users: name the CA of user certificates in [opcua] user_ca"
            );
        }
        Users {
            config,
            anonymous: section.anonymous,
            pki,
            user_ca: section.user_ca.clone(),
            certificates: Mutex::new(HashMap::new()),
            guesses: Mutex::new(SignIns::new(allowed)),
            metrics,
        }
    }

    fn config(&self) -> Option<Arc<Config>> {
        self.config.borrow().clone()
    }

    fn tokens(&self) -> Vec<TokenConfig> {
        self.config()
            .map(|c| c.http.tokens.clone())
            .unwrap_or_default()
    }

    /// Who the session with `token` is, now.
    pub fn identity(&self, token: &UserToken) -> Identity {
        if token.is_anonymous() {
            return Identity {
                user: "anonymous".into(),
                role: (self.anonymous == Anonymous::Viewer).then_some(Role::Viewer),
            };
        }
        if let Some(name) = token.0.strip_prefix(USER) {
            let role = self
                .config()
                .and_then(|c| identify(&c, Face::OpcUa, Credential::Token(name)).ok())
                .map(|i| i.role);
            return Identity {
                user: name.into(),
                role,
            };
        }
        let certificates = self.certificates.lock().unwrap_or_else(|p| p.into_inner());
        match certificates.get(&token.0) {
            Some((cn, role)) => Identity {
                user: cn.clone(),
                role: Some(*role),
            },
            None => Identity {
                user: token.0.as_str().into(),
                role: None,
            },
        }
    }

    /// Refuses while `name` (or the whole address) is paused for guessing.
    fn not_paused(&self, sign_in: &SignIn, name: &str) -> Result<(), String> {
        let guesses = self.guesses.lock().unwrap_or_else(|p| p.into_inner());
        guesses
            .check(address(sign_in), Some(name), Instant::now())
            .map_err(|wait| {
                format!(
                    "\"{name}\" from {}: too many failed sign-ins from this address within a \
                     minute; refused for {} s more (other addresses are not concerned)",
                    client(sign_in),
                    wait.as_secs().max(1)
                )
            })
    }

    fn failed(&self, sign_in: &SignIn, name: &str) {
        self.guesses
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .failed(address(sign_in), Some(name), Instant::now());
    }

    fn check_password(&self, user: &str, password: &str, sign_in: &SignIn) -> Result<(), String> {
        self.not_paused(sign_in, user)?;
        let presented: [u8; 32] = Sha256::digest(password.as_bytes()).into();
        let found = self
            .tokens()
            .iter()
            .find(|t| t.name == user)
            .map(|t| digest_of(t).is_some_and(|d| constant_time_eq(&d, &presented)));
        match found {
            Some(true) => Ok(()),
            found => {
                self.failed(sign_in, user);
                Err(match found {
                    None => format!("user \"{user}\": no [[http.token]] has this name"),
                    _ => format!("user \"{user}\": wrong token"),
                })
            }
        }
    }

    /// The identity of the certificate of `sign_in`: trusted as a user
    /// (see [`Users::vouched`]), its role from the core.
    fn check_certificate(&self, sign_in: &SignIn) -> Result<(Arc<str>, Role), String> {
        let data = sign_in
            .certificate
            .as_ref()
            .and_then(|c| c.value.as_deref())
            .ok_or("the user token carries no certificate")?;
        let der = leaf(data)?;
        let name = hex(&crate::tls::sha1_fingerprint(der));
        self.not_paused(sign_in, &name)?;
        let vouched = self
            .vouched(der)
            .inspect_err(|_| self.failed(sign_in, &name))?;
        let config = self.config().ok_or("no configuration")?;
        let identity = identify(
            &config,
            Face::OpcUa,
            Credential::Certificate { der, vouched },
        )?;
        Ok((identity.who, identity.role))
    }

    /// What vouches for a user certificate: listed in
    /// `users/trusted/certs` (compared by content, whatever the file's
    /// name), or signed by `user_ca` (checked as the TLS listeners check a
    /// client's). An application certificate in `trusted/certs` is no
    /// user.
    fn vouched(&self, der: &[u8]) -> Result<Vouched, String> {
        if read_certs(&self.pki.users_trusted())
            .iter()
            .any(|c| c == der)
        {
            return Ok(Vouched::TrustList);
        }
        let Some(ca) = &self.user_ca else {
            return Err(format!(
                "the user certificate (SHA-1 {}) is not in {} and [opcua] user_ca is not set",
                hex(&crate::tls::sha1_fingerprint(der)),
                self.pki.users_trusted().display(),
            ));
        };
        let mut roots = rustls::RootCertStore::empty();
        for c in crate::tls::load_certificates(ca, "[opcua] user_ca").map_err(|e| e.to_string())? {
            let _ = roots.add(c);
        }
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let verifier =
            rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .build()
                .map_err(|e| e.to_string())?;
        verifier
            .verify_client_cert(
                &rustls::pki_types::CertificateDer::from(der.to_vec()),
                &[],
                rustls::pki_types::UnixTime::now(),
            )
            .map(|_| Vouched::RoleCa)
            .map_err(|e| {
                format!(
                    "the user certificate (SHA-1 {}) is not in {} nor signed by user_ca: {e}",
                    hex(&crate::tls::sha1_fingerprint(der)),
                    self.pki.users_trusted().display(),
                )
            })
    }

    fn refused(&self, kind: &'static str, sign_in: &SignIn, why: &str) -> Error {
        self.metrics.opcua().signed_in(kind, false);
        crate::control::audit::sign_in_refused("opcua", &client(sign_in), why);
        Error::new(StatusCode::BadIdentityTokenRejected, why.to_string())
    }
}

/// The first certificate of an X.509 token's data (a client may send its
/// chain after it).
fn leaf(data: &[u8]) -> Result<&[u8], String> {
    let (rest, _) = x509_parser::parse_x509_certificate(data)
        .map_err(|e| format!("the user certificate is not valid X.509: {e}"))?;
    Ok(&data[..data.len() - rest.len()])
}

/// The digest of a token's secret: kept in the file, or read now from its
/// file or environment variable (so a rotated secret applies at once).
fn digest_of(token: &TokenConfig) -> Option<[u8; 32]> {
    let secret = match &token.source {
        TokenSource::Sha256(d) => return Some(*d),
        TokenSource::File(path) => std::fs::read_to_string(path).ok()?,
        TokenSource::Env(var) => std::env::var(var).ok()?,
    };
    let secret = secret.trim();
    (!secret.is_empty()).then(|| Sha256::digest(secret.as_bytes()).into())
}

/// Compares two digests in time independent of where they differ.
fn constant_time_eq(a: &[u8; 32], b: &[u8; 32]) -> bool {
    let diff = a
        .iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y));
    std::hint::black_box(diff) == 0
}

fn policy(
    id: impl Into<UAString>,
    token_type: UserTokenType,
    security_policy_uri: UAString,
) -> UserTokenPolicy {
    UserTokenPolicy {
        policy_id: id.into(),
        token_type,
        issued_token_type: UAString::null(),
        issuer_endpoint_url: UAString::null(),
        security_policy_uri,
    }
}

#[async_trait]
impl AuthManager for Users {
    async fn authenticate_anonymous_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        sign_in: &SignIn,
    ) -> Result<(), Error> {
        match self.anonymous {
            Anonymous::Viewer => {
                self.metrics.opcua().signed_in("anonymous", true);
                Ok(())
            }
            Anonymous::None => Err(self.refused(
                "anonymous",
                sign_in,
                "an anonymous session ([opcua] anonymous = \"none\")",
            )),
        }
    }

    async fn authenticate_username_identity_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
        sign_in: &SignIn,
    ) -> Result<UserToken, Error> {
        if !sign_in.secret_protected() {
            return Err(self.refused(
                "user",
                sign_in,
                &format!(
                    "user \"{username}\": its password came in clear (a channel without \
                     encryption, the token not encrypted with the server's key); refused unread: \
                     the client must follow the endpoint's user token policy, or use an \
                     encrypted endpoint"
                ),
            ));
        }
        match self.check_password(username, password.get(), sign_in) {
            Ok(()) => {
                self.metrics.opcua().signed_in("user", true);
                tracing::info!(target: "drivegate::opcua", user = username, client = %client(sign_in), "OPC UA sign-in");
                Ok(UserToken(format!("{USER}{username}")))
            }
            Err(why) => Err(self.refused("user", sign_in, &why)),
        }
    }

    async fn authenticate_x509_identity_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        signing_thumbprint: &Thumbprint,
        sign_in: &SignIn,
    ) -> Result<UserToken, Error> {
        match self.check_certificate(sign_in) {
            Ok((cn, role)) => {
                let token = format!("{CERTIFICATE}{}", signing_thumbprint.as_hex_string());
                self.metrics.opcua().signed_in("certificate", true);
                tracing::info!(target: "drivegate::opcua", user = %cn, role = role.name(), client = %client(sign_in), "OPC UA sign-in with a user certificate");
                let mut certificates = self.certificates.lock().unwrap_or_else(|p| p.into_inner());
                if certificates.len() >= 1024 {
                    certificates.clear();
                }
                certificates.insert(token.clone(), (cn, role));
                Ok(UserToken(token))
            }
            Err(why) => Err(self.refused("certificate", sign_in, &why)),
        }
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut out = Vec::new();
        if self.anonymous == Anonymous::Viewer {
            out.push(policy(
                "anonymous",
                UserTokenType::Anonymous,
                UAString::null(),
            ));
        }
        // On an endpoint without security the password is still encrypted,
        // with the endpoint's password policy.
        let password_policy = if endpoint.security_policy() == SecurityPolicy::None {
            UAString::from(endpoint.password_security_policy().to_uri())
        } else {
            UAString::null()
        };
        out.push(policy(
            user_pass_security_policy_id(endpoint),
            UserTokenType::UserName,
            password_policy,
        ));
        out.push(policy(
            "x509",
            UserTokenType::Certificate,
            UAString::from(SecurityPolicy::Basic256Sha256.to_uri()),
        ));
        out
    }

    /// What `UserAccessLevel` shows: the setpoints writable for operators,
    /// the settings for admins, nothing for viewers (the core still
    /// decides every write).
    fn effective_user_access_level(
        &self,
        token: &UserToken,
        user_access_level: AccessLevel,
        node_id: &NodeId,
    ) -> AccessLevel {
        let needed = match path_of(node_id)
            .and_then(split_drive_path)
            .and_then(|(_, rest)| variable_at(rest))
            .map(|v| v.source)
        {
            Some(Source::Setting(_)) => for_settings(),
            _ => Operation::Lease.needs(),
        };
        match self.identity(token).role {
            Some(role) if role.allows(needed) => user_access_level,
            _ => user_access_level - AccessLevel::CURRENT_WRITE,
        }
    }

    fn core_permissions(&self, token: &UserToken) -> CoreServerPermissions {
        CoreServerPermissions {
            read_diagnostics: self.identity(token).role == Some(Role::Admin),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digests_of_hashes_files_and_variables() {
        let token = |source| TokenConfig {
            name: "panel".into(),
            role: Role::Operator,
            source,
        };
        let expected: [u8; 32] = Sha256::digest(b"s3cret").into();
        assert_eq!(
            digest_of(&token(TokenSource::Sha256(expected))),
            Some(expected)
        );
        let file =
            std::env::temp_dir().join(format!("drivegate-opcua-token-{}", std::process::id()));
        std::fs::write(&file, "s3cret\n").unwrap();
        assert_eq!(
            digest_of(&token(TokenSource::File(file.clone()))),
            Some(expected)
        );
        std::fs::write(&file, "").unwrap();
        assert_eq!(digest_of(&token(TokenSource::File(file.clone()))), None);
        let _ = std::fs::remove_file(&file);
        assert_eq!(
            digest_of(&token(TokenSource::Env(
                "DRIVEGATE_NO_SUCH_VARIABLE".into()
            ))),
            None
        );
        assert!(constant_time_eq(&expected, &expected));
        assert!(!constant_time_eq(&expected, &[0; 32]));
    }
}
