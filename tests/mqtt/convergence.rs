//! Report by exception converges: a host's value ends equal to the
//! drive's after every change, also when the drive settles within the
//! deadband of the value last published. The host is a third-party
//! library, pysparkplug, following the conveyor's `status/speed_rpm` as a
//! SCADA tag would (`tests/python/sparkplug_follow.py`); the deadband is
//! 50 rpm, so steps of 30 or 40 rpm reach it only by the settled value
//! being published once it held.

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, BufReader};

use super::{GROUP, NODE, config};
use crate::support::api::Api;
use crate::support::mosquitto::Mosquitto;
use crate::support::{TestDaemon, bounded, tools};

const WAIT: Duration = Duration::from_secs(20);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_host_ends_with_the_drives_speed_after_every_setpoint_even_within_the_deadband() {
    bounded(Duration::from_secs(120), async {
        let broker = Mosquitto::start();
        let d = TestDaemon::start(&config(
            &broker.url(),
            "[mqtt.deadbands]\nspeed_rpm = 50",
        ))
        .await;
        let api = Api::new(d.http, None);
        api.activate_in("conveyor", "speed").await;

        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/sparkplug_follow.py");
        let mut host = tokio::process::Command::new("python3")
            .arg(&script)
            .args([&broker.port.to_string(), GROUP, NODE, "conveyor", "status/speed_rpm"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("{}", tools::cannot_run("python3", &e)));
        let mut lines = BufReader::new(host.stdout.take().unwrap()).lines();
        let mut stderr = host.stderr.take().unwrap();
        // The tag's value: from the rebirth's DBIRTH on.
        let mut tag: Option<i64> = None;
        let mut updates = 0;
        let mut next_value = async |tag: &mut Option<i64>, updates: &mut u32, limit: Duration| {
            let line = tokio::time::timeout(limit, lines.next_line()).await;
            let Ok(line) = line else { return false };
            let Some(line) = line.unwrap() else {
                let mut err = String::new();
                tokio::io::AsyncReadExt::read_to_string(&mut stderr, &mut err)
                    .await
                    .unwrap();
                if err.contains("No module named 'pysparkplug'") {
                    panic!("pysparkplug is missing: {}", tools::how_to_get("pysparkplug"));
                }
                panic!("the pysparkplug host ended: {err}");
            };
            let v: Value = serde_json::from_str(&line).unwrap();
            *tag = v["value"].as_i64();
            *updates += 1;
            true
        };
        assert!(
            next_value(&mut tag, &mut updates, WAIT).await,
            "no DBIRTH at the pysparkplug host"
        );

        // From standstill past the band, then steps within it, both ways.
        for rpm in [120_i64, 150, 110, 100, 60, 0] {
            api.put("/api/v1/drives/conveyor/setpoint", json!({"speed_rpm": rpm}))
                .await
                .expect(200);
            // The drive settles at the setpoint (the daemon's own poll).
            let start = Instant::now();
            loop {
                let s = api.get("/api/v1/drives/conveyor/status").await.expect(200);
                if s["speed_rpm"] == rpm {
                    break;
                }
                assert!(start.elapsed() < WAIT, "the conveyor never reached {rpm} rpm: {s}");
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            // The host's tag follows within a few polls of it holding.
            let settled = Instant::now();
            while tag != Some(rpm) {
                let left = WAIT.saturating_sub(settled.elapsed());
                assert!(
                    next_value(&mut tag, &mut updates, left).await,
                    "the host's tag stayed at {tag:?} rpm, the drive at {rpm} rpm"
                );
            }
            eprintln!(
                "{rpm} rpm: the host had it {} ms after the drive settled ({updates} updates so far)",
                settled.elapsed().as_millis()
            );
        }
        drop(host.stdin.take());
        let _ = tokio::time::timeout(Duration::from_secs(5), host.wait()).await;
        d.stop().await;
    })
    .await;
}
