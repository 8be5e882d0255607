//! How fresh a drive's data is, as the API and the stream tell it: a
//! drive whose polls go missing is `stale` before it is `offline`, and
//! `live` again when it answers, each change a `freshness` message on the
//! stream at the moment the daemon decides it (no event announces a poll
//! that does not happen); a drive that never answered (a bus at the wrong
//! baud rate) is `never`, and its status's problem names the rate, the
//! unit address and `drivegate probe --try-bauds`.

use std::time::{Duration, Instant};

use serde_json::Value;

use crate::support::api::{Api, connect, next_json};
use crate::support::config::ConfigBuilder;
use crate::support::faults::Scrape;
use crate::support::sim_process::ExternalSim;
use crate::support::{TestDaemon, bounded, eventually};

const LIMIT: Duration = Duration::from_secs(60);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_drive_is_stale_then_offline_then_live_again_on_rest_and_the_stream() {
    bounded(LIMIT, async {
        // Polled once a second: its data may be 1 s + two attempts of
        // 250 ms + 0.5 s old and still be live.
        let toml = ConfigBuilder::new()
            .bus("sim", |b| {
                b.keys("poll_interval_ms = 1000")
                    .drive(1, "conveyor")
                    .drive(2, "belt")
            })
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        let mut ws = connect(d.http, "?drives=conveyor", None).await;
        eventually(Duration::from_secs(10), "the conveyor live", || {
            d.plant.buses()[0]
                .handle
                .freshness(1)
                .filter(|v| v.freshness.is_live())
        })
        .await;

        d.sim().set_silent(1, true);
        let silenced = Instant::now();
        let mut told = Vec::new();
        while told.last().map(|(f, _): &(String, Value)| f.as_str()) != Some("offline") {
            let m = next_json(&mut ws, Duration::from_secs(20)).await;
            if m["type"] == "freshness" {
                assert_eq!(
                    (&m["drive"], &m["bus"], &m["unit"]),
                    (&"conveyor".into(), &"sim".into(), &1.into())
                );
                told.push((m["freshness"].as_str().unwrap().to_string(), m));
            }
        }
        let states: Vec<&str> = told.iter().map(|(f, _)| f.as_str()).collect();
        assert_eq!(states, ["stale", "offline"], "{told:?}");
        let stale = &told[0].1;
        let reason = stale["freshness_reason"].as_str().unwrap();
        assert!(
            reason.starts_with("polls missing: the drive is polled every 1.0 s, "),
            "{reason}"
        );
        // Not before its period and slack were over (1 s + 0.5 s + 0.5 s
        // after its last status, which came at most a period before the
        // silence).
        assert!(stale["age_ms"].as_u64().unwrap() > 2000, "{stale}");
        assert!(stale["freshness_since"].is_string(), "{stale}");
        let offline = &told[1].1;
        assert!(
            offline["freshness_reason"]
                .as_str()
                .unwrap()
                .starts_with("the drive stopped answering (3 polls failed, the last: "),
            "{offline}"
        );
        eprintln!(
            "stale then offline within {:?} of the silence",
            silenced.elapsed()
        );

        // REST says the same, the last value kept with its age; the belt
        // stays live, and /readyz counts it alone.
        let conveyor = api.get("/api/v1/drives/conveyor").await.expect(200);
        assert_eq!(conveyor["freshness"], "offline", "{conveyor}");
        assert_eq!(conveyor["link"], "offline", "{conveyor}");
        assert!(conveyor["status"].is_object() && conveyor["age_ms"].as_u64().unwrap() > 2000);
        let belt = api.get("/api/v1/drives/belt").await.expect(200);
        assert_eq!(belt["freshness"], "live", "{belt}");
        let ready = api.get("/readyz").await.expect(200);
        assert_eq!(ready["buses"][0]["drives_online"], 1, "{ready}");

        d.sim().set_silent(1, false);
        let back = loop {
            let m = next_json(&mut ws, Duration::from_secs(40)).await;
            if m["type"] == "freshness" {
                break m;
            }
        };
        assert_eq!(back["freshness"], "live", "{back}");
        assert!(back["freshness_reason"].is_null() && back["freshness_since"].is_null());
        let conveyor = api.get("/api/v1/drives/conveyor/status").await.expect(200);
        assert_eq!(conveyor["freshness"], "live", "{conveyor}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_that_never_answered_at_the_wrong_baud_rate_is_told_to_check_the_rate() {
    bounded(LIMIT, async {
        // The drives at 115200, the bus configured at 11520 (a digit
        // lost): the simulator hears what a UART at 115200 reads of bits
        // sent at 11520, garbage, and stays silent as a real drive would.
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-drives");
        let _sim = ExternalSim::start(&link, "3", &["--check-master-baud"]).await;
        let port = link.display().to_string();
        let toml = ConfigBuilder::new()
            .bus("line1", |b| b.port(&port).keys("baud = 11520").drive(3, "conveyor"))
            .toml();
        let d = TestDaemon::start_no_wait(&toml).await;
        let api = Api::new(d.http, None);
        eventually(Duration::from_secs(20), "the conveyor polled in vain", || {
            let handle = d.plant.buses()[0].handle.clone();
            let polled = handle.drive(3).is_some_and(|s| s.consecutive_failures >= 1);
            polled.then_some(())
        })
        .await;
        let drive = api.get("/api/v1/drives/conveyor").await.expect(200);
        assert_eq!(drive["freshness"], "never", "{drive}");
        assert!(drive["status"].is_null() && drive["age_ms"].is_null(), "{drive}");
        assert!(drive["freshness_since"].is_string(), "since the bus opened: {drive}");
        let reason = drive["freshness_reason"].as_str().unwrap();
        assert!(
            reason.starts_with("no answer since bus line1 opened (")
                && reason.contains("the bus runs at 11520 baud")
                && reason.contains("the unit address (3)"),
            "{reason}"
        );

        let problem = api
            .get("/api/v1/drives/conveyor/status")
            .await
            .expect_problem(503, "drive-offline");
        let detail = problem["detail"].as_str().unwrap();
        for words in [
            "drive \"conveyor\" has not answered once since bus line1 opened",
            "check the baud rate (bus line1 runs at 11520 baud; the drives leave the factory at 115200)",
            "the unit address (3)",
            &format!("`drivegate probe --port {port} --try-bauds`"),
        ] {
            assert!(detail.contains(words), "{words:?} not in {detail}");
        }

        // /readyz and the metrics agree.
        let ready = api.get("/readyz").await;
        assert_eq!(ready.status, 503, "{}", ready.body);
        assert_eq!(ready.body["buses"][0]["drives_online"], 0);
        assert_eq!(ready.body["buses"][0]["port_open"], true);
        let text = reqwest::get(api.url("/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        let s = Scrape::parse(&text);
        let l = [("bus", "line1"), ("unit", "3"), ("name", "conveyor")];
        assert_eq!(s.get("drivegate_drive_up", &l), 0.0);
        let mut never = l.to_vec();
        never.push(("freshness", "never"));
        assert_eq!(s.get("drivegate_drive_freshness", &never), 1.0);
        d.stop().await;
    })
    .await;
}
