//! Certificates made by `openssl` for the TLS tests: a CA, a server
//! certificate for 127.0.0.1 and localhost, client certificates with (or
//! without) the Modbus/TCP Security role extension, and a foreign CA.

use std::path::{Path, PathBuf};
use std::process::Command;

use super::tools;

/// The role extension of Modbus/TCP Security.
pub const ROLE_OID: &str = "1.3.6.1.4.1.50316.802.1";

/// A directory of keys and certificates.
pub struct Pki {
    pub dir: tempfile::TempDir,
}

/// Runs `openssl args` in `dir`, failing the test with its words.
pub fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl")
        .current_dir(dir)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("openssl", &e)));
    assert!(
        out.status.success(),
        "openssl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

impl Pki {
    /// A CA named `ca` and a server certificate `server` signed by it.
    pub fn new() -> Pki {
        let pki = Pki {
            dir: tempfile::tempdir().unwrap(),
        };
        pki.ca("ca");
        pki.server("server", "ca");
        pki
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// `name.pem` and `name.key`: a self-signed CA.
    pub fn ca(&self, name: &str) {
        openssl(
            self.dir.path(),
            &[
                "req",
                "-x509",
                "-newkey",
                "ec",
                "-pkeyopt",
                "ec_paramgen_curve:prime256v1",
                "-nodes",
                "-keyout",
                &format!("{name}.key"),
                "-out",
                &format!("{name}.pem"),
                "-days",
                "2",
                "-subj",
                &format!("/CN=drivegate test {name}"),
                "-addext",
                "basicConstraints=critical,CA:TRUE",
                "-addext",
                "keyUsage=critical,keyCertSign,cRLSign",
            ],
        );
    }

    fn signed(&self, name: &str, ca: &str, cn: &str, extensions: &str) {
        let dir = self.dir.path();
        std::fs::write(dir.join(format!("{name}.ext")), extensions).unwrap();
        openssl(
            dir,
            &[
                "req",
                "-new",
                "-newkey",
                "ec",
                "-pkeyopt",
                "ec_paramgen_curve:prime256v1",
                "-nodes",
                "-keyout",
                &format!("{name}.key"),
                "-out",
                &format!("{name}.csr"),
                "-subj",
                &format!("/CN={cn}"),
            ],
        );
        openssl(
            dir,
            &[
                "x509",
                "-req",
                "-in",
                &format!("{name}.csr"),
                "-CA",
                &format!("{ca}.pem"),
                "-CAkey",
                &format!("{ca}.key"),
                "-CAcreateserial",
                "-out",
                &format!("{name}.pem"),
                "-days",
                "2",
                "-extfile",
                &format!("{name}.ext"),
            ],
        );
    }

    /// `name.pem`/`name.key`: a server certificate for 127.0.0.1 and
    /// localhost, CN `cn`, signed by `ca`.
    pub fn server_named(&self, name: &str, ca: &str, cn: &str) {
        self.signed(
            name,
            ca,
            cn,
            "basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\nsubjectAltName=IP:127.0.0.1,DNS:localhost\n",
        );
    }

    pub fn server(&self, name: &str, ca: &str) {
        self.server_named(name, ca, "127.0.0.1");
    }

    /// `name.pem`/`name.key`: a client certificate, CN `name`, signed by
    /// `ca`, with `role` in the role extension if given (written as the
    /// openssl line, e.g. `ASN1:UTF8String:operator`).
    pub fn client(&self, name: &str, ca: &str, role: Option<&str>) {
        let role = role.map_or_else(String::new, |r| format!("{ROLE_OID}={r}\n"));
        self.signed(
            name,
            ca,
            name,
            &format!("basicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n{role}"),
        );
    }
}
