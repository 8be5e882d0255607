//! Every write through Modbus TCP is in the audit log, with the client's
//! address, the drive and the outcome; reads are not.

// `common` is shared by several test crates: its `pub` items are for them.
#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod common;
mod modbus_tcp_support;

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::{FOUR_DRIVES, TestDaemon, eventually};
use modbus_tcp_support::{Raw, read, write};

/// The log lines written so far.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Captured {
    fn lines(&self) -> Vec<String> {
        String::from_utf8_lossy(&self.0.lock().unwrap())
            .lines()
            .map(str::to_string)
            .collect()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_write_is_audited_with_the_client_address() {
    let log = Captured::default();
    let writer = log.clone();
    // The only test of this binary: the global subscriber sees every thread.
    tracing_subscriber::fmt()
        .with_writer(move || writer.clone())
        .with_env_filter("drivegate::audit=info")
        .with_ansi(false)
        .init();

    tokio::time::timeout(Duration::from_secs(60), async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let mut c = Raw::connect(d.modbus_tcp.unwrap()).await;
        let who = format!("who=\"{}\"", c.stream.local_addr().unwrap());

        // Confirmed, refused by the drive, no path, and a read.
        assert_eq!(c.ask(2, &write(0x000E, 1500)).await, write(0x000E, 1500));
        assert_eq!(c.ask(2, &write(0x0006, 3000)).await, [0x86, 0x03]);
        assert_eq!(c.ask(42, &write(0x0002, 0)).await, [0x86, 0x0A]);
        assert_eq!(c.ask(2, &read(0xC0, 7)).await.len(), 16);

        let lines = eventually(Duration::from_secs(5), "three audit lines", || {
            let lines = log.lines();
            (lines.len() >= 3).then_some(lines)
        })
        .await;
        assert_eq!(lines.len(), 3, "{lines:#?}");
        assert!(lines.iter().all(|l| l.contains(&who)), "{lines:#?}");
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
