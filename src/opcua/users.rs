//! Who a session is: the face's `AuthManager`.
//!
//! - **User name and password**: the name of an `[[http.token]]` and that
//!   token (one credential store for every face), checked against the
//!   running configuration at each activation, in constant time; its role
//!   is read again at each request, so a reload that changes or removes
//!   the token applies from the next one.
//! - **X.509 user certificate**: trusted when it is in `trusted/certs`, or
//!   signed by a CA in `issuers/certs`; its role is the extension
//!   1.3.6.1.4.1.50316.802.1, as for Modbus/TCP Security.
//! - **Anonymous**: a viewer, or refused (`[opcua] anonymous`).
//!
//! A name that gets wrong passwords `[http] token_guesses` times within a
//! minute is refused until the minute is over, as the API pauses an
//! address. The crate hands a client only `BadIdentityTokenRejected`; the
//! reason is logged, and counted.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use opcua::crypto::{SecurityPolicy, Thumbprint};
use opcua::server::ServerEndpoint;
use opcua::server::address_space::AccessLevel;
use opcua::server::authenticator::{
    AuthManager, CoreServerPermissions, Password, UserToken, user_pass_security_policy_id,
};
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};
use sha2::{Digest, Sha256};
use tokio::sync::watch;

use super::pki::{Pki, read_certs};
use super::spec::{Source, path_of, split_drive_path, variable_at};
use super::user_cert::Stash;
use crate::config::http::{TokenConfig, TokenSource};
use crate::config::opcua::Anonymous;
use crate::config::{Config, ROLE_EXTENSION, Role};
use crate::control::policy::{Operation, for_settings};
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
    stash: Arc<Stash>,
    /// Certificate users by token: CN and role from the certificate.
    certificates: Mutex<HashMap<String, (Arc<str>, Role)>>,
    guesses: Mutex<Guesses>,
    metrics: Arc<Metrics>,
}

/// The prefix of a user-name session's token.
const USER: &str = "user:";
/// The prefix of a certificate session's token.
const CERTIFICATE: &str = "x509:";

impl Users {
    /// The authenticator of a face started with `anonymous`, reading the
    /// tokens from `config` (the running configuration) and the trust of
    /// user certificates from `pki`.
    pub fn new(
        config: watch::Receiver<Option<Arc<Config>>>,
        anonymous: Anonymous,
        pki: Pki,
        stash: Arc<Stash>,
        metrics: Arc<Metrics>,
    ) -> Self {
        Users {
            config,
            anonymous,
            pki,
            stash,
            certificates: Mutex::new(HashMap::new()),
            guesses: Mutex::new(Guesses::default()),
            metrics,
        }
    }

    fn tokens(&self) -> (Vec<TokenConfig>, u32) {
        match self.config.borrow().as_ref() {
            Some(c) => (c.http.tokens.clone(), c.http.token_guesses),
            None => (Vec::new(), 10),
        }
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
                .tokens()
                .0
                .iter()
                .find(|t| t.name == name)
                .map(|t| t.role);
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

    fn check_password(&self, user: &str, password: &str) -> Result<(), String> {
        let (tokens, guesses) = self.tokens();
        let now = Instant::now();
        if self
            .guesses
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .paused(user, guesses, now)
        {
            return Err(format!(
                "user \"{user}\": {guesses} wrong tokens within a minute; refused until the minute is over"
            ));
        }
        let presented: [u8; 32] = Sha256::digest(password.as_bytes()).into();
        let found = tokens
            .iter()
            .find(|t| t.name == user)
            .map(|t| digest_of(t).is_some_and(|d| constant_time_eq(&d, &presented)));
        match found {
            Some(true) => Ok(()),
            found => {
                self.guesses
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .failed(user, now);
                Err(match found {
                    None => format!("user \"{user}\": no [[http.token]] has this name"),
                    _ => format!("user \"{user}\": wrong token"),
                })
            }
        }
    }

    fn check_certificate(&self, thumbprint: &Thumbprint) -> Result<(Arc<str>, Role), String> {
        let der = self
            .stash
            .take(thumbprint)
            .ok_or("the user certificate was not seen with its token")?;
        self.trusted(&der)?;
        let identity = crate::tls::peer_identity(&der.clone().into(), ROLE_EXTENSION)?;
        let cn: Arc<str> = identity
            .common_name
            .unwrap_or_else(|| thumbprint.as_hex_string())
            .into();
        let role = match identity.extension {
            None => {
                return Err(format!(
                    "the user certificate of {cn} has no role extension {ROLE_EXTENSION}"
                ));
            }
            Some(Err(e)) => return Err(format!("the user certificate of {cn}: {e}")),
            Some(Ok(name)) => Role::from_name(&name).ok_or_else(|| {
                format!(
                    "the user certificate of {cn} names the role \"{name}\": expected viewer, operator or admin"
                )
            })?,
        };
        Ok((cn, role))
    }

    /// Trusted: listed in `trusted/certs`, or signed by a CA of
    /// `issuers/certs` (checked as the TLS listeners check a client's).
    fn trusted(&self, der: &[u8]) -> Result<(), String> {
        if read_certs(&self.pki.trusted()).iter().any(|c| c == der) {
            return Ok(());
        }
        let mut roots = rustls::RootCertStore::empty();
        for ca in read_certs(&self.pki.issuers()) {
            let _ = roots.add(rustls::pki_types::CertificateDer::from(ca));
        }
        if roots.is_empty() {
            return Err(format!(
                "the user certificate is not in {} and {} holds no CA",
                self.pki.trusted().display(),
                self.pki.issuers().display()
            ));
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
            .map(|_| ())
            .map_err(|e| format!("the user certificate is not trusted: {e}"))
    }

    fn refused(&self, kind: &'static str, why: &str) -> Error {
        self.metrics.opcua().signed_in(kind, false);
        tracing::warn!(target: "drivegate::opcua", "OPC UA sign-in refused: {why}");
        Error::new(StatusCode::BadIdentityTokenRejected, why.to_string())
    }
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

/// Wrong passwords per user name over the last minute. Pure, time passed
/// in; at most [`Guesses::NAMES`] names are followed (the oldest go).
#[derive(Debug, Default)]
struct Guesses {
    failures: HashMap<String, VecDeque<Instant>>,
}

impl Guesses {
    const WINDOW: Duration = Duration::from_secs(60);
    const NAMES: usize = 1024;

    fn recent(&mut self, user: &str, now: Instant) -> usize {
        let Some(times) = self.failures.get_mut(user) else {
            return 0;
        };
        while times
            .front()
            .is_some_and(|t| now.duration_since(*t) >= Self::WINDOW)
        {
            times.pop_front();
        }
        times.len()
    }

    fn paused(&mut self, user: &str, allowed: u32, now: Instant) -> bool {
        self.recent(user, now) >= usize::try_from(allowed).unwrap_or(usize::MAX)
    }

    fn failed(&mut self, user: &str, now: Instant) {
        if self.failures.len() >= Self::NAMES && !self.failures.contains_key(user) {
            self.failures.retain(|_, t| {
                t.back()
                    .is_some_and(|last| now.duration_since(*last) < Self::WINDOW)
            });
            if self.failures.len() >= Self::NAMES {
                return;
            }
        }
        self.failures
            .entry(user.to_string())
            .or_default()
            .push_back(now);
    }
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
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), Error> {
        match self.anonymous {
            Anonymous::Viewer => {
                self.metrics.opcua().signed_in("anonymous", true);
                Ok(())
            }
            Anonymous::None => Err(self.refused(
                "anonymous",
                "an anonymous session ([opcua] anonymous = \"none\")",
            )),
        }
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        match self.check_password(username, password.get()) {
            Ok(()) => {
                self.metrics.opcua().signed_in("user", true);
                tracing::info!(target: "drivegate::opcua", user = username, "OPC UA sign-in");
                Ok(UserToken(format!("{USER}{username}")))
            }
            Err(why) => Err(self.refused("user", &why)),
        }
    }

    async fn authenticate_x509_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        signing_thumbprint: &Thumbprint,
    ) -> Result<UserToken, Error> {
        match self.check_certificate(signing_thumbprint) {
            Ok((cn, role)) => {
                let token = format!("{CERTIFICATE}{}", signing_thumbprint.as_hex_string());
                self.metrics.opcua().signed_in("certificate", true);
                tracing::info!(target: "drivegate::opcua", user = %cn, role = role.name(), "OPC UA sign-in with a user certificate");
                let mut certificates = self.certificates.lock().unwrap_or_else(|p| p.into_inner());
                if certificates.len() >= 1024 {
                    certificates.clear();
                }
                certificates.insert(token.clone(), (cn, role));
                Ok(UserToken(token))
            }
            Err(why) => Err(self.refused("certificate", &why)),
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
    fn a_name_is_paused_after_its_guesses_for_a_minute() {
        let mut g = Guesses::default();
        let t0 = Instant::now();
        for i in 0..3 {
            assert!(!g.paused("alice", 3, t0), "after {i}");
            g.failed("alice", t0 + Duration::from_secs(i));
        }
        assert!(g.paused("alice", 3, t0 + Duration::from_secs(10)));
        assert!(!g.paused("bob", 3, t0 + Duration::from_secs(10)));
        assert!(!g.paused("alice", 3, t0 + Duration::from_secs(61)));
    }

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
