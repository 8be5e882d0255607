//! How the HTTP face takes tokens: the stream's token in a WebSocket
//! subprotocol (answered with the non-secret one only), `?access_token=`
//! still served but never logged, and an address that guesses tokens
//! paused with 429 and `Retry-After`, counted, and logged once per burst,
//! whether it guesses in a header or in the stream's subprotocol, and that
//! address only.

use std::time::Duration;

use tokio_tungstenite::tungstenite::client::IntoClientRequest;

use crate::support::TestDaemon;
use crate::support::api::next_json;
use crate::support::input::{ADMIN, VIEWER, config, raw_http, request};
use crate::support::logs::{capture_logs, log_text};

const LIMIT: Duration = Duration::from_secs(60);

/// base64url without padding, as the console encodes a token.
fn base64url(bytes: &[u8]) -> String {
    const ALPHABET: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |acc, (i, b)| acc | (u32::from(*b) << (16 - 8 * i)));
        for i in 0..=chunk.len() {
            out.push(ALPHABET[((n >> (18 - 6 * i)) & 63) as usize] as char);
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_takes_its_token_in_a_subprotocol_and_never_echoes_it() {
    tokio::time::timeout(LIMIT, async {
        capture_logs();
        let d = TestDaemon::start(&config("", "", true, "")).await;
        let mut upgrade = format!("ws://{}/api/v1/stream?drives=all", d.http)
            .into_client_request()
            .unwrap();
        upgrade.headers_mut().insert(
            "sec-websocket-protocol",
            format!(
                "drivegate, drivegate.bearer.{}",
                base64url(VIEWER.as_bytes())
            )
            .parse()
            .unwrap(),
        );
        let (mut ws, answer) = tokio_tungstenite::connect_async(upgrade)
            .await
            .expect("the stream opens with the token in a subprotocol");
        assert_eq!(
            answer.headers().get("sec-websocket-protocol").unwrap(),
            "drivegate",
            "only the non-secret subprotocol is answered"
        );
        let first = next_json(&mut ws, Duration::from_secs(10)).await;
        assert!(first["type"].is_string(), "{first}");

        // A wrong token in the subprotocol is refused like a wrong header.
        let wrong = request_with_protocol(d.http, "drivegate, drivegate.bearer.d3Jvbmc");
        let a = raw_http(d.http, &wrong).await.unwrap();
        assert_eq!(a.status, 401, "{}", a.text());

        // The URL still works for old scripts, and is never logged.
        let secret_query = format!("?drives=all&access_token={ADMIN}");
        let (mut ws, _) = tokio_tungstenite::connect_async(format!(
            "ws://{}/api/v1/stream{secret_query}",
            d.http
        ))
        .await
        .expect("?access_token= still opens the stream");
        next_json(&mut ws, Duration::from_secs(10)).await;
        let a = raw_http(
            d.http,
            &request(
                "GET",
                &format!("/api/v1/nowhere?access_token={ADMIN}"),
                None,
                &[],
                b"",
            ),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 404);
        assert!(!a.text().contains(ADMIN), "{}", a.text());
        assert!(!log_text().contains(ADMIN), "a token reached the log");
        assert!(!log_text().contains(&base64url(VIEWER.as_bytes())));
        d.stop().await;
    })
    .await
    .expect("in time");
}

fn request_with_protocol(addr: std::net::SocketAddr, protocols: &str) -> Vec<u8> {
    format!(
        "GET /api/v1/stream HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade, close\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {protocols}\r\n\r\n"
    )
    .into_bytes()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_guessing_is_paused_counted_and_logged_once() {
    tokio::time::timeout(LIMIT, async {
        capture_logs();
        let d = TestDaemon::start(&config("", "", true, "")).await;
        let guess = |i: usize| {
            request(
                "GET",
                "/api/v1/drives",
                Some(&format!("guess-{i}")),
                &[],
                b"",
            )
        };
        let pauses_logged = || {
            log_text()
                .lines()
                .filter(|l| l.contains("10 unknown API tokens from this address"))
                .count()
        };
        let before = pauses_logged();
        let mut statuses = Vec::new();
        for i in 0..12 {
            statuses.push(raw_http(d.http, &guess(i)).await.unwrap().status);
        }
        assert_eq!(statuses[..10], [401; 10], "{statuses:?}");
        assert_eq!(statuses[10..], [429; 2], "{statuses:?}");
        let logged = pauses_logged();
        assert!(logged > before, "the pause was not logged");
        // Paused: even the right token is refused meanwhile, with a time.
        let a = raw_http(
            d.http,
            &request("GET", "/api/v1/drives", Some(VIEWER), &[], b""),
        )
        .await
        .unwrap();
        assert_eq!(a.status, 429, "{}", a.text());
        let retry: u64 = a.header("retry-after").unwrap().parse().unwrap();
        assert!((1..=60).contains(&retry), "Retry-After: {retry}");
        assert_eq!(
            a.json().unwrap()["type"],
            "urn:drivegate:problem:too-many-failures"
        );
        // Routes that need no token are still served.
        let a = raw_http(d.http, &request("GET", "/healthz", None, &[], b""))
            .await
            .unwrap();
        assert_eq!(a.status, 200);
        let metrics = d.metrics.render();
        assert!(
            metrics.contains("drivegate_http_auth_failures_total 10"),
            "{metrics}"
        );
        assert!(
            metrics.contains("drivegate_http_auth_throttled_total 3"),
            "{metrics}"
        );
        // Once per burst: the refused requests did not log again.
        assert_eq!(pauses_logged(), logged);
        let log = log_text();
        assert!(!log.contains("guess-3"), "a token reached the log");
        d.stop().await;
    })
    .await
    .expect("in time");
}

/// The status of a WebSocket upgrade offering `protocols`, sent from the
/// loopback address `source`.
async fn upgrade_from(source: &str, addr: std::net::SocketAddr, protocols: &str) -> u16 {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let exchange = async {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
        let mut s = socket.connect(addr).await.unwrap();
        s.write_all(&request_with_protocol(addr, protocols))
            .await
            .unwrap();
        // The head only: a 101 keeps the connection open.
        let mut head = Vec::new();
        let mut byte = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            if s.read(&mut byte).await.unwrap() == 0 {
                break;
            }
            head.push(byte[0]);
        }
        let head = String::from_utf8_lossy(&head).into_owned();
        head.split(' ')
            .nth(1)
            .and_then(|c| c.parse().ok())
            .unwrap_or_else(|| panic!("no status in {head:?}"))
    };
    tokio::time::timeout(Duration::from_secs(10), exchange)
        .await
        .expect("an answer within 10 s")
}

/// Ten wrong tokens offered as the stream's subprotocol from 127.0.0.2
/// pause that address (429, the right token included): the stream's
/// sign-in is the API's, under the core's rule; the operator at 127.0.0.1
/// still opens the stream with its token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_guessing_the_streams_token_pauses_only_its_own_address() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(&config("", "", true, "")).await;
        let bearer = |token: &str| {
            format!(
                "drivegate, drivegate.bearer.{}",
                base64url(token.as_bytes())
            )
        };
        let mut statuses = Vec::new();
        for i in 0..11 {
            statuses.push(upgrade_from("127.0.0.2", d.http, &bearer(&format!("guess-{i}"))).await);
        }
        assert_eq!(statuses[..10], [401; 10], "{statuses:?}");
        assert_eq!(statuses[10], 429, "{statuses:?}");
        assert_eq!(
            upgrade_from("127.0.0.2", d.http, &bearer(VIEWER)).await,
            429
        );
        assert_eq!(
            upgrade_from("127.0.0.1", d.http, &bearer(VIEWER)).await,
            101
        );
        d.stop().await;
    })
    .await
    .expect("in time");
}
