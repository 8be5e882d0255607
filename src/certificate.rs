//! What a certificate says, for the people who decide to trust it: its
//! subject and issuer, its OPC UA application URI, when it is valid, and
//! its thumbprints (SHA-1, as OPC UA clients and Windows show it, and
//! SHA-256, as browsers do). Pure: DER or PEM bytes in. A leaf: the core
//! (the expiry alarm), the daemon (the certificate directories) and the
//! API name certificates alike.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rustls::pki_types::CertificateDer;
use rustls::pki_types::pem::PemObject;
use sha2::Digest;

/// One certificate, read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CertificateInfo {
    /// Its subject (`CN=drivegate@press-gw, O=drivegate`).
    pub subject: String,
    /// Its common name, if any.
    pub common_name: Option<String>,
    /// Its issuer (the subject again for a self-signed one).
    pub issuer: String,
    /// The URI in its subject alternative names: an OPC UA application's
    /// application URI.
    pub application_uri: Option<String>,
    /// Valid from.
    pub not_before: SystemTime,
    /// Valid until.
    pub not_after: SystemTime,
    /// SHA-1 of the DER, lowercase hex: OPC UA's thumbprint.
    pub thumbprint: String,
    /// SHA-256 of the DER, lowercase hex.
    pub sha256: String,
    /// True when it is a CA's.
    pub is_ca: bool,
}

impl CertificateInfo {
    /// True when it is its own issuer.
    pub fn self_signed(&self) -> bool {
        self.subject == self.issuer
    }

    /// Days from `now` until it expires (negative once expired).
    pub fn days_left(&self, now: SystemTime) -> i64 {
        let secs = match self.not_after.duration_since(now) {
            Ok(d) => i64::try_from(d.as_secs()).unwrap_or(i64::MAX),
            Err(e) => -i64::try_from(e.duration().as_secs()).unwrap_or(i64::MAX),
        };
        secs.div_euclid(86_400)
    }
}

/// Reads one DER certificate.
pub fn read(der: &[u8]) -> Result<CertificateInfo, String> {
    let (_, cert) = x509_parser::parse_x509_certificate(der)
        .map_err(|e| format!("not an X.509 certificate: {e}"))?;
    let time =
        |t: i64| u64::try_from(t).map_or(UNIX_EPOCH, |s| UNIX_EPOCH + Duration::from_secs(s));
    let application_uri = cert
        .subject_alternative_name()
        .ok()
        .flatten()
        .and_then(|san| {
            san.value.general_names.iter().find_map(|n| match n {
                x509_parser::extensions::GeneralName::URI(u) => Some((*u).to_string()),
                _ => None,
            })
        });
    let hex = |bytes: &[u8]| bytes.iter().map(|b| format!("{b:02x}")).collect::<String>();
    Ok(CertificateInfo {
        subject: cert.subject().to_string(),
        common_name: cert
            .subject()
            .iter_common_name()
            .next()
            .and_then(|cn| cn.as_str().ok())
            .map(str::to_string),
        issuer: cert.issuer().to_string(),
        application_uri,
        not_before: time(cert.validity().not_before.timestamp()),
        not_after: time(cert.validity().not_after.timestamp()),
        thumbprint: hex(&sha1::Sha1::digest(der)),
        sha256: hex(&sha2::Sha256::digest(der)),
        is_ca: cert.is_ca(),
    })
}

/// The certificates (DER) in a file's bytes: every one of a PEM file, or
/// the file itself as DER.
pub fn ders(bytes: &[u8]) -> Vec<Vec<u8>> {
    if bytes.starts_with(b"-----BEGIN") || bytes.windows(10).any(|w| w == b"-----BEGIN") {
        CertificateDer::pem_slice_iter(bytes)
            .flatten()
            .map(|c| c.to_vec())
            .collect()
    } else {
        vec![bytes.to_vec()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A self-signed certificate made by `openssl req -x509 -newkey ec
    /// -pkeyopt ec_paramgen_curve:prime256v1 -subj "/CN=probe/O=drivegate
    /// tests" -addext "subjectAltName=URI:urn:probe:client,DNS:localhost"
    /// -days 1`; `openssl x509 -fingerprint -sha1` gives its thumbprint.
    const PEM: &str = "-----BEGIN CERTIFICATE-----
MIIB0DCCAXegAwIBAgIUU97ugX5u2p3Dq2S4HnSblTpo92gwCgYIKoZIzj0EAwIw
KjEOMAwGA1UEAwwFcHJvYmUxGDAWBgNVBAoMD2RyaXZlZ2F0ZSB0ZXN0czAeFw0y
NjExMjgyMzMyMjVaFw0yNjExMjkyMzMyMjVaMCoxDjAMBgNVBAMMBXByb2JlMRgw
FgYDVQQKDA9kcml2ZWdhdGUgdGVzdHMwWTATBgcqhkjOPQIBBggqhkjOPQMBBwNC
AAQtCTexBwN0jYooGBMLwBBdyIKjF+jTXa9/i9ipDY6LA4yeNIsFL88QnkTpahEM
Vw7fC+UdwO9TRYoNxPbjRTUjo3sweTAdBgNVHQ4EFgQUG6uqHOC4AXiXkF60m1O6
i6NnGEkwHwYDVR0jBBgwFoAUG6uqHOC4AXiXkF60m1O6i6NnGEkwDwYDVR0TAQH/
BAUwAwEB/zAmBgNVHREEHzAdhhB1cm46cHJvYmU6Y2xpZW50gglsb2NhbGhvc3Qw
CgYIKoZIzj0EAwIDRwAwRAIgSoaw8S3Sibs3nhWhDbUinoYGH41vaKo9AkZtPwn0
DqoCICp/1tEz3Kutf8dF5e23xHUzCRCRKSl5jqH4j8bhlT/A
-----END CERTIFICATE-----
";

    #[test]
    fn a_certificate_is_read_as_openssl_shows_it() {
        let found = ders(PEM.as_bytes());
        assert_eq!(found.len(), 1);
        let info = read(&found[0]).unwrap();
        assert_eq!(info.subject, "CN=probe, O=drivegate tests");
        assert_eq!(info.common_name.as_deref(), Some("probe"));
        assert!(info.self_signed() && info.is_ca);
        assert_eq!(info.application_uri.as_deref(), Some("urn:probe:client"));
        assert_eq!(info.thumbprint, "12ddb19e7f96015e174588793ed2e86d93fe25de");
        assert_eq!(info.sha256.len(), 64);
        let valid = info.not_after.duration_since(info.not_before).unwrap();
        assert_eq!(valid, Duration::from_secs(86_400));
        // Garbage is no certificate.
        assert!(read(b"hello").is_err());
        assert_eq!(ders(b"hello"), vec![b"hello".to_vec()]);
    }

    #[test]
    fn days_left_count_down_and_go_negative() {
        let info = CertificateInfo {
            subject: "CN=a".into(),
            common_name: Some("a".into()),
            issuer: "CN=a".into(),
            application_uri: None,
            not_before: UNIX_EPOCH,
            not_after: UNIX_EPOCH + Duration::from_secs(10 * 86_400),
            thumbprint: String::new(),
            sha256: String::new(),
            is_ca: false,
        };
        assert!(info.self_signed());
        assert_eq!(info.days_left(UNIX_EPOCH), 10);
        assert_eq!(
            info.days_left(UNIX_EPOCH + Duration::from_secs(9 * 86_400 + 1)),
            0
        );
        assert_eq!(
            info.days_left(UNIX_EPOCH + Duration::from_secs(11 * 86_400)),
            -1
        );
    }
}
