//! `drivegate sim` as a user runs it: prints the pty and the link, serves a
//! master through the link, stops on SIGTERM with a line of counters and
//! without leaving the link behind.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly by design

use std::process::Stdio;
use std::time::Duration;

use drivegate::drive::DriveRequest;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::process::Command;
use tokio_serial::SerialPortBuilderExt;

#[tokio::test]
async fn serves_through_the_link_until_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyDRIVES");
    let mut child = Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .args(["sim", "--units", "1,3-4", "--turnaround-ms", "0", "--link"])
        .arg(&link)
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap()).lines();
    let first = tokio::time::timeout(Duration::from_secs(10), stdout.next_line())
        .await
        .expect("no pty line within 10 s")
        .unwrap()
        .unwrap();
    let (pty, printed_link) = first.split_once(' ').unwrap();
    assert!(pty.starts_with("/dev/pts/"), "{first}");
    assert_eq!(printed_link, link.to_string_lossy());
    assert_eq!(std::fs::read_link(&link).unwrap().to_string_lossy(), pty);

    let mut port = tokio_serial::new(link.to_string_lossy(), 115_200)
        .open_native_async()
        .unwrap();
    port.write_all(&DriveRequest::ReadStatus.frame(4).unwrap())
        .await
        .unwrap();
    let mut reply = [0u8; 19];
    tokio::time::timeout(Duration::from_secs(2), port.read_exact(&mut reply))
        .await
        .expect("no reply within 2 s")
        .unwrap();
    assert_eq!(reply[..3], [4, 0x03, 0x0E]);

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
    assert!(stats.starts_with("requests=1 replies=1 "), "{stats}");
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "the link is removed on exit"
    );
}
