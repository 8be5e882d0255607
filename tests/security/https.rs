//! HTTPS (`[http.tls]`) with certificates made by `openssl`: curl with the
//! test CA is served (with HSTS), a plain-HTTP client gets no HTTP answer,
//! mutual TLS wants a client certificate of `client_ca`, `check-config`
//! names a bad file, and SIGHUP reloads the certificate under load without
//! dropping a stream, keeping the old one when the new one is bad.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;

use crate::support::certs::Pki;
use crate::support::eventually;
use crate::support::{FOUR_DRIVES, TestDaemon, tools};

const LIMIT: Duration = Duration::from_secs(120);

pub fn tls_config(pki: &Pki, client: Option<&str>) -> String {
    let mut text = format!(
        "[http.tls]\ncert = \"{}\"\nkey = \"{}\"\n",
        pki.path("server.pem").display(),
        pki.path("server.key").display()
    );
    if let Some(ca) = client {
        text.push_str(&format!(
            "client_ca = \"{}\"\n",
            pki.path(&format!("{ca}.pem")).display()
        ));
    }
    text
}

/// FOUR_DRIVES with `[http.tls]` (a table after the [http] keys).
fn config(pki: &Pki, client_ca: Option<&str>) -> String {
    FOUR_DRIVES.replacen(
        "[modbus_tcp]\n",
        &format!("{}[modbus_tcp]\n", tls_config(pki, client_ca)),
        1,
    )
}

pub fn client_config(ca: &Path) -> Arc<rustls::ClientConfig> {
    let mut roots = rustls::RootCertStore::empty();
    for cert in drivegate::tls::load_certificates(ca, "CA").unwrap() {
        roots.add(cert).unwrap();
    }
    Arc::new(
        rustls::ClientConfig::builder_with_provider(Arc::new(
            rustls::crypto::ring::default_provider(),
        ))
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth(),
    )
}

async fn connect(
    addr: SocketAddr,
    config: &Arc<rustls::ClientConfig>,
) -> std::io::Result<TlsStream<TcpStream>> {
    let tcp = TcpStream::connect(addr).await?;
    let name = rustls::pki_types::ServerName::IpAddress(addr.ip().into());
    tokio_rustls::TlsConnector::from(config.clone())
        .connect(name, tcp)
        .await
}

/// The CN of the certificate the server presented.
fn server_cn(stream: &TlsStream<TcpStream>) -> String {
    let certs = stream.get_ref().1.peer_certificates().unwrap();
    drivegate::tls::peer_identity(&certs[0], "2.5.29.17")
        .unwrap()
        .common_name
        .unwrap()
}

/// One status read on a new TLS connection: the status code.
async fn get_once(
    addr: SocketAddr,
    config: &Arc<rustls::ClientConfig>,
) -> std::io::Result<(u16, String)> {
    let mut s = connect(addr, config).await?;
    let cn = server_cn(&s);
    s.write_all(b"GET /api/v1/drives/conveyor/status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        .await?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).await?;
    let status = String::from_utf8_lossy(answer.get(9..12).unwrap_or_default())
        .parse()
        .unwrap_or(0);
    Ok((status, cn))
}

/// The next JSON text of a stream over TLS, within 10 s.
async fn next_text(
    ws: &mut tokio_tungstenite::WebSocketStream<TlsStream<TcpStream>>,
) -> serde_json::Value {
    use futures_util::StreamExt;
    loop {
        let message = tokio::time::timeout(Duration::from_secs(10), ws.next())
            .await
            .expect("a stream message within 10 s")
            .expect("the stream is open")
            .expect("a message");
        if let tokio_tungstenite::tungstenite::Message::Text(text) = message {
            return serde_json::from_str(&text).unwrap();
        }
    }
}

async fn curl(args: &[&str]) -> std::process::Output {
    tools::require("curl");
    tokio::process::Command::new("curl")
        .args(["--silent", "--show-error", "--max-time", "20"])
        .args(args)
        .output()
        .await
        .unwrap_or_else(|e| panic!("{}", tools::cannot_run("curl", &e)))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn https_is_served_to_curl_with_the_ca_and_plain_http_is_not() {
    tokio::time::timeout(LIMIT, async {
        let pki = Pki::new();
        let d = TestDaemon::start(&config(&pki, None)).await;
        let url = format!("https://127.0.0.1:{}/api/v1/drives", d.http.port());
        let ca = pki.path("ca.pem");
        let out = curl(&["--cacert", ca.to_str().unwrap(), "-D", "-", &url]).await;
        let text = String::from_utf8_lossy(&out.stdout).to_lowercase();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(text.starts_with("http/1.1 200"), "{text}");
        assert!(
            text.contains("strict-transport-security: max-age=31536000"),
            "{text}"
        );
        assert!(text.contains("\"conveyor\""), "{text}");
        // Without the CA curl refuses the certificate.
        let out = curl(&[&url]).await;
        assert!(!out.status.success());
        // Plain HTTP on the TLS port gets no HTTP answer.
        let mut plain = TcpStream::connect(d.http).await.unwrap();
        plain
            .write_all(b"GET /api/v1/drives HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            .await
            .unwrap();
        let mut answer = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(20), plain.read_to_end(&mut answer)).await;
        assert!(
            !answer.starts_with(b"HTTP/"),
            "{:?}",
            String::from_utf8_lossy(&answer)
        );
        // The series exists from start-up at 0: the failure counted it.
        assert!(
            crate::support::metrics::counter(
                &d,
                "drivegate_tls_handshake_failures_total{face=\"http\"}"
            ) >= 1.0
        );
        d.stop().await;
    })
    .await
    .expect("in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_wants_a_certificate_of_the_client_ca() {
    tokio::time::timeout(LIMIT, async {
        let pki = Pki::new();
        pki.client("panel", "ca", None);
        pki.ca("foreign");
        pki.client("stranger", "foreign", None);
        let d = TestDaemon::start(&config(&pki, Some("ca"))).await;
        let url = format!("https://127.0.0.1:{}/api/v1/drives", d.http.port());
        let ca = pki.path("ca.pem");
        let ca = ca.to_str().unwrap();
        let out = curl(&["--cacert", ca, &url]).await;
        assert!(!out.status.success(), "served without a client certificate");
        let (cert, key) = (pki.path("stranger.pem"), pki.path("stranger.key"));
        let out = curl(&[
            "--cacert",
            ca,
            "--cert",
            cert.to_str().unwrap(),
            "--key",
            key.to_str().unwrap(),
            &url,
        ])
        .await;
        assert!(
            !out.status.success(),
            "served a certificate of a foreign CA"
        );
        let (cert, key) = (pki.path("panel.pem"), pki.path("panel.key"));
        let out = curl(&[
            "--cacert",
            ca,
            "--cert",
            cert.to_str().unwrap(),
            "--key",
            key.to_str().unwrap(),
            &url,
        ])
        .await;
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(String::from_utf8_lossy(&out.stdout).contains("\"conveyor\""));
        d.stop().await;
    })
    .await
    .expect("in time");
}

#[test]
fn check_config_names_a_bad_certificate_or_key() {
    let pki = Pki::new();
    let file = pki.path("drivegate.toml");
    let check = |text: &str| {
        std::fs::write(&file, text).unwrap();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
            .arg("check-config")
            .arg(&file)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let good = config(&pki, None);
    let (ok, err) = check(&good);
    assert!(ok, "{err}");
    std::fs::write(
        pki.path("junk.pem"),
        "-----BEGIN PRIVATE KEY-----\nnot base64\n",
    )
    .unwrap();
    let bad_key = good.replace("server.key", "junk.pem");
    let (ok, err) = check(&bad_key);
    assert!(!ok);
    assert!(
        err.contains("junk.pem") && err.contains("private key"),
        "{err}"
    );
    pki.server("other", "ca");
    let mismatch = good.replace("server.key", "other.key");
    let (ok, err) = check(&mismatch);
    assert!(!ok);
    assert!(err.contains("does not belong to the certificate"), "{err}");
    let missing = good.replace("server.pem", "absent.pem");
    let (ok, err) = check(&missing);
    assert!(!ok);
    assert!(err.contains("absent.pem"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_reloads_the_certificate_under_load_without_dropping_a_stream() {
    tokio::time::timeout(LIMIT, async {
        let pki = Pki::new();
        let d = TestDaemon::start(&config(&pki, None)).await;
        let addr = d.http;
        let client = client_config(&pki.path("ca.pem"));
        let tls = connect(addr, &client).await.unwrap();
        assert_eq!(server_cn(&tls), "127.0.0.1");
        let (mut ws, _) = tokio_tungstenite::client_async(
            format!("wss://127.0.0.1:{}/api/v1/stream?drives=all", addr.port()),
            tls,
        )
        .await
        .expect("the stream opens over TLS");
        next_text(&mut ws).await;

        // Load: status reads on new connections, each a new handshake.
        let (served, failed) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
        let stop = tokio_util::sync::CancellationToken::new();
        let load = {
            let (client, served, failed, stop) =
                (client.clone(), served.clone(), failed.clone(), stop.clone());
            tokio::spawn(async move {
                let mut names = std::collections::BTreeSet::new();
                while !stop.is_cancelled() {
                    match get_once(addr, &client).await {
                        Ok((200, cn)) => {
                            names.insert(cn);
                            served.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {
                            failed.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                names
            })
        };
        let reloads = |result: &str| {
            let text = d.metrics.render();
            text.lines()
                .find(|l| {
                    l.starts_with(&format!(
                        "drivegate_tls_reloads_total{{face=\"http\",result=\"{result}\"}}"
                    ))
                })
                .and_then(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
                .unwrap_or(0)
        };
        let before = served.load(Ordering::Relaxed);
        eventually(LIMIT, "load before the reload", || {
            (served.load(Ordering::Relaxed) > before + 5).then_some(())
        })
        .await;

        // Renew: the new pair replaces the files, then SIGHUP.
        pki.server_named("renewed", "ca", "renewed");
        std::fs::copy(pki.path("renewed.key"), pki.path("server.key")).unwrap();
        std::fs::copy(pki.path("renewed.pem"), pki.path("server.pem")).unwrap();
        let ok_before = reloads("ok");
        nix::sys::signal::raise(nix::sys::signal::Signal::SIGHUP).unwrap();
        eventually(LIMIT, "the reload", || {
            (reloads("ok") > ok_before).then_some(())
        })
        .await;
        let (_, cn) = get_once(addr, &client).await.unwrap();
        assert_eq!(cn, "renewed");

        // A bad file: logged, counted, and the renewed one stays.
        std::fs::write(pki.path("server.pem"), "garbage\n").unwrap();
        let failed_before = reloads("failed");
        nix::sys::signal::raise(nix::sys::signal::Signal::SIGHUP).unwrap();
        eventually(LIMIT, "the failed reload", || {
            (reloads("failed") > failed_before).then_some(())
        })
        .await;
        let (status, cn) = get_once(addr, &client).await.unwrap();
        assert_eq!((status, cn.as_str()), (200, "renewed"));

        stop.cancel();
        let names = load.await.unwrap();
        assert_eq!(
            failed.load(Ordering::Relaxed),
            0,
            "requests failed during the reloads"
        );
        assert!(
            names.contains("127.0.0.1") && names.contains("renewed"),
            "{names:?}"
        );
        // The stream opened before the reloads is still served.
        let later = next_text(&mut ws).await;
        assert!(later["type"].is_string(), "{later}");
        d.stop().await;
    })
    .await
    .expect("in time");
}
