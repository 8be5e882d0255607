//! OPC UA application certificates: the server's made at the first start,
//! a client's refused, saved and then trusted without a restart (the
//! clients and the daemon: `opcua.rs`).

use std::time::{Duration, Instant};

use super::opcua::{Client, LIMIT, Ua, section_keys, step};
use crate::support::certs::openssl;
use crate::support::metrics::metric;
use crate::support::opcua::{application_cert, host_name};
use crate::support::wait::{bounded, eventually};

/// The server's certificate is made at the first start (its SANs: the
/// application URI and the address); an unknown client certificate is
/// refused and saved in `rejected/certs` as `<application
/// name>-<thumbprint>.der`; copied to `trusted/certs` as PEM under a name
/// of its own (the rejected copy left where it is), the same client is
/// served, without a restart, trusted by its content; the docs' `mv` line
/// works as written.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_certificate_is_refused_then_trusted_without_a_restart() {
    bounded(LIMIT, async {
        // The server's own certificate made at its first start.
        let dir = tempfile::tempdir().unwrap();
        let section = section_keys(&dir.path().join("pki"));
        let ua = Ua::start_with(None, dir, section).await;
        let own = ua.pki.join("own/cert.der");
        let out = std::process::Command::new("openssl")
            .args([
                "x509",
                "-inform",
                "der",
                "-noout",
                "-ext",
                "subjectAltName",
                "-in",
            ])
            .arg(&own)
            .output()
            .unwrap();
        let san = String::from_utf8_lossy(&out.stdout);
        assert!(
            san.contains(&format!("URI:urn:{}:drivegate", host_name())),
            "{san}"
        );
        assert!(san.contains("127.0.0.1"), "{san}");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(ua.pki.join("private/private.pem"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);

        let dir = ua.pki.parent().unwrap().to_path_buf();
        application_cert(&dir, "pyclient", "urn:freeopcua:client");
        let args: Vec<String> = [
            "--policy",
            "basic256sha256",
            "--cert",
            &dir.join("pyclient.der").display().to_string(),
            "--key",
            &dir.join("pyclient-key.pem").display().to_string(),
        ]
        .map(String::from)
        .to_vec();
        let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
        assert_ne!(step(&all, "secure")["status"], "Good", "{all:?}");
        let rejected = ua.pki.join("rejected/certs");
        let file = eventually(
            Duration::from_secs(20),
            "the certificate in rejected/certs",
            || {
                std::fs::read_dir(&rejected)
                    .ok()?
                    .flatten()
                    .map(|e| e.path())
                    .next()
            },
        )
        .await;
        // Counted once the mirror has moved it (the same pass).
        eventually(Duration::from_secs(10), "the refusal counted", || {
            let text = ua.d.metrics.render();
            (metric(&text, "drivegate_opcua_rejected_certificates_total") >= 1.0).then_some(())
        })
        .await;
        // Saved under a name that needs no quoting: the application's name
        // and the SHA-1 thumbprint.
        let der = std::fs::read(dir.join("pyclient.der")).unwrap();
        let thumbprint: String = drivegate::tls::sha1_fingerprint(&der)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let name = file.file_name().unwrap().to_string_lossy().to_string();
        assert_eq!(name, format!("pyclient-{thumbprint}.der"));
        // Copied (not moved) from the client's machine, as PEM under a name
        // of its own: trusted by its content, whatever rejected/ still holds.
        openssl(
            &dir,
            &[
                "x509",
                "-inform",
                "der",
                "-in",
                "pyclient.der",
                "-out",
                "copied.pem",
            ],
        );
        std::fs::copy(
            dir.join("copied.pem"),
            ua.pki.join("trusted/certs/pyclient from the laptop.pem"),
        )
        .unwrap();
        assert!(file.is_file(), "the rejected copy stays");
        // Trusted at the next secure channel (the store follows the
        // directory every second).
        let t0 = Instant::now();
        loop {
            let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
            if step(&all, "secure")["status"] == "Good" {
                break;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "still refused: {all:?}"
            );
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
        // The docs' `mv` line, as written (no quoting), works too.
        let mv = format!(
            "mv {}/{name} {}/",
            rejected.display(),
            ua.pki.join("trusted/certs").display()
        );
        let done = std::process::Command::new("sh")
            .args(["-c", &mv])
            .status()
            .unwrap();
        assert!(done.success(), "{mv}");
        let all = Client::asyncua(&ua.url, "secure", &args).steps().await;
        assert_eq!(step(&all, "secure")["status"], "Good", "{all:?}");
    })
    .await;
}
