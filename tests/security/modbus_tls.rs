//! Modbus/TCP Security (`[modbus_tcp.tls]`) with pymodbus's
//! ModbusTlsClient and certificates made by `openssl`: the role comes from
//! the certificate's extension 1.3.6.1.4.1.50316.802.1 and the control core
//! applies it as for a network's role (an operator sets a speed but cannot
//! save; a viewer reads but cannot write), the communication-loss function
//! holds for TLS clients, the audit log and the bus monitor name the CN,
//! and a foreign CA, no certificate or an unknown role are not served; a
//! flood of handshakes that never come, or of plain bytes, from one
//! address leaves a certified client of another served.

use std::path::Path;
use std::time::Duration;

use crate::support::certs::Pki;
use crate::support::eventually;
use crate::support::logs::{capture_logs, log_text};
use crate::support::{FOUR_DRIVES, TestDaemon, tools};

const LIMIT: Duration = Duration::from_secs(120);

async fn client(
    addr: std::net::SocketAddr,
    pki: &Pki,
    cert: Option<&str>,
    steps: &[&str],
) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/modbus_tls_client.py");
    let (cert, key) = match cert {
        Some(name) => (
            pki.path(&format!("{name}.pem")).display().to_string(),
            pki.path(&format!("{name}.key")).display().to_string(),
        ),
        None => ("-".to_string(), "-".to_string()),
    };
    let output = tokio::time::timeout(
        Duration::from_secs(60),
        tokio::process::Command::new("python3")
            .arg(script)
            .arg(addr.ip().to_string())
            .arg(addr.port().to_string())
            .arg(pki.path("ca.pem"))
            .args([cert, key])
            .args(steps)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("the client finishes")
    .unwrap_or_else(|e| {
        panic!(
            "cannot run python3 ({e}): {}",
            tools::how_to_get("pymodbus")
        )
    });
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_ne!(
        output.status.code(),
        Some(3),
        "pymodbus is missing: {}",
        tools::how_to_get("pymodbus")
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("no JSON ({e}): {stdout:?} {stderr:?}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn roles_come_from_client_certificates() {
    tokio::time::timeout(LIMIT, async {
        capture_logs();
        let pki = Pki::new();
        pki.client("line-3-plc", "ca", Some("ASN1:UTF8String:Operator"));
        pki.client("hmi-panel", "ca", Some("ASN1:UTF8String:viewer"));
        pki.client("no-role", "ca", None);
        pki.client("boss", "ca", Some("ASN1:UTF8String:boss"));
        pki.ca("foreign");
        pki.client("stranger", "foreign", Some("ASN1:UTF8String:admin"));
        let section = format!(
            "[modbus_tcp.tls]\nlisten = \"127.0.0.1:0\"\ncert = \"{}\"\nkey = \"{}\"\nclient_ca = \"{}\"\ncomm_loss_ms = 500\n",
            pki.path("server.pem").display(),
            pki.path("server.key").display(),
            pki.path("ca.pem").display()
        );
        let toml = FOUR_DRIVES.replacen("[[bus]]\n", &format!("{section}[[bus]]\n"), 1);
        let d = TestDaemon::start(&toml).await;
        let addr = d.modbus_tls.expect("the Modbus/TCP Security listener");

        // Operator: activate, speed mode, 120 rpm; a save flag is refused.
        let out = client(
            addr,
            &pki,
            Some("line-3-plc"),
            &["write:3:0x02:0", "write:3:0x02:0xA", "write:3:0x06:120", "write:3:0x1C:1"],
        )
        .await;
        let r = &out["results"];
        assert_eq!(out["connected"], true, "{out}");
        for i in 0..3 {
            assert_eq!(r[i]["written"], true, "{out}");
        }
        assert_eq!(r[3]["exception"], 1, "{out}");
        // The connection closed: its communication-loss lease ends with a
        // zero speed (without it the motor would keep turning).
        eventually(LIMIT, "the comm-loss stop", || {
            let drive = d.sim().drive(3)?;
            (drive.setpoints.speed_rpm == 0).then_some(())
        })
        .await;
        let log = log_text();
        assert!(
            log.lines().any(|l| l.contains("who=\"line-3-plc (127.0.0.1:") && l.contains("SPEED_TD_R_SAVE_FLAG")),
            "the audit log does not name the certificate's CN:\n{}", log.lines().filter(|l| l.contains("line-3")).collect::<Vec<_>>().join("\n")
        );
        let frames = reqwest::get(d.url("/api/v1/buses/sim/monitor/frames?limit=500"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        assert!(frames.contains("line-3-plc (127.0.0.1:"), "the bus monitor does not name the CN");

        // Viewer, and a certificate without the extension (default viewer):
        // reads pass, writes are refused with 0x01.
        for name in ["hmi-panel", "no-role"] {
            let out = client(addr, &pki, Some(name), &["read:3:0xC0:7", "write:3:0x06:50"]).await;
            assert_eq!(out["connected"], true, "{name}: {out}");
            assert_eq!(out["results"][0]["registers"].as_array().map(Vec::len), Some(7), "{name}: {out}");
            assert_eq!(out["results"][1]["exception"], 1, "{name}: {out}");
        }
        assert_eq!(d.sim().drive(3).unwrap().setpoints.speed_rpm, 0);

        // Not served: a foreign CA, no certificate, an unknown role.
        for who in [Some("stranger"), None, Some("boss")] {
            let out = client(addr, &pki, who, &["read:3:0xC0:7"]).await;
            assert_eq!(out["connected"], false, "{who:?} was served: {out}");
        }
        assert!(log_text().contains("the certificate's role \"boss\" is none of viewer, operator, admin"));
        let metrics = d.metrics.render();
        assert!(metrics.contains("drivegate_modbus_tcp_tls_refused_total{reason=\"role\"} 1"), "{metrics}");
        d.stop().await;
    })
    .await
    .expect("in time");
}

/// A connection to `addr` from the loopback address `source`.
async fn connect_from(
    source: &str,
    addr: std::net::SocketAddr,
) -> std::io::Result<tokio::net::TcpStream> {
    let socket = tokio::net::TcpSocket::new_v4()?;
    socket.bind(format!("{source}:0").parse().unwrap())?;
    socket.connect(addr).await
}

/// 100 connections from 127.0.0.2 that never start their handshake, and
/// 20 that send plain Modbus TCP, HTTP or a record of no known handshake
/// message instead of a ClientHello: the garbage costs its own
/// connections (closed at once, counted, logged a few times, not once
/// each), the silent ones hold no more than their share of the budget
/// until the idle timeout closes them, and a client with its certificate
/// from 127.0.0.1 is served meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_handshakes_from_one_address_leaves_a_certified_client_served() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    tokio::time::timeout(LIMIT, async {
        capture_logs();
        let pki = Pki::new();
        pki.client("line-3-plc", "ca", Some("ASN1:UTF8String:operator"));
        let section = format!(
            "[modbus_tcp.tls]\nlisten = \"127.0.0.1:0\"\ncert = \"{}\"\nkey = \"{}\"\nclient_ca = \"{}\"\n",
            pki.path("server.pem").display(),
            pki.path("server.key").display(),
            pki.path("ca.pem").display()
        );
        // Handshakes that never start are closed after the idle timeout.
        let toml = FOUR_DRIVES
            .replacen("[modbus_tcp]\n", "[modbus_tcp]\nidle_timeout_ms = 3000\n", 1)
            .replacen("[[bus]]\n", &format!("{section}[[bus]]\n"), 1);
        let d = TestDaemon::start(&toml).await;
        let addr = d.modbus_tls.expect("the Modbus/TCP Security listener");
        let handshakes_failed = || {
            crate::support::metrics::metric(
                &d.metrics.render(),
                "drivegate_tls_handshake_failures_total{face=\"modbus_tcp\"}",
            )
        };
        let logged = || {
            log_text()
                .lines()
                .filter(|l| l.contains("Modbus/TCP Security handshake failed") && l.contains("127.0.0.2:"))
                .count()
        };
        let mut garbage = Vec::new();
        for i in 0..20 {
            let Ok(mut s) = connect_from("127.0.0.2", addr).await else {
                continue;
            };
            let bytes: &[u8] = match i % 3 {
                // Read holding registers, plain MBAP: waits for a record.
                0 => &[0, 1, 0, 0, 0, 6, 3, 3, 0, 0xC0, 0, 7],
                // HTTP: a record header announcing 8 kB that never come.
                1 => b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
                // A whole handshake record of no known message: refused.
                _ => &[0x16, 3, 1, 0, 4, 0xFF, 0, 0, 0],
            };
            let _ = s.write_all(bytes).await;
            garbage.push(s);
        }
        // Each garbage connection is closed by the daemon.
        for s in &mut garbage {
            let mut buf = [0u8; 512];
            let closed = loop {
                match tokio::time::timeout(Duration::from_secs(20), s.read(&mut buf)).await {
                    Ok(Ok(0) | Err(_)) => break true,
                    Ok(Ok(_)) => continue,
                    Err(_) => break false,
                }
            };
            assert!(closed, "a connection that sent garbage is still open");
        }
        let mut silent = Vec::new();
        for _ in 0..100 {
            if let Ok(s) = connect_from("127.0.0.2", addr).await {
                silent.push(s);
            }
        }
        let out = client(addr, &pki, Some("line-3-plc"), &["read:3:0xC0:7"]).await;
        assert_eq!(out["connected"], true, "{out}");
        assert_eq!(
            out["results"][0]["registers"].as_array().map(Vec::len),
            Some(7),
            "{out}"
        );
        eventually(LIMIT, "the failed handshakes counted", || {
            (handshakes_failed() >= 20.0).then_some(())
        })
        .await;
        let lines = logged();
        assert!(
            (1..=10).contains(&lines),
            "{lines} log lines for 20 failed handshakes of one address: {}",
            log_text().lines().filter(|l| l.contains("Security")).collect::<Vec<_>>().join("\n")
        );
        drop(silent);
        d.stop().await;
    })
    .await
    .expect("in time");
}
