//! Every write through Modbus TCP is in the audit log, with the client's
//! address, the drive and the outcome; reads are not.

use std::time::Duration;

use crate::support::logs::{capture_logs, log_text};
use crate::support::modbus_tcp::{Raw, read, write};
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};

/// The audit lines logged so far that name `who` (other tests of this
/// binary write through their own connections, with their own addresses).
fn audit_lines_of(who: &str) -> Vec<String> {
    log_text()
        .lines()
        .filter(|l| l.contains("drivegate::audit") && l.contains(who))
        .map(str::to_string)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_write_is_audited_with_the_client_address() {
    capture_logs();
    tokio::time::timeout(Duration::from_secs(60), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let who = format!("who=\"{}\"", c.stream.local_addr().unwrap());

        // Confirmed, refused by the drive, no path, and a read.
        assert_eq!(c.ask(2, &write(0x000E, 1500)).await, write(0x000E, 1500));
        assert_eq!(c.ask(2, &write(0x0006, 3000)).await, [0x86, 0x03]);
        assert_eq!(c.ask(42, &write(0x0002, 0)).await, [0x86, 0x0A]);
        assert_eq!(c.ask(2, &read(0xC0, 7)).await.len(), 16);

        // Three writes, each named by this client's address; the read is
        // not audited.
        let lines = eventually(Duration::from_secs(5), "three audit lines", || {
            let lines = audit_lines_of(&who);
            (lines.len() >= 3).then_some(lines)
        })
        .await;
        assert_eq!(lines.len(), 3, "{lines:#?}");
        // And no audit line, of this test or another, lacks its client.
        let log = log_text();
        let anonymous: Vec<&str> = log
            .lines()
            .filter(|l| l.contains("drivegate::audit") && !l.contains("who="))
            .collect();
        assert!(anonymous.is_empty(), "{anonymous:#?}");
        assert!(
            lines[0].contains("write confirmed")
                && lines[0].contains("bus=\"sim\" unit=2")
                && lines[0].contains("[06 00 0E 05 DC]"),
            "{}",
            lines[0]
        );
        assert!(
            lines[1].contains("write failed")
                && lines[1].contains("[06 00 06 0B B8]")
                && lines[1].contains("exception 0x03"),
            "{}",
            lines[1]
        );
        assert!(
            lines[2].contains("write failed")
                && lines[2].contains("unit=42")
                && lines[2].contains("activate")
                && lines[2].contains("not on any configured bus"),
            "{}",
            lines[2]
        );
        d.stop().await;
    })
    .await
    .expect("test finished within 60 s");
}
