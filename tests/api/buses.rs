//! Bus routes over real HTTP against the daemon on the simulator: health
//! and counters, a scan that finds the units that answer, and address
//! setting by broadcast, verified at the new address.

use std::time::Duration;

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon};
use serde_json::json;

const LIMIT: Duration = Duration::from_secs(40);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bus_counters_and_a_scan() {
    tokio::time::timeout(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let api = Api::new(d.http, None);

        let buses = api.get("/api/v1/buses").await.expect(200);
        let bus = &buses[0];
        assert_eq!(
            (
                bus["name"].as_str(),
                bus["port"].as_str(),
                bus["baud"].as_u64()
            ),
            (Some("sim"), Some("sim"), Some(115_200))
        );
        assert_eq!(bus["state"], "up");
        assert_eq!(
            (bus["drives"].as_u64(), bus["drives_online"].as_u64()),
            (Some(4), Some(4))
        );
        assert!(bus["counters"]["polls"].as_u64().unwrap() > 0);
        assert!(bus["queue"]["poll"].is_u64());
        // The silence before each drive's requests: the spec's by default.
        assert_eq!(bus["interframe"]["setting"], "spec");
        let gaps = bus["interframe"]["drives"].as_array().unwrap();
        assert_eq!(gaps.len(), 4);
        assert_eq!(
            (gaps[0]["unit"].as_u64(), gaps[0]["gap_us"].as_u64()),
            (Some(1), Some(1750))
        );
        assert_eq!(gaps[0]["fallbacks"], 0);
        assert_eq!(
            api.get("/api/v1/buses/sim").await.expect(200)["name"],
            "sim"
        );

        // Units 1-4 answer; 5-8 are silent. The silent lift is "missing".
        d.sim().set_silent(2, true);
        let scan = api
            .post("/api/v1/buses/sim/scan", json!({"from": 1, "to": 8}))
            .await
            .expect(200);
        let answered: Vec<u64> = scan["answered"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| h["unit"].as_u64().unwrap())
            .collect();
        assert_eq!(answered, [1, 3, 4]);
        assert_eq!(scan["answered"][0]["configured_as"], "conveyor");
        assert!(scan["answered"][0]["status"]["voltage_v"].as_u64().unwrap() > 0);
        assert_eq!(scan["silent"], 5);
        assert_eq!(scan["missing"], json!(["lift"]));
        assert!(scan["garbled"].as_array().unwrap().is_empty());
        // The scan did not make the unconfigured units appear as drives.
        let drives = api.get("/api/v1/drives").await.expect(200);
        assert_eq!(drives.as_array().unwrap().len(), 4);

        // Without a body, the default range; a reversed range is refused.
        let scan = api.post_empty("/api/v1/buses/sim/scan").await.expect(200);
        assert_eq!(
            (scan["from"].as_u64(), scan["to"].as_u64()),
            (Some(1), Some(32))
        );
        api.post("/api/v1/buses/sim/scan", json!({"from": 9, "to": 3}))
            .await
            .expect_problem(400, "invalid-request");
        api.post("/api/v1/buses/sim/scan", json!({"from": 0, "to": 3}))
            .await
            .expect_problem(422, "out-of-range");
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn address_setting_is_verified_at_the_new_address() {
    tokio::time::timeout(LIMIT, async {
        // One drive on the bus, as the manual requires for address setting.
        let single = "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nlisten = \"127.0.0.1:0\"\n\
            [[bus]]\nname = \"bench\"\nport = \"sim\"\n[bus.sim]\nseed = 3\n\
            [[bus.drive]]\nunit = 1\nname = \"spare\"\ngear_ratio = 1.0\n";
        let d = TestDaemon::start(single).await;
        let api = Api::new(d.http, None);

        api.post("/api/v1/buses/bench/address", json!({"address": 12}))
            .await
            .expect_problem(409, "confirmation-required");
        let r = api
            .post(
                "/api/v1/buses/bench/address",
                json!({"address": 12, "only_drive_on_bus": true}),
            )
            .await
            .expect(200);
        assert_eq!(
            (r["address"].as_u64(), r["verified"].as_bool()),
            (Some(12), Some(true))
        );
        assert!(r["configured_as"].is_null());
        assert!(r["note"].as_str().unwrap().contains("unit = 12"), "{r:#}");
        assert!(r["status"]["voltage_v"].as_u64().unwrap() > 0);
        // The drive answers at 12 now (and is kept there over a power cycle).
        let spare = d.sim().drive(12).expect("a drive at unit 12");
        assert_eq!(spare.flash.address, 12);
        assert!(d.sim().drive(1).is_none());
        // The configured unit 1 no longer answers: the config must change.
        let scan = api
            .post("/api/v1/buses/bench/scan", json!({"from": 1, "to": 12}))
            .await
            .expect(200);
        assert_eq!(scan["answered"][0]["unit"], 12);
        assert_eq!(scan["missing"], json!(["spare"]));
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A scan meets a full queue, then a job that waited its whole queue time:
/// it tries that unit again and carries on, and no unit it found is lost.
/// An emergency job to a unit nobody answers holds the wire for 6 s (a
/// 3 s response timeout and as long a guard), one command fills the queue
/// (capacity 1), and the scan's first read is refused busy; once that
/// command is withdrawn the retry is queued, waits past its 2 s queue time
/// behind the emergency job and is dropped unsent; the next try is read.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scan_tries_a_busy_unit_again_and_keeps_what_it_found() {
    use drivegate::bus::handle::JobOptions;
    use drivegate::bus::stats::Outcome;
    use drivegate::bus::{Priority, SourceId};
    use drivegate::drive::DriveRequest;

    tokio::time::timeout(LIMIT, async {
        let toml = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.timing(3000, 3000).keys("queue_capacity = 1"))
            .toml();
        let d = TestDaemon::start(&toml).await;
        let api = Api::new(d.http, None);
        let bus = d.plant.buses()[0].handle.clone();
        let status = DriveRequest::ReadStatus.pdu().unwrap();
        let options = |priority| JobOptions {
            priority,
            source: SourceId::new_unique(),
            queue_timeout: Some(Duration::from_secs(30)),
            max_attempts: Some(1),
            origin: Default::default(),
        };

        // Unit 30 answers nobody: 6 s on the wire, nothing else moves.
        let blocker = bus
            .submit(30, status.clone(), options(Priority::Emergency))
            .unwrap();
        crate::support::eventually(Duration::from_secs(5), "the blocker on the wire", || {
            (bus.queue_depths()[0] == 0).then_some(())
        })
        .await;
        let filler = bus
            .submit(1, status.clone(), options(Priority::Command))
            .unwrap();
        let before = bus.stats();

        let scan = tokio::spawn({
            let api = api.clone();
            async move {
                api.post("/api/v1/buses/sim/scan", json!({"from": 1, "to": 4}))
                    .await
            }
        });
        crate::support::eventually(Duration::from_secs(5), "the scan refused busy", || {
            (bus.stats().busy_rejections > before.busy_rejections).then_some(())
        })
        .await;
        drop(filler);

        let scan = scan.await.unwrap().expect(200);
        let answered: Vec<u64> = scan["answered"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| h["unit"].as_u64().unwrap())
            .collect();
        assert_eq!(answered, [1, 2, 3, 4], "{scan:#}");
        assert_eq!(scan["not_scanned"], json!([]), "{scan:#}");
        let after = bus.stats();
        let dropped = |s: &drivegate::bus::stats::BusStatsSnapshot| {
            s.transactions
                .get(&(0x03, Outcome::Dropped))
                .copied()
                .unwrap_or(0)
        };
        // The withdrawn command and the scan's expired read.
        assert!(
            dropped(&after) >= dropped(&before) + 2,
            "{:?}",
            after.transactions
        );
        drop(blocker);
        d.stop().await;
    })
    .await
    .expect("test finished in time");
}

/// A configuration without a bus (the package's, as shipped) and a bus
/// without drives (one to scan and commission) are valid: the daemon runs,
/// every face copes, and `/readyz` says in words what to do first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_bus_and_a_bus_without_drives_are_served() {
    tokio::time::timeout(LIMIT, async {
        let no_bus = "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nlisten = \"127.0.0.1:0\"\n";
        let d = TestDaemon::start_no_wait(no_bus).await;
        let api = Api::new(d.http, None);
        assert_eq!(api.get("/api/v1/buses").await.expect(200), json!([]));
        assert_eq!(api.get("/api/v1/drives").await.expect(200), json!([]));
        let ready = api.get("/readyz").await.expect(503);
        assert_eq!(
            ready["reasons"],
            json!([drivegate::api::health::NO_BUS]),
            "{ready}"
        );
        assert!(
            ready["reasons"][0]
                .as_str()
                .unwrap()
                .starts_with("no bus configured: run `drivegate probe")
        );
        let metrics = api.raw(|c| c.get(d.url("/metrics"))).await;
        assert_eq!(metrics.status, 200);
        // The console is served, and reads the empty list it shows its
        // message for.
        let page = reqwest::get(d.url("/")).await.unwrap();
        assert_eq!(page.status(), 200);
        d.stop().await;

        // A simulated bus without drives: a silent line, polled by nobody.
        let empty = format!(
            "{no_bus}[[bus]]\nname = \"line1\"\nport = \"sim\"\n{}\n",
            crate::support::WIRE_TIMING
        );
        let d = TestDaemon::start_no_wait(&empty).await;
        let api = Api::new(d.http, None);
        let buses = api.get("/api/v1/buses").await.expect(200);
        assert_eq!(buses[0]["name"], "line1");
        assert_eq!(buses[0]["drives"], 0, "{buses}");
        let ready = api.get("/readyz").await.expect(503);
        // (The port may not be open yet: that is a reason of its own.)
        let reasons = ready["reasons"].as_array().unwrap();
        assert!(
            reasons.contains(&json!(
                "bus line1 has no drives configured: scan it (the console's commissioning page, \
                 or POST /api/v1/buses/line1/scan) and add its [[bus.drive]] sections"
            )),
            "{ready}"
        );
        assert!(
            !reasons
                .iter()
                .any(|r| r.as_str().unwrap().contains("no drive answers")),
            "{ready}"
        );
        let scan = api
            .post("/api/v1/buses/line1/scan", json!({"from": 1, "to": 2}))
            .await
            .expect(200);
        assert_eq!(scan["silent"], 2, "{scan}");
        // The bus has its series; no drive has any.
        let metrics = reqwest::get(d.url("/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        assert!(
            metrics.contains("drivegate_bus_port_open{bus=\"line1\"}"),
            "{metrics}"
        );
        assert!(!metrics.contains("drivegate_drive_up{"), "{metrics}");
        d.stop().await;
    })
    .await
    .expect("within the limit");
}
