//! The console over HTTPS in Debian's chromium: the test's own server
//! certificate (made by `openssl`) is trusted by its public key only
//! (`--ignore-certificate-errors-spki-list`), the page loads, logs in with
//! a token and goes live over `wss://`, the token sent as a subprotocol.

use std::process::Command;

use super::browser::{LONG, assert_no_errors, open};
use super::harness::{ADMIN, config};
use crate::support::TestDaemon;
use crate::support::cdp::Browser;

/// base64 of the SHA-256 of the certificate's public key (SPKI), as
/// chromium's `--ignore-certificate-errors-spki-list` takes it.
fn spki_hash(cert: &std::path::Path) -> String {
    let script = format!(
        "openssl x509 -in '{}' -pubkey -noout | openssl pkey -pubin -outform der | openssl dgst -sha256 -binary | base64",
        cert.display()
    );
    let out = Command::new("sh").arg("-c").arg(script).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap().trim().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_console_works_over_https_with_its_stream_on_wss() {
    crate::support::tools::require("openssl");
    let pki = crate::support::certs::Pki::new();
    let tls = format!(
        "[http.tls]\ncert = \"{}\"\nkey = \"{}\"\n",
        pki.path("server.pem").display(),
        pki.path("server.key").display()
    );
    let daemon = TestDaemon::start(&config(true, &tls)).await;
    let base = format!("https://127.0.0.1:{}", daemon.http.port());
    let trust = format!(
        "--ignore-certificate-errors-spki-list={}",
        spki_hash(&pki.path("server.pem"))
    );
    let browser = Browser::start(&[&trust]).await;
    let page = open(&browser, &base, "/", Some(ADMIN)).await;
    assert_eq!(page.eval("location.protocol").await, "https:");
    page.wait_for(
        "document.querySelectorAll('table.drives tbody tr').length === 4",
        LONG,
        "four rows",
    )
    .await;
    let requests = page.requests();
    let stream = format!("wss://127.0.0.1:{}/api/v1/stream", daemon.http.port());
    assert!(
        requests.iter().any(|u| u.starts_with(&stream)),
        "no wss:// stream: {requests:#?}"
    );
    assert!(
        requests.iter().all(|u| !u.contains("access_token")),
        "the token went into a URL: {requests:#?}"
    );
    assert_no_errors(&page, false);
    daemon.stop().await;
}
