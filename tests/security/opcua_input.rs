//! Bad input to OPC UA's TCP transport, raw, as an attacker sends it:
//! bytes that are no OPC UA message, a message announcing gigabytes, a
//! Hello whose URL claims a megabyte, buffers below the specification's
//! minimum, a chunk above the buffer the server acknowledged, a request on
//! no secure channel. Each costs only its own connection: answered `ERR`
//! or closed (at once, or at the server's hello timeout, 5 s, for a
//! message that announced more than it sent), while a secure channel
//! opened before stays open and a new one from another address opens (the
//! frames: `opcua_budget.rs`).

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::opcua_budget::{channel, connect_from, hello, message, next_type, open, string};
use crate::support::config::ConfigBuilder;
use crate::support::opcua::server_pki;
use crate::support::{TestDaemon, bounded};

/// How the daemon answered what was sent on `s`: `ERR`, or `closed`
/// (never an `ACK`, `OPN` or `MSG`, and never silence).
async fn turned_away(s: &mut TcpStream) -> String {
    match next_type(s).await {
        Ok(kind) => kind,
        Err(e) if e.contains("within 20 s") => e,
        Err(_) => "closed".to_string(),
    }
}

/// A Hello with `buffers` as both buffer sizes and `url`.
fn hello_with(buffers: u32, url: &str) -> Vec<u8> {
    let mut b = Vec::new();
    for v in [0u32, buffers, buffers, 0, 0] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    string(&mut b, url);
    message(b"HEL", &b)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_oversized_frames_close_only_their_connection() {
    bounded(Duration::from_secs(90), async {
        let dir = tempfile::tempdir().unwrap();
        let pki = server_pki(dir.path());
        let toml = ConfigBuilder::four_drives()
            .section(
                "opcua",
                &format!(
                    "listen = \"127.0.0.1:0\"\npki_dir = \"{}\"\nsecurity = [\"none\"]",
                    pki.display()
                ),
            )
            .toml();
        let d = TestDaemon::start(&toml).await;
        let addr = d.faces_addresses().await.opcua.expect("OPC UA listens");
        let url = format!("opc.tcp://{addr}/");
        let mut kept = channel("127.0.0.3", addr).await.expect("a secure channel");

        // A megabyte claimed for the URL of a small Hello.
        let mut lying = Vec::new();
        for v in [0u32, 65_536, 65_536, 0, 0] {
            lying.extend_from_slice(&v.to_le_bytes());
        }
        lying.extend_from_slice(&1_000_000i32.to_le_bytes());
        lying.extend_from_slice(b"opc.tcp://x/");
        // A whole Hello with four gigabytes announced in its header.
        let mut huge = hello(&url);
        huge[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
        let cases: Vec<(&'static str, Vec<u8>)> = vec![
            (
                "an HTTP request",
                b"GET / HTTP/1.1\r\nHost: x\r\n\r\n".to_vec(),
            ),
            (
                "random bytes",
                (0..64u8).map(|b| b.wrapping_mul(37)).collect(),
            ),
            ("a Hello announcing 4 GB", huge),
            (
                "a Hello whose URL claims a megabyte",
                message(b"HEL", &lying),
            ),
            ("buffers of 1 byte", hello_with(1, &url)),
            ("a request on no secure channel", message(b"MSG", &[0; 32])),
            ("an OpenSecureChannel before any Hello", open()),
        ];
        // All at once: a message cut short waits for the server's hello
        // timeout (5 s) before its ERR, the rest are answered at once.
        let attempts: Vec<_> = cases
            .into_iter()
            .map(|(what, bytes)| {
                tokio::spawn(async move {
                    let mut s = connect_from("127.0.0.2", addr).await.unwrap();
                    let _ = s.write_all(&bytes).await;
                    (what, turned_away(&mut s).await)
                })
            })
            .collect();
        for attempt in attempts {
            let (what, answer) = attempt.await.unwrap();
            assert!(
                answer == "ERR" || answer == "closed",
                "{what}: answered {answer}"
            );
        }

        // A chunk of a megabyte after a Hello of 64 KiB buffers.
        let mut s = connect_from("127.0.0.2", addr).await.unwrap();
        s.write_all(&hello(&url)).await.unwrap();
        assert_eq!(next_type(&mut s).await.as_deref(), Ok("ACK"));
        let mut chunk = b"OPNF".to_vec();
        chunk.extend_from_slice(&(1u32 << 20).to_le_bytes());
        chunk.resize(1 << 20, 0);
        let _ = s.write_all(&chunk).await;
        let answer = turned_away(&mut s).await;
        assert!(
            answer == "ERR" || answer == "closed",
            "a 1 MiB chunk: answered {answer}"
        );

        // The channel opened before is still open, and another opens.
        let mut probe = [0u8; 1];
        assert!(
            tokio::time::timeout(Duration::from_millis(200), kept.read(&mut probe))
                .await
                .is_err(),
            "the channel opened before was closed"
        );
        channel("127.0.0.4", addr)
            .await
            .expect("a new secure channel after the garbage");
        let health = crate::support::api::Api::new(d.http, None)
            .get("/healthz")
            .await;
        assert_eq!(health.status, 200);
        drop(kept);
        d.stop().await;
    })
    .await;
}
