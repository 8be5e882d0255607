//! The daemon's certificates, for the core's certificate operations
//! (`control::certificates`): the OPC UA server's directory in the layout
//! of Part 12 (`opcua::pki`: its own certificate, the client applications
//! trusted and refused, user certificates and issuers), and the files the
//! HTTPS and Modbus/TCP Security listeners serve, as the running
//! configuration names them.
//!
//! Trusting a refused client moves its file from `rejected/certs` to
//! `trusted/certs`, which the server follows within a second (its next
//! connection is accepted); removing a trusted one moves it back, so it
//! is refused and can be trusted again. Renewing the server's certificate
//! keeps the old one beside it (`cert.der.old`, `private.pem.old`) and
//! restarts the OPC UA face alone, which makes a new one as at its first
//! start: the other faces, the buses and the drives run on.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures_util::future::BoxFuture;

use crate::certificate;
use crate::config::Config;
use crate::config::diff::Face;
use crate::control::Control;
use crate::control::certificates::{
    Action, CertError, CertificateStore, Done, Held, Listing, Place,
};
use crate::opcua::pki::Pki;

/// Restarts one face alone, on its socket (the supervisor's
/// `Running::restart`); what was done, in words.
pub type Restart = Arc<dyn Fn(Face) -> BoxFuture<'static, Result<String, String>> + Send + Sync>;

/// How long a renewal waits for the new certificate (RSA key generation).
const RENEWAL_LIMIT: Duration = Duration::from_secs(120);

/// The certificates of the running daemon.
pub struct Store {
    control: Control,
    /// Restarts the OPC UA server after a renewal.
    restart: Restart,
}

impl Store {
    /// The certificates of the configuration `control` runs with;
    /// `restart` restarts the OPC UA face after a renewal.
    pub fn new(control: Control, restart: Restart) -> Self {
        Store { control, restart }
    }

    fn config(&self) -> Option<Arc<Config>> {
        self.control.follow_config().borrow().clone()
    }

    /// The OPC UA server's directory, if it has one of its own.
    fn pki(&self) -> Result<Pki, CertError> {
        let config = self.config().ok_or_else(|| {
            CertError::Unavailable("drivegate is starting: try again in a moment".to_string())
        })?;
        let section = config.opcua.as_ref().ok_or_else(|| {
            CertError::Unavailable("no OPC UA server is configured ([opcua])".to_string())
        })?;
        section
            .pki_dir(config.safety.state_dir().as_deref())
            .map(Pki::new)
            .ok_or_else(|| {
                CertError::Unavailable(
                    "the OPC UA server has no pki_dir and drivegate no state directory: its certificates are made anew at each start, and nothing can be trusted for good; set [opcua] pki_dir".to_string(),
                )
            })
    }
}

/// Every certificate in the files of `dir`, as `place`.
fn from_dir(listing: &mut Listing, place: Place, dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let mut files: Vec<PathBuf> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    for file in files {
        from_file(listing, place, &file, false);
    }
}

/// The certificates of `file` (the first only, with `leaf`), as `place`.
fn from_file(listing: &mut Listing, place: Place, file: &Path, leaf: bool) {
    let bytes = match std::fs::read(file) {
        Ok(b) => b,
        Err(e) => {
            listing.notes.push(format!("{}: {e}", file.display()));
            return;
        }
    };
    let ders = certificate::ders(&bytes);
    let take = if leaf { 1 } else { ders.len() };
    for der in ders.iter().take(take) {
        match certificate::read(der) {
            Ok(info) => listing.certificates.push(Held {
                place,
                file: file.to_path_buf(),
                info,
            }),
            Err(e) => listing.notes.push(format!("{}: {e}", file.display())),
        }
    }
}

/// The file in `dir` that holds the certificate with `thumbprint`.
fn find(dir: &Path, thumbprint: &str) -> Option<PathBuf> {
    let mut listing = Listing::default();
    from_dir(&mut listing, Place::OpcUaTrusted, dir);
    listing
        .certificates
        .into_iter()
        .find(|h| h.info.thumbprint == thumbprint.to_lowercase())
        .map(|h| h.file)
}

/// Moves `file` into `dir` under its own name (or a free one beside it).
fn move_into(file: &Path, dir: &Path) -> std::io::Result<PathBuf> {
    let name = file.file_name().map_or_else(
        || "certificate.der".into(),
        |n| n.to_string_lossy().into_owned(),
    );
    let mut to = dir.join(&name);
    let mut n = 1;
    while to.exists() {
        to = dir.join(format!("{n}-{name}"));
        n += 1;
    }
    std::fs::rename(file, &to)?;
    Ok(to)
}

/// The certificate at `file`, as `place`.
fn held(place: Place, file: &Path) -> Option<Held> {
    let mut listing = Listing::default();
    from_file(&mut listing, place, file, true);
    listing.certificates.into_iter().next()
}

#[async_trait::async_trait]
impl CertificateStore for Store {
    fn list(&self) -> Listing {
        let mut listing = Listing::default();
        let Some(config) = self.config() else {
            return listing;
        };
        if config.opcua.is_some() {
            match self.pki() {
                Ok(pki) => {
                    from_file(&mut listing, Place::OpcUaServer, &pki.cert_path(), true);
                    from_dir(&mut listing, Place::OpcUaTrusted, &pki.trusted());
                    from_dir(&mut listing, Place::OpcUaRejected, &pki.rejected());
                    from_dir(&mut listing, Place::OpcUaUser, &pki.users_trusted());
                    from_dir(&mut listing, Place::OpcUaIssuer, &pki.issuers());
                }
                Err(e) => listing.notes.push(e.to_string()),
            }
        }
        if let Some(tls) = &config.http.tls {
            from_file(&mut listing, Place::Https, &tls.cert, true);
            if let Some(ca) = &tls.client_ca {
                from_file(&mut listing, Place::HttpsClientCa, ca, false);
            }
        }
        if let Some(tls) = &config.modbus_tcp.tls {
            let files = tls.files();
            from_file(&mut listing, Place::ModbusTls, &files.cert, true);
            if let Some(ca) = &files.client_ca {
                from_file(&mut listing, Place::ModbusTlsClientCa, ca, false);
            }
        }
        listing
    }

    async fn act(&self, action: &Action) -> Result<Done, CertError> {
        let pki = self.pki()?;
        match action {
            Action::Trust(thumbprint) => {
                let file = find(&pki.rejected(), thumbprint).ok_or_else(|| {
                    CertError::Unknown(format!(
                        "no refused OPC UA client has the thumbprint {thumbprint} (in {})",
                        pki.rejected().display()
                    ))
                })?;
                let to = move_into(&file, &pki.trusted()).map_err(|e| {
                    CertError::Failed(format!("cannot move {}: {e}", file.display()))
                })?;
                Ok(Done {
                    words: format!(
                        "trusted ({}): its next connection is accepted, within a second, without a restart",
                        to.display()
                    ),
                    certificate: held(Place::OpcUaTrusted, &to),
                })
            }
            Action::Remove(thumbprint) => {
                let file = find(&pki.trusted(), thumbprint).ok_or_else(|| {
                    CertError::Unknown(format!(
                        "no trusted OPC UA client has the thumbprint {thumbprint} (in {})",
                        pki.trusted().display()
                    ))
                })?;
                let to = move_into(&file, &pki.rejected()).map_err(|e| {
                    CertError::Failed(format!("cannot move {}: {e}", file.display()))
                })?;
                Ok(Done {
                    words: format!(
                        "no longer trusted ({}): its next connection is refused (one open now stays until it closes); it is listed with the refused clients, where it can be trusted again",
                        to.display()
                    ),
                    certificate: held(Place::OpcUaRejected, &to),
                })
            }
            Action::Renew => self.renew(&pki).await,
        }
    }
}

impl Store {
    /// A new self-signed certificate for the OPC UA server: the old one
    /// and its key kept as `.old`, the face restarted to make and serve
    /// the new one.
    async fn renew(&self, pki: &Pki) -> Result<Done, CertError> {
        let old = held(Place::OpcUaServer, &pki.cert_path());
        let aside = |p: PathBuf| {
            let mut to = p.clone().into_os_string();
            to.push(".old");
            std::fs::rename(&p, PathBuf::from(to))
        };
        aside(pki.cert_path())
            .and_then(|()| aside(pki.key_path()))
            .map_err(|e| {
                CertError::Failed(format!(
                    "cannot set the old certificate aside in {}: {e}",
                    pki.root().display()
                ))
            })?;
        let restarted = (self.restart)(Face::OpcUa)
            .await
            .map_err(CertError::Failed)?;
        // The face makes its certificate as it starts (RSA key generation).
        let start = tokio::time::Instant::now();
        let new = loop {
            if let Some(new) = held(Place::OpcUaServer, &pki.cert_path())
                && old
                    .as_ref()
                    .is_none_or(|o| o.info.thumbprint != new.info.thumbprint)
            {
                break new;
            }
            if start.elapsed() > RENEWAL_LIMIT {
                return Err(CertError::Failed(format!(
                    "the OPC UA server did not make its new certificate within {} s ({restarted}): see the log",
                    RENEWAL_LIMIT.as_secs()
                )));
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        Ok(Done {
            words: format!(
                "renewed: the OPC UA server serves the new certificate (thumbprint {}); clients must trust it once, as the first; the old one is kept as {}.old ({restarted})",
                new.info.thumbprint,
                pki.cert_path().display()
            ),
            certificate: Some(new),
        })
    }
}
