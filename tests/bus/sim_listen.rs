//! `drivegate sim --listen` as a user runs it: the simulated bus served on
//! TCP as a serial device server serves a line, read by a third-party
//! RTU-over-TCP master (pymodbus) and by raw bytes; stops on SIGTERM with
//! its line of counters.

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use drivegate::drive::DriveRequest;
use drivegate::modbus::crc::frame_crc_ok;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::process::Command;

#[tokio::test]
async fn serves_rtu_over_tcp_until_sigterm() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .args([
            "sim",
            "--units",
            "1-2",
            "--devices",
            "100",
            "--listen",
            "127.0.0.1:0",
        ])
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap()).lines();
    let first = tokio::time::timeout(Duration::from_secs(10), stdout.next_line())
        .await
        .expect("no address line within 10 s")
        .unwrap()
        .unwrap();
    let address = first
        .strip_prefix("tcp://")
        .unwrap_or_else(|| panic!("not a tcp:// address: {first}"));
    assert!(address.starts_with("127.0.0.1:"), "{first}");

    // Raw RTU frames over the connection, as the daemon sends them.
    let mut stream = TcpStream::connect(address).await.unwrap();
    stream
        .write_all(&DriveRequest::ReadStatus.frame(2).unwrap())
        .await
        .unwrap();
    let mut reply = [0u8; 19];
    tokio::time::timeout(Duration::from_secs(2), stream.read_exact(&mut reply))
        .await
        .expect("no reply within 2 s")
        .unwrap();
    assert_eq!(reply[..3], [2, 0x03, 0x0E]);
    assert!(frame_crc_ok(&reply));
    drop(stream);

    // A third-party master: pymodbus with its RTU framer over TCP, reading
    // the longest frame from the register device.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/rtu_over_tcp_client.py");
    let (host, port) = address.rsplit_once(':').unwrap();
    let output = Command::new("python3")
        .arg(script)
        .args([host, port, "100", "0x0200", "125"])
        .output();
    let output = tokio::time::timeout(Duration::from_secs(30), output)
        .await
        .expect("pymodbus did not finish within 30 s")
        .expect("cannot run python3: install Python 3 and pymodbus");
    assert_ne!(
        output.status.code(),
        Some(3),
        "pymodbus is missing: install it with `pip install 'pymodbus>=3.10'`"
    );
    let printed: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| {
        panic!(
            "{e}: {} {}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        )
    });
    let expected: Vec<u16> = (0x0200..0x0200 + 125).collect();
    assert_eq!(
        printed["registers"],
        serde_json::json!(expected),
        "{printed}"
    );

    let status = std::process::Command::new("kill")
        .args(["-TERM", &child.id().unwrap().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let exit = tokio::time::timeout(Duration::from_secs(10), child.wait())
        .await
        .expect("did not stop within 10 s of SIGTERM")
        .unwrap();
    assert!(exit.success(), "{exit:?}");
    let stats = stdout.next_line().await.unwrap().unwrap();
    assert!(stats.contains("requests=2 replies=2"), "{stats}");
    assert!(stats.contains("connections=2"), "{stats}");
}
