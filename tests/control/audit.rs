//! One audit log for every face: a write refused by the control core (a
//! role, a still-check) is logged as a failed write with the face and who
//! sent it, whether it came over Modbus TCP or HTTP; so is one refused
//! before it became a request (a value out of range, a mode the drive does
//! not have), over HTTP and the stream; an override is logged;
//! and after a PLC's brake ended an HTTP lease, no lease-expiry write is.

// `common` is shared by several test crates: its `pub` items are for them.

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::support::alone;
use crate::support::api::{Api, connect, ws_command};
use crate::support::modbus_tcp::{Raw, four_drives_with, write};
use crate::support::{TestDaemon, eventually};
use serde_json::json;

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

    /// Waits for a line with every one of `parts`.
    async fn line_with(&self, parts: &[&str]) -> String {
        eventually(
            Duration::from_secs(10),
            &format!("an audit line with {parts:?}"),
            || {
                self.lines()
                    .into_iter()
                    .find(|l| parts.iter().all(|p| l.contains(p)))
            },
        )
        .await
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_and_overrides_are_audited_alike_for_every_face() {
    let name = "refusals_and_overrides_are_audited_alike_for_every_face";
    if !alone::here(module_path!(), name) {
        return;
    }
    let log = Captured::default();
    let writer = log.clone();
    // Alone in its process: the global subscriber sees every thread, and
    // no other test's writes.
    tracing_subscriber::fmt()
        .with_writer(move || writer.clone())
        .with_env_filter("drivegate::audit=info")
        .with_ansi(false)
        .init();

    tokio::time::timeout(Duration::from_secs(60), async {
        let d = TestDaemon::start(&four_drives_with(
            "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"",
        ))
        .await;
        let api = Api::new(d.http, None);
        let mut plc = Raw::connect(d.modbus_tcp.unwrap()).await;
        let who = format!("who=\"{}\"", plc.stream.local_addr().unwrap());

        // A role refusal over Modbus TCP.
        assert_eq!(plc.ask(3, &write(0x0024, 4)).await, [0x86, 0x01]);
        let line = log
            .line_with(&[
                "write failed",
                "face=\"modbus-tcp\"",
                &who,
                "INERTIA_RATIO=4",
            ])
            .await;
        assert!(
            line.contains("refused: this needs the admin role"),
            "{line}"
        );

        // Values refused before they became a request, over HTTP and the
        // stream: out of the drive's range, a mode it does not have.
        api.put("/api/v1/drives/feeder/setpoint", json!({"speed_rpm": 5000}))
            .await
            .expect_problem(422, "out-of-range");
        let line = log
            .line_with(&[
                "write failed",
                "face=\"http\"",
                "unit=4",
                "what=\"speed setpoint 5000 rpm\"",
            ])
            .await;
        assert!(line.contains("valid -2048 to 2047 rpm"), "{line}");
        api.put("/api/v1/drives/feeder/mode", json!({"mode": "fast"}))
            .await
            .expect(400);
        log.line_with(&[
            "write failed",
            "face=\"http\"",
            "mode \\\"fast\\\"",
            "speed, position or torque",
        ])
        .await;
        let mut ws = connect(d.http, "", None).await;
        let reply = ws_command(
            &mut ws,
            1,
            "setpoint",
            "feeder",
            json!({"position_deg": 720}),
        )
        .await;
        assert_eq!(reply["ok"], false, "{reply}");
        log.line_with(&[
            "write failed",
            "face=\"websocket\"",
            "position setpoint 720 deg",
            "valid -180 to 180 deg",
        ])
        .await;

        // A still-check refusal over HTTP and an override, both audited.
        api.activate_in("conveyor", "speed").await;
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            json!({"speed_rpm": 200}),
        )
        .await
        .expect(200);
        eventually(Duration::from_secs(10), "the conveyor turning", || {
            (d.sim().drive(1)?.speed_rpm > 50.0).then_some(())
        })
        .await;
        api.put(
            "/api/v1/drives/conveyor/inertia",
            json!({"ratio": 2, "save": true}),
        )
        .await
        .expect_problem(409, "drive-moving");
        let line = log
            .line_with(&["write failed", "face=\"http\"", "load inertia ratio 2"])
            .await;
        assert!(
            line.contains("refused: drive \"conveyor\" turns at"),
            "{line}"
        );
        api.put(
            "/api/v1/drives/conveyor/inertia",
            json!({"ratio": 2, "save": true, "force": true}),
        )
        .await
        .expect(200);
        log.line_with(&[
            "a save to flash while the motor turns, as the override allowed",
            "face=\"http\"",
        ])
        .await;
        log.line_with(&["write confirmed", "face=\"http\"", "load inertia ratio 2"])
            .await;

        // The scenario of a brake over Modbus TCP ending an HTTP lease: the
        // brake is audited, and no lease-expiry write follows it.
        api.activate_in("lift", "torque").await;
        api.put(
            "/api/v1/drives/lift/setpoint",
            json!({"torque_a": 1.0, "lease_ms": 800}),
        )
        .await
        .expect(200);
        let brake = write(0x0002, 0x0005);
        assert_eq!(plc.ask(2, &brake).await, brake);
        log.line_with(&[
            "write confirmed",
            "face=\"modbus-tcp\"",
            &who,
            "config command brake 5",
        ])
        .await;
        tokio::time::sleep(Duration::from_millis(1800)).await;
        let expiry: Vec<String> = log
            .lines()
            .into_iter()
            .filter(|l| l.contains("lease-expiry"))
            .collect();
        assert!(expiry.is_empty(), "a stop followed the brake: {expiry:#?}");
        d.stop().await;
    })
    .await
    .expect("test finished within 60 s");
}
