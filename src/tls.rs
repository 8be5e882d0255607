//! TLS for the faces (HTTPS and Modbus/TCP Security, and the MQTT face's
//! connection to its broker): certificate chains,
//! keys and client CAs read from PEM files, server configurations built
//! with rustls (ring, TLS 1.2 and 1.3, no OpenSSL), and reloading them
//! without touching the connections already open.
//!
//! A leaf: nothing here knows a face, a role or the configuration file; a
//! face gives it file names and gets a [`Reloadable`] configuration whose
//! [`Reloadable::current`] every new handshake takes. A reload that fails
//! keeps the configuration in use: a renewal that went wrong must not take
//! the gateway off the network.

use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::{RootCertStore, ServerConfig};
use serde::Deserialize;

/// The files of a TLS listener, as configured (`[http.tls]`, and the
/// common part of `[modbus_tcp.tls]`).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// The server's certificate chain, PEM, leaf first.
    pub cert: PathBuf,
    /// Its private key, PEM (PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
    /// The CA(s) whose client certificates are accepted, PEM; absent: no
    /// client certificate is asked for.
    #[serde(default)]
    pub client_ca: Option<PathBuf>,
}

/// Why a TLS configuration cannot be built: which file, and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TlsError {
    /// A file cannot be read or holds no PEM block of the kind needed.
    #[error("{what} {path}: {reason}")]
    File {
        /// What the file should hold ("certificate", "private key", "client CA").
        what: &'static str,
        /// The file.
        path: String,
        /// Why it is not usable.
        reason: String,
    },
    /// The key and the certificate do not go together, or rustls refused them.
    #[error("certificate {cert} with key {key}: {reason}")]
    Pair {
        /// The certificate file.
        cert: String,
        /// The key file.
        key: String,
        /// Why.
        reason: String,
    },
    /// The configuration needs a client CA and has none.
    #[error("{0}")]
    Missing(String),
}

/// The protocol suite and versions every listener uses.
fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

fn file_error(what: &'static str, path: &Path, reason: impl ToString) -> TlsError {
    TlsError::File {
        what,
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// Reads a PEM certificate chain (leaf first); at least one certificate.
pub fn load_certificates(
    path: &Path,
    what: &'static str,
) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let bytes = std::fs::read(path).map_err(|e| file_error(what, path, e))?;
    let certs = CertificateDer::pem_slice_iter(&bytes)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| file_error(what, path, format!("not valid PEM: {e}")))?;
    if certs.is_empty() {
        return Err(file_error(
            what,
            path,
            "holds no \"-----BEGIN CERTIFICATE-----\" block",
        ));
    }
    for (i, cert) in certs.iter().enumerate() {
        x509_parser::parse_x509_certificate(cert).map_err(|e| {
            file_error(
                what,
                path,
                format!("certificate {} is not valid X.509: {e}", i + 1),
            )
        })?;
    }
    Ok(certs)
}

/// Reads a PEM private key.
pub fn load_key(path: &Path) -> Result<PrivateKeyDer<'static>, TlsError> {
    let bytes = std::fs::read(path).map_err(|e| file_error("private key", path, e))?;
    PrivateKeyDer::from_pem_slice(&bytes).map_err(|e| {
        file_error(
            "private key",
            path,
            match e {
                rustls::pki_types::pem::Error::NoItemsFound => {
                    "holds no private key (\"-----BEGIN PRIVATE KEY-----\", RSA or EC)".to_string()
                }
                other => format!("not a usable PEM private key: {other}"),
            },
        )
    })
}

/// Whether a listener asks its clients for certificates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClientAuth {
    /// Only if `client_ca` is set, then required (HTTPS: mutual TLS is
    /// optional in the configuration).
    IfConfigured,
    /// Always (Modbus/TCP Security: `client_ca` is required).
    Required,
}

/// Builds the server configuration of `files`; `alpn` lists the
/// application protocols offered (empty: none).
pub fn server_config(
    files: &TlsFiles,
    client_auth: ClientAuth,
    alpn: &[&[u8]],
) -> Result<Arc<ServerConfig>, TlsError> {
    let chain = load_certificates(&files.cert, "certificate")?;
    let key = load_key(&files.key)?;
    let builder = ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13, &rustls::version::TLS12])
        .map_err(|e| TlsError::Missing(format!("TLS versions: {e}")))?;
    let builder = match (&files.client_ca, client_auth) {
        (Some(ca), _) => {
            let mut roots = RootCertStore::empty();
            for cert in load_certificates(ca, "client CA")? {
                roots
                    .add(cert)
                    .map_err(|e| file_error("client CA", ca, format!("not a usable CA: {e}")))?;
            }
            let verifier = WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider())
                .build()
                .map_err(|e| file_error("client CA", ca, e))?;
            builder.with_client_cert_verifier(verifier)
        }
        (None, ClientAuth::Required) => {
            return Err(TlsError::Missing(
                "client_ca is required: clients are authenticated by their certificates"
                    .to_string(),
            ));
        }
        (None, ClientAuth::IfConfigured) => builder.with_no_client_auth(),
    };
    let mut config = builder
        .with_single_cert(chain, key)
        .map_err(|e| TlsError::Pair {
            cert: files.cert.display().to_string(),
            key: files.key.display().to_string(),
            reason: match e {
                rustls::Error::InconsistentKeys(_) => {
                    "the private key does not belong to the certificate".to_string()
                }
                other => other.to_string(),
            },
        })?;
    config.alpn_protocols = alpn.iter().map(|p| p.to_vec()).collect();
    Ok(Arc::new(config))
}

/// Where Debian keeps the system's trusted CAs, for a client configured
/// without a CA of its own.
pub const SYSTEM_CAS: &str = "/etc/ssl/certs/ca-certificates.crt";

/// Builds a client configuration (the MQTT face's to its broker): the
/// server is trusted when signed by `ca` (absent: the system's CAs), and
/// `identity` (certificate chain, key) is shown when the server asks.
pub fn client_config(
    ca: Option<&Path>,
    identity: Option<(&Path, &Path)>,
) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    let ca_path = ca.unwrap_or(Path::new(SYSTEM_CAS));
    let mut roots = RootCertStore::empty();
    for cert in load_certificates(ca_path, "CA")? {
        roots
            .add(cert)
            .map_err(|e| file_error("CA", ca_path, format!("not a usable CA: {e}")))?;
    }
    let builder = rustls::ClientConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13, &rustls::version::TLS12])
        .map_err(|e| TlsError::Missing(format!("TLS versions: {e}")))?
        .with_root_certificates(roots);
    let config = match identity {
        None => builder.with_no_client_auth(),
        Some((cert, key)) => {
            let chain = load_certificates(cert, "client certificate")?;
            let private = load_key(key)?;
            builder
                .with_client_auth_cert(chain, private)
                .map_err(|e| TlsError::Pair {
                    cert: cert.display().to_string(),
                    key: key.display().to_string(),
                    reason: match e {
                        rustls::Error::InconsistentKeys(_) => {
                            "the private key does not belong to the certificate".to_string()
                        }
                        other => other.to_string(),
                    },
                })?
        }
    };
    Ok(Arc::new(config))
}

/// A server configuration that can be reloaded from its files while the
/// listener runs: each handshake takes the one current when it starts.
#[derive(Debug)]
pub struct Reloadable {
    files: TlsFiles,
    client_auth: ClientAuth,
    alpn: Vec<Vec<u8>>,
    current: RwLock<Arc<ServerConfig>>,
}

impl Reloadable {
    /// Loads `files` (an error names the file and why).
    pub fn load(
        files: TlsFiles,
        client_auth: ClientAuth,
        alpn: &[&[u8]],
    ) -> Result<Self, TlsError> {
        let current = server_config(&files, client_auth, alpn)?;
        Ok(Reloadable {
            files,
            client_auth,
            alpn: alpn.iter().map(|p| p.to_vec()).collect(),
            current: RwLock::new(current),
        })
    }

    /// The configuration for a new handshake.
    pub fn current(&self) -> Arc<ServerConfig> {
        self.current
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Reads the files again; on error the configuration in use stays.
    pub fn reload(&self) -> Result<(), TlsError> {
        let alpn: Vec<&[u8]> = self.alpn.iter().map(Vec::as_slice).collect();
        let next = server_config(&self.files, self.client_auth, &alpn)?;
        *self.current.write().unwrap_or_else(|p| p.into_inner()) = next;
        Ok(())
    }

    /// The files it is loaded from.
    pub fn files(&self) -> &TlsFiles {
        &self.files
    }
}

/// Reloads `config` on every SIGHUP (`systemctl reload drivegate`) until
/// `shutdown` fires, logging the outcome (`face` names the listener) and
/// telling `counted` whether it worked. Connections already open keep the
/// configuration they started with.
pub fn reload_on_hangup(
    config: Arc<Reloadable>,
    face: &'static str,
    counted: impl Fn(bool) + Send + 'static,
    shutdown: tokio_util::sync::CancellationToken,
) -> std::io::Result<tokio::task::JoinHandle<()>> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut hangups = signal(SignalKind::hangup())?;
    Ok(tokio::spawn(async move {
        loop {
            tokio::select! {
                received = hangups.recv() => if received.is_none() { break },
                () = shutdown.cancelled() => break,
            }
            match config.reload() {
                Ok(()) => {
                    counted(true);
                    tracing::info!(
                        face,
                        cert = %config.files().cert.display(),
                        "TLS certificate reloaded: new connections use it, open ones carry on"
                    );
                }
                Err(e) => {
                    counted(false);
                    tracing::error!(
                        face,
                        "TLS certificate not reloaded, the previous one stays in use: {e}"
                    );
                }
            }
        }
    }))
}

/// What a client certificate says about its holder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PeerIdentity {
    /// The subject's common name (CN), if any.
    pub common_name: Option<String>,
    /// The value of the extension asked for, if present.
    pub extension: Option<Result<String, String>>,
    /// The subject's attributes, by their short names (`CN`, `O`, ...) or
    /// dotted OIDs, in the certificate's order.
    pub subject: Vec<(String, String)>,
}

/// The SHA-1 fingerprint of a certificate (DER): what OPC UA calls its
/// thumbprint, and `openssl x509 -fingerprint` prints.
pub fn sha1_fingerprint(der: &[u8]) -> [u8; 20] {
    use sha1::Digest;
    sha1::Sha1::digest(der).into()
}

/// Reads the subject CN of `cert` and the UTF8String in its extension
/// `oid` (dotted, e.g. "1.3.6.1.4.1.50316.802.1"); an extension that is
/// not a UTF8String is `Some(Err(why))`.
pub fn peer_identity(cert: &CertificateDer<'_>, oid: &str) -> Result<PeerIdentity, String> {
    let (_, parsed) = x509_parser::parse_x509_certificate(cert)
        .map_err(|e| format!("the client certificate is not valid X.509: {e}"))?;
    let common_name = parsed
        .subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .map(str::to_string);
    let extension = parsed
        .extensions()
        .iter()
        .find(|e| e.oid.to_id_string() == oid)
        .map(|e| utf8_string(e.value));
    let subject = parsed
        .subject()
        .iter_attributes()
        .map(|a| {
            let name = x509_parser::objects::oid2abbrev(
                a.attr_type(),
                x509_parser::objects::oid_registry(),
            )
            .map(str::to_string)
            .unwrap_or_else(|_| a.attr_type().to_id_string());
            (name, a.as_str().unwrap_or_default().to_string())
        })
        .collect();
    Ok(PeerIdentity {
        common_name,
        extension,
        subject,
    })
}

/// The text of a DER-encoded ASN.1 UTF8String (tag 12).
fn utf8_string(der: &[u8]) -> Result<String, String> {
    let (&tag, rest) = der.split_first().ok_or("the extension is empty")?;
    if tag != 0x0c {
        return Err(format!(
            "the extension is not an ASN.1 UTF8String (tag 0x{tag:02x}, expected 0x0c)"
        ));
    }
    let (&first, rest) = rest.split_first().ok_or("the extension is truncated")?;
    let (len, body) = if first < 0x80 {
        (usize::from(first), rest)
    } else {
        let n = usize::from(first & 0x7f);
        if n == 0 || n > 2 || rest.len() < n {
            return Err("the extension's length is malformed".to_string());
        }
        let len = rest[..n]
            .iter()
            .fold(0usize, |acc, b| (acc << 8) | usize::from(*b));
        (len, &rest[n..])
    };
    if body.len() != len {
        return Err("the extension's length does not match its content".to_string());
    }
    String::from_utf8(body.to_vec()).map_err(|_| "the extension is not valid UTF-8".to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utf8_strings_are_read_and_others_refused() {
        assert_eq!(utf8_string(b"\x0c\x08operator").unwrap(), "operator");
        assert_eq!(utf8_string(b"\x0c\x00").unwrap(), "");
        let long = [b"\x0c\x81\x80".as_slice(), &[b'a'; 128]].concat();
        assert_eq!(utf8_string(&long).unwrap().len(), 128);
        assert!(
            utf8_string(b"\x13\x08operator")
                .unwrap_err()
                .contains("not an ASN.1 UTF8String")
        );
        assert!(utf8_string(b"\x0c\x09operator").is_err());
        assert!(utf8_string(b"\x0c\x02\xff\xfe").is_err());
        assert!(utf8_string(b"").is_err());
    }

    #[test]
    fn missing_and_malformed_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope.pem");
        let files = TlsFiles {
            cert: missing.clone(),
            key: missing.clone(),
            client_ca: None,
        };
        let e = server_config(&files, ClientAuth::IfConfigured, &[]).unwrap_err();
        assert!(
            e.to_string()
                .starts_with(&format!("certificate {}: ", missing.display())),
            "{e}"
        );
        let junk = dir.path().join("junk.pem");
        std::fs::write(&junk, "not a certificate\n").unwrap();
        let e = load_certificates(&junk, "certificate").unwrap_err();
        assert!(
            e.to_string().contains("no \"-----BEGIN CERTIFICATE-----\""),
            "{e}"
        );
        let e = load_key(&junk).unwrap_err();
        assert!(e.to_string().contains("holds no private key"), "{e}");
        let e = server_config(&files, ClientAuth::Required, &[]).unwrap_err();
        assert!(matches!(e, TlsError::File { .. }), "{e}");
    }
}
