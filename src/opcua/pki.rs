//! The certificates' directory, in the layout of OPC UA Part 12, F.1:
//!
//! ```text
//! <pki_dir>/own/cert.der          the server's certificate (made at the first start)
//! <pki_dir>/private/private.pem   its key (0600, in a 0700 directory)
//! <pki_dir>/trusted/certs/        client certificates trusted (DER or PEM, any name)
//! <pki_dir>/rejected/certs/       client certificates refused, for an admin to move
//! <pki_dir>/issuers/certs/        CAs of application certificates (Part 12's; not checked)
//! <pki_dir>/users/trusted/certs/  user certificates trusted one by one (X.509 identity tokens)
//! ```
//!
//! async-opcua's own store knows only `trusted/*.der` under its own file
//! names (`<CN> [<sha1>].der`) and `rejected/*.der`, and refuses a
//! certificate that is in its `rejected/` even if it is trusted too. So
//! its store is kept apart, in `<pki_dir>/.stack`, and [`Pki::sync`]
//! (every second, and before the server starts) mirrors `trusted/certs`
//! into `.stack/trusted` under the crate's names and moves what the crate
//! rejected into `rejected/certs` (as `<application name>-<thumbprint>.der`):
//! a certificate moved or copied into `trusted/certs`, under any file name,
//! is trusted at the client's next connection, without a restart.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use opcua::crypto::{CertificateStore, X509, X509Data};
use rustls::pki_types::pem::PemObject;

/// The directories of one server's certificates.
#[derive(Debug, Clone)]
pub struct Pki {
    root: PathBuf,
}

/// The server's own certificate, as its start found or made it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Own {
    /// Found in `own/`.
    Found,
    /// Made now (the first start).
    Made,
}

impl Pki {
    /// The directory `root`.
    pub fn new(root: PathBuf) -> Self {
        Pki { root }
    }

    /// Its root.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The crate's own store.
    pub fn stack_dir(&self) -> PathBuf {
        self.root.join(".stack")
    }

    /// The server's certificate.
    pub fn cert_path(&self) -> PathBuf {
        self.root.join("own/cert.der")
    }

    /// Its private key.
    pub fn key_path(&self) -> PathBuf {
        self.root.join("private/private.pem")
    }

    /// Client certificates trusted.
    pub fn trusted(&self) -> PathBuf {
        self.root.join("trusted/certs")
    }

    /// Client certificates refused.
    pub fn rejected(&self) -> PathBuf {
        self.root.join("rejected/certs")
    }

    /// CAs of application certificates (Part 12's; not checked yet).
    pub fn issuers(&self) -> PathBuf {
        self.root.join("issuers/certs")
    }

    /// User certificates trusted one by one (X.509 identity tokens): their
    /// role comes from `[[opcua.user_certificate]]`.
    pub fn users_trusted(&self) -> PathBuf {
        self.root.join("users/trusted/certs")
    }

    /// Makes the directories (blocking: call it off the runtime).
    pub fn prepare(&self) -> Result<(), String> {
        for dir in [
            "own",
            "private",
            "trusted/certs",
            "trusted/crl",
            "rejected/certs",
            "issuers/certs",
            "issuers/crl",
            "users/trusted/certs",
            ".stack/trusted",
            ".stack/rejected",
        ] {
            let path = self.root.join(dir);
            std::fs::create_dir_all(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        }
        use std::os::unix::fs::PermissionsExt;
        let private = self.root.join("private");
        std::fs::set_permissions(&private, std::fs::Permissions::from_mode(0o700))
            .map_err(|e| format!("{}: {e}", private.display()))?;
        self.sync();
        Ok(())
    }

    /// Makes the server's certificate and key when `own/` has none (the
    /// first start; blocking, RSA key generation: call it off the
    /// runtime). Its subject alternative names: `application_uri`, the
    /// `addresses` clients reach it by, localhost and its addresses, and
    /// the host's name and addresses. Its CN names the host, so two
    /// gateways' certificates differ (the crate gives every one serial 42).
    pub fn ensure_own_certificate(
        &self,
        application_uri: &str,
        host: &str,
        addresses: &[String],
    ) -> Result<Own, String> {
        if self.cert_path().exists() && self.key_path().exists() {
            return Ok(Own::Found);
        }
        let data = X509Data {
            key_size: 2048,
            common_name: format!("drivegate@{host}"),
            organization: "drivegate".to_string(),
            organizational_unit: String::new(),
            country: String::new(),
            state: String::new(),
            alt_host_names: X509Data::alt_host_names(
                application_uri,
                Some(addresses.to_vec()),
                true,
                true,
                true,
            ),
            certificate_duration_days: 3650,
        };
        CertificateStore::create_certificate_and_key(
            &data,
            false,
            &self.cert_path(),
            &self.key_path(),
        )?;
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(self.key_path(), std::fs::Permissions::from_mode(0o600))
            .map_err(|e| format!("{}: {e}", self.key_path().display()))?;
        Ok(Own::Made)
    }

    /// One pass of the mirror (blocking): `trusted/certs` into
    /// `.stack/trusted` under the crate's names (and nothing else there);
    /// a trusted certificate taken out of `.stack/rejected` (the crate
    /// refuses what is there before it looks at its trust: trust is by
    /// content, whatever was rejected before); what the crate rejected
    /// moved to `rejected/certs` under a name that needs no quoting
    /// ([`rejected_name`]). Returns the names of the certificates rejected
    /// since the last pass.
    pub fn sync(&self) -> Vec<String> {
        let stack_trusted = self.root.join(".stack/trusted");
        let mut wanted = HashSet::new();
        for der in read_certs(&self.trusted()) {
            let Ok(cert) = X509::from_der(&der) else {
                continue;
            };
            let name = CertificateStore::cert_file_name(&cert);
            let path = stack_trusted.join(&name);
            if std::fs::read(&path).ok().as_deref() != Some(der.as_slice()) {
                let _ = std::fs::write(&path, &der);
            }
            wanted.insert(name);
        }
        for entry in std::fs::read_dir(&stack_trusted)
            .into_iter()
            .flatten()
            .flatten()
        {
            if !wanted.contains(&entry.file_name().to_string_lossy().to_string()) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        let mut rejected = Vec::new();
        let stack_rejected = self.root.join(".stack/rejected");
        for entry in std::fs::read_dir(&stack_rejected)
            .into_iter()
            .flatten()
            .flatten()
        {
            if wanted.contains(&entry.file_name().to_string_lossy().to_string()) {
                let _ = std::fs::remove_file(entry.path());
                continue;
            }
            let der = std::fs::read(entry.path()).unwrap_or_default();
            let name = rejected_name(&der, &entry.file_name().to_string_lossy());
            if std::fs::rename(entry.path(), self.rejected().join(&name)).is_ok() {
                rejected.push(name);
            }
        }
        rejected
    }
}

/// The name a rejected certificate is saved under in `rejected/certs`:
/// `<application name>-<SHA-1 thumbprint>.der`, with only letters, digits,
/// `.`, `_` and `-` (no space, no bracket: the docs' `mv` line works as
/// written). `fallback` (the crate's file name) when `der` is no
/// certificate.
pub fn rejected_name(der: &[u8], fallback: &str) -> String {
    let clean = |text: &str| -> String {
        let mut out = String::new();
        for c in text.chars() {
            let c = if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            };
            if !(c == '_' && out.ends_with('_')) {
                out.push(c);
            }
        }
        out.trim_matches(['_', '.', '-']).to_string()
    };
    let Ok(facts) = crate::tls::peer_identity(&der.to_vec().into(), "") else {
        let stem = clean(fallback.trim_end_matches(".der"));
        return format!(
            "{}.der",
            if stem.is_empty() {
                "certificate"
            } else {
                &stem
            }
        );
    };
    let thumbprint: String = crate::tls::sha1_fingerprint(der)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let name = facts.common_name.map(|cn| clean(&cn)).unwrap_or_default();
    if name.is_empty() {
        format!("{thumbprint}.der")
    } else {
        format!("{name}-{thumbprint}.der")
    }
}

/// The certificates (DER) of the files of `dir`: DER files, and every
/// certificate of PEM files.
pub fn read_certs(dir: &Path) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let path = entry.path();
        if !path.is_file() {
            continue;
        }
        let Ok(bytes) = std::fs::read(&path) else {
            continue;
        };
        if bytes.starts_with(b"-----BEGIN") {
            out.extend(
                rustls::pki_types::CertificateDer::pem_slice_iter(&bytes)
                    .flatten()
                    .map(|c| c.to_vec()),
            );
        } else {
            out.push(bytes);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("drivegate-pki-test-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn the_layout_is_part_12s_and_the_key_is_private() {
        let root = scratch("layout");
        let pki = Pki::new(root.clone());
        pki.prepare().unwrap();
        for dir in [
            "own",
            "private",
            "trusted/certs",
            "rejected/certs",
            "issuers/certs",
        ] {
            assert!(root.join(dir).is_dir(), "{dir}");
        }
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(root.join("private"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o700);
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn rejected_certificates_move_to_rejected_certs() {
        let root = scratch("rejected");
        let pki = Pki::new(root.clone());
        pki.prepare().unwrap();
        std::fs::write(root.join(".stack/rejected/client [ab].der"), b"x").unwrap();
        assert_eq!(pki.sync(), vec!["client_ab.der".to_string()]);
        assert!(root.join("rejected/certs/client_ab.der").is_file());
        assert!(pki.sync().is_empty());
        // Something that is no certificate in trusted/certs is not mirrored.
        std::fs::write(root.join("trusted/certs/notes.txt"), b"hello").unwrap();
        std::fs::write(root.join(".stack/trusted/old.der"), b"gone").unwrap();
        pki.sync();
        assert_eq!(
            std::fs::read_dir(root.join(".stack/trusted"))
                .unwrap()
                .count(),
            0
        );
        let _ = std::fs::remove_dir_all(&root);
    }
}
