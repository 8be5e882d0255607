//! Certificates as the core sees them: who may trust a refused OPC UA
//! client, remove a trusted one or renew the server's own certificate
//! (`Operation::Certificates`, admin), the audit line of each, and the
//! alarm of a certificate that expires within [`EXPIRY_WARNING_DAYS`].
//!
//! The files are the daemon's: it attaches a [`CertificateStore`] (the
//! OPC UA directory of Part 12, the TLS listeners' files) as it attaches
//! its reloader, and the core asks it. A face asks the core
//! ([`crate::control::Control::certificates`], `certificate_action`) and
//! renders the answer.

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

use tokio_util::sync::CancellationToken;

use super::alarms::{AlarmKey, AlarmKind, Alarms, Raise};
use super::caller::Caller;
use super::outcome::Refusal;
use super::policy::Operation;
use super::{audit, rules};
use crate::certificate::CertificateInfo;

/// A certificate that expires within this many days raises an alarm.
pub const EXPIRY_WARNING_DAYS: i64 = 30;

/// How often the certificates are looked at for their expiry (and after
/// every change made through the core).
const EXPIRY_CHECK: Duration = Duration::from_secs(3600);

/// What a certificate is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Place {
    /// The OPC UA server's own (`own/cert.der`).
    OpcUaServer,
    /// An OPC UA client application trusted (`trusted/certs`).
    OpcUaTrusted,
    /// An OPC UA client application refused (`rejected/certs`).
    OpcUaRejected,
    /// An OPC UA user certificate trusted, or the CA of such.
    OpcUaUser,
    /// A CA of OPC UA application certificates (`issuers/certs`).
    OpcUaIssuer,
    /// The Modbus/TCP Security listener's own.
    ModbusTls,
    /// A CA whose client certificates Modbus/TCP Security accepts.
    ModbusTlsClientCa,
    /// The HTTPS listener's own.
    Https,
    /// A CA whose client certificates HTTPS accepts.
    HttpsClientCa,
}

impl Place {
    /// Stable name for the API.
    pub fn name(self) -> &'static str {
        match self {
            Place::OpcUaServer => "opcua-server",
            Place::OpcUaTrusted => "opcua-trusted",
            Place::OpcUaRejected => "opcua-rejected",
            Place::OpcUaUser => "opcua-user",
            Place::OpcUaIssuer => "opcua-issuer",
            Place::ModbusTls => "modbus-tls",
            Place::ModbusTlsClientCa => "modbus-tls-client-ca",
            Place::Https => "https",
            Place::HttpsClientCa => "https-client-ca",
        }
    }

    /// In words, as the subject of a sentence.
    pub fn words(self) -> &'static str {
        match self {
            Place::OpcUaServer => "the OPC UA server's certificate",
            Place::OpcUaTrusted => "the trusted OPC UA client",
            Place::OpcUaRejected => "the refused OPC UA client",
            Place::OpcUaUser => "the OPC UA user certificate",
            Place::OpcUaIssuer => "the OPC UA issuer",
            Place::ModbusTls => "the Modbus/TCP Security certificate",
            Place::ModbusTlsClientCa => "the Modbus/TCP Security client CA",
            Place::Https => "the HTTPS certificate",
            Place::HttpsClientCa => "the HTTPS client CA",
        }
    }
}

/// A certificate where it is kept.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Held {
    /// What it is for.
    pub place: Place,
    /// Its file.
    pub file: PathBuf,
    /// What it says.
    pub info: CertificateInfo,
}

/// Every certificate the daemon holds, and what it could not read.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Listing {
    /// The certificates, by place.
    pub certificates: Vec<Held>,
    /// What is worth knowing beside them (a directory that cannot be
    /// read, a file that holds no certificate), in words.
    pub notes: Vec<String>,
}

/// A change of who is trusted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Trust the refused OPC UA client with this SHA-1 thumbprint.
    Trust(String),
    /// Remove the trusted OPC UA client with this thumbprint (it is then
    /// refused, and listed as such).
    Remove(String),
    /// Make the OPC UA server a new self-signed certificate.
    Renew,
}

impl Action {
    /// In the audit log's words.
    pub fn words(&self) -> &'static str {
        match self {
            Action::Trust(_) => "trusted",
            Action::Remove(_) => "removed",
            Action::Renew => "renewed",
        }
    }
}

/// Why a certificate could not be changed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CertError {
    /// The caller may not.
    Refused(Refusal),
    /// No certificate with that thumbprint where it would have to be.
    Unknown(String),
    /// The change failed; nothing or only part was done (in words).
    Failed(String),
    /// Nothing to act on (no OPC UA server, the daemon stops).
    Unavailable(String),
}

impl std::fmt::Display for CertError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CertError::Refused(r) => f.write_str(&r.detail),
            CertError::Unknown(why) | CertError::Failed(why) | CertError::Unavailable(why) => {
                f.write_str(why)
            }
        }
    }
}

/// What a change did: in words, and the certificate it concerns now (the
/// new one, for a renewal).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Done {
    /// What was done, in words.
    pub words: String,
    /// The certificate.
    pub certificate: Option<Held>,
}

/// Where the certificates are: the daemon's side.
#[async_trait::async_trait]
pub trait CertificateStore: Send + Sync {
    /// Every certificate (blocking: it reads files).
    fn list(&self) -> Listing;
    /// Carries out `action`.
    async fn act(&self, action: &Action) -> Result<Done, CertError>;
}

/// The core's part: the store attached, if any.
#[derive(Default)]
pub(super) struct Certificates {
    store: Mutex<Option<Arc<dyn CertificateStore>>>,
}

impl Certificates {
    fn store(&self) -> Option<Arc<dyn CertificateStore>> {
        self.store.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Takes `store` from now on, and looks at its certificates' expiry
    /// now and every hour until `stop`.
    pub(super) fn attach(
        &self,
        store: Arc<dyn CertificateStore>,
        alarms: Arc<Alarms>,
        stop: CancellationToken,
    ) {
        *self.store.lock().unwrap_or_else(|p| p.into_inner()) = Some(store.clone());
        if tokio::runtime::Handle::try_current().is_err() {
            return;
        }
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(EXPIRY_CHECK);
            loop {
                tokio::select! {
                    () = stop.cancelled() => return,
                    _ = tick.tick() => {}
                }
                check_expiry(&store, &alarms).await;
            }
        });
    }

    /// Every certificate, for `caller` (an admin).
    pub(super) async fn list(&self, caller: &Caller) -> Result<Listing, CertError> {
        rules::role(caller, Operation::Certificates.needs()).map_err(CertError::Refused)?;
        let store = self.store().ok_or_else(unavailable)?;
        tokio::task::spawn_blocking(move || store.list())
            .await
            .map_err(|e| CertError::Failed(e.to_string()))
    }

    /// Carries out `action` for `caller` (an admin); audited either way,
    /// the expiry alarms looked at again after it.
    pub(super) async fn act(
        &self,
        caller: &Caller,
        action: Action,
        alarms: &Arc<Alarms>,
    ) -> Result<Done, CertError> {
        let by = format!("{} {}", caller.face.name(), caller.who);
        let store = self.store();
        let (subject, thumbprint) = match (&store, &action) {
            (Some(store), Action::Trust(t) | Action::Remove(t)) => {
                let store = store.clone();
                let listing = tokio::task::spawn_blocking(move || store.list())
                    .await
                    .unwrap_or_default();
                let subject = listing
                    .certificates
                    .iter()
                    .find(|h| h.info.thumbprint == *t)
                    .map_or_else(String::new, |h| h.info.subject.clone());
                (subject, t.clone())
            }
            _ => ("the OPC UA server's own".to_string(), String::new()),
        };
        let result = match rules::role(caller, Operation::Certificates.needs()) {
            Err(refusal) => Err(CertError::Refused(refusal)),
            Ok(()) => match &store {
                None => Err(unavailable()),
                Some(store) => store.act(&action).await,
            },
        };
        let thumbprint = match (&result, &action) {
            (Ok(done), Action::Renew) => done
                .certificate
                .as_ref()
                .map_or(thumbprint, |h| h.info.thumbprint.clone()),
            _ => thumbprint,
        };
        let said = result
            .as_ref()
            .map(|d| d.words.clone())
            .map_err(|e| e.to_string());
        audit::certificate(
            &by,
            action.words(),
            &subject,
            &thumbprint,
            said.as_deref().map_err(String::as_str),
        );
        if let Some(store) = &store {
            check_expiry(store, alarms).await;
        }
        result
    }
}

fn unavailable() -> CertError {
    CertError::Unavailable(
        "drivegate holds no certificates to manage yet (it is starting or stopping)".to_string(),
    )
}

/// Raises an alarm for each certificate of `store` that expires within
/// [`EXPIRY_WARNING_DAYS`] (or has), and clears the others'.
async fn check_expiry(store: &Arc<dyn CertificateStore>, alarms: &Arc<Alarms>) {
    let store = store.clone();
    let Ok(listing) = tokio::task::spawn_blocking(move || store.list()).await else {
        return;
    };
    alarms.certificates_expiring(expiring(&listing, SystemTime::now()));
}

/// The alarms `listing` calls for at `now`: one per certificate that
/// expires within [`EXPIRY_WARNING_DAYS`], keyed by its thumbprint. A
/// refused client's certificate raises none (nobody relies on it).
pub fn expiring(listing: &Listing, now: SystemTime) -> Vec<Raise> {
    let mut seen = HashSet::new();
    listing
        .certificates
        .iter()
        .filter(|h| h.place != Place::OpcUaRejected)
        .filter(|h| h.info.days_left(now) < EXPIRY_WARNING_DAYS)
        .filter(|h| seen.insert(h.info.thumbprint.clone()))
        .map(|h| {
            let days = h.info.days_left(now);
            let until = crate::timestamp::rfc3339(h.info.not_after);
            let date = until.get(..10).unwrap_or(&until);
            let when = if days < 0 {
                format!("expired on {date}")
            } else {
                format!("expires on {date}, in {days} days")
            };
            let name = h.info.common_name.as_deref().unwrap_or(&h.info.subject);
            let help = match h.place {
                Place::OpcUaServer => "Renew it on the console's Certificates page (one click; the OPC UA clients then trust the new one), or put a new one in own/cert.der and private/private.pem.",
                Place::OpcUaTrusted | Place::OpcUaUser | Place::OpcUaIssuer => "Ask the client's owner for a new certificate and trust it; connections with this one are refused once it expired.",
                Place::ModbusTls | Place::Https => "Put a new certificate and key in place of the files [http.tls] or [modbus_tcp.tls] names, then reload (systemctl reload drivegate): clients are refused once it expired.",
                Place::ModbusTlsClientCa | Place::HttpsClientCa => "Put the CA's new certificate in place of the file client_ca names and reload: client certificates it signs are refused once it expired.",
                Place::OpcUaRejected => "",
            };
            Raise {
                key: AlarmKey {
                    kind: AlarmKind::CertificateExpiring,
                    bus: format!("certificate {}", h.info.thumbprint),
                    drive: None,
                    code: 0,
                },
                text: format!("{} {name} {when}", h.place.words()),
                help: help.to_string(),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::UNIX_EPOCH;

    fn held(place: Place, thumbprint: &str, days: u64) -> Held {
        Held {
            place,
            file: PathBuf::from(format!("/pki/{thumbprint}.der")),
            info: CertificateInfo {
                subject: format!("CN={thumbprint}"),
                common_name: Some(thumbprint.to_string()),
                issuer: format!("CN={thumbprint}"),
                application_uri: None,
                not_before: UNIX_EPOCH,
                not_after: UNIX_EPOCH + Duration::from_secs(days * 86_400),
                thumbprint: thumbprint.to_string(),
                sha256: String::new(),
                is_ca: false,
            },
        }
    }

    #[test]
    fn certificates_expiring_within_thirty_days_are_alarms_and_refused_ones_are_not() {
        let listing = Listing {
            certificates: vec![
                held(Place::OpcUaServer, "aa", 400),
                held(Place::Https, "bb", 20),
                held(Place::OpcUaRejected, "cc", 5),
                held(Place::OpcUaTrusted, "dd", 0),
            ],
            notes: Vec::new(),
        };
        let now = UNIX_EPOCH + Duration::from_secs(86_400);
        let raised = expiring(&listing, now);
        let keys: Vec<&str> = raised.iter().map(|r| r.key.bus.as_str()).collect();
        assert_eq!(keys, ["certificate bb", "certificate dd"]);
        assert_eq!(
            raised[0].text,
            "the HTTPS certificate bb expires on 1970-01-21, in 19 days"
        );
        assert!(
            raised[1].text.ends_with("expired on 1970-01-01"),
            "{}",
            raised[1].text
        );
        assert!(raised[0].help.contains("reload"));
    }
}
