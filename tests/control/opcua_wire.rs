//! OPC UA values when the wire goes: `BadNoCommunication` once the adapter
//! is gone, stale values `UncertainLastUsableValue`, alarms as events
//! acknowledged as through the API, the bus's variables against the API's
//! view (the clients and the daemon: `opcua.rs`).

use std::time::{Duration, Instant};

use serde_json::Value;

use super::opcua::{Client, LIMIT, STEP, Ua, operator, section, step};
use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::input::OPERATOR;
use crate::support::metrics::metric;
use crate::support::sim_process::ExternalSim;
use crate::support::wait::bounded;

/// The daemon on an external simulator: killed (the adapter unplugged),
/// a subscribed value turns `BadNoCommunication` (clients with no filter:
/// the default trigger).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn good_turns_bad_no_communication_when_the_adapter_goes_away() {
    bounded(LIMIT, async {
        let links = tempfile::tempdir().unwrap();
        let link = links.path().join("adapter");
        let sim = ExternalSim::start(&link, "1,2", &[]).await;
        let ua = Ua::start(Some(&link)).await;
        ua.d.wait_all_online(Duration::from_secs(30)).await;
        let mut c = Client::asyncua(&ua.url, "quality", &["--seconds".into(), "60".into()]);
        c.until("subscribed").await;
        loop {
            let v = c.until("value").await;
            if v["status"] == "Good" {
                break;
            }
        }
        sim.kill().await;
        let t0 = Instant::now();
        loop {
            let v = c.until("value").await;
            if v["status"] == "BadNoCommunication" {
                break;
            }
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
        c.kill().await;
    })
    .await;
}

/// An alarm of the book (a drive gone silent: offline) reaches both
/// clients, at once, as an AlarmConditionType event with their default
/// filters; acknowledged over OPC UA, the API shows it acknowledged.
/// The lift, silent here, is polled once a second, so that its data is
/// stale for a while before it is offline: its Speed in asyncua's
/// subscription (no filter: the default trigger) turns from `Good` to
/// `UncertainLastUsableValue` (its last value, kept) and then to
/// `BadNoCommunication`. Then the bus's variables say what the API's bus
/// view says (see [`buses_as_the_api_says`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_is_an_event_acknowledged_as_through_the_api() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let section = section(dir.path());
        let plant = ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.drive_keys("lift", "poll_interval_ms = 1000"));
        let ua = Ua::start_plant(plant, false, dir, section).await;
        let api = Api::new(ua.d.http, Some(OPERATOR));
        let pki = ua.pki.parent().unwrap().join("node-pki");
        let leg = |unit: u8, drive: &'static str, client: &'static str| {
            let (ua, api, pki) = (&ua, &api, &pki);
            async move {
                let mut args = operator();
                args.extend([
                    "--drive".into(),
                    drive.into(),
                    "--seconds".into(),
                    "40".into(),
                ]);
                let mut c = match client {
                    "asyncua" => Client::asyncua(&ua.url, "events", &args),
                    _ => Client::node(&ua.url, "events", pki, &args),
                };
                c.until("subscribed").await;
                ua.d.sim().set_silent(unit, true);
                // Until acknowledged, and asyncua's Speed is no value.
                let (mut statuses, mut acked) = (Vec::<String>::new(), None);
                while acked.is_none()
                    || (client == "asyncua"
                        && statuses.last().map(String::as_str) != Some("BadNoCommunication"))
                {
                    let v = c.next().await.unwrap_or_else(|| panic!("{client} ended"));
                    match v["step"].as_str() {
                        Some("value") => {
                            statuses.push(v["status"].as_str().unwrap_or_default().into())
                        }
                        Some("acknowledged") => acked = Some(v),
                        _ => {}
                    }
                }
                let acked = acked.unwrap_or_default();
                assert_eq!(acked["status"], "Good", "{client}: {acked}");
                let t0 = Instant::now();
                loop {
                    let list = api
                        .get(&format!("/api/v1/alarms?drive={drive}"))
                        .await
                        .expect(200);
                    let offline = list["alarms"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .find(|a| a["kind"] == "offline")
                        .cloned();
                    if offline.as_ref().is_some_and(|a| a["acknowledged"] == true) {
                        break;
                    }
                    assert!(t0.elapsed() < STEP, "{client}: not acknowledged: {list:#}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                c.kill().await;
                statuses
            }
        };
        let (mut statuses, _) =
            tokio::join!(leg(2, "lift", "asyncua"), leg(4, "feeder", "node-opcua"));
        statuses.dedup();
        assert_eq!(
            statuses,
            ["Good", "UncertainLastUsableValue", "BadNoCommunication"]
        );
        buses_as_the_api_says(&ua, &api).await;
    })
    .await;
}

/// `ua`'s bus variables (`Objects/Buses/sim`), read by asyncua, against
/// the API's view of the bus (`/api/v1/buses/sim`, read before and after)
/// with two of its four drives silent: its state, two drives online (once
/// the server's refresh, every second, has caught up), the silent drives'
/// timeouts and retries (counted, never ahead of the API), no CRC error,
/// bad reply or reopening, the utilisation as `/metrics` has it (in %);
/// and the silent lift's Speed read as `BadNoCommunication`.
async fn buses_as_the_api_says(ua: &Ua, api: &Api) {
    let t0 = Instant::now();
    let (before, read, after) = loop {
        let before = api.get("/api/v1/buses/sim").await.expect(200);
        let all = Client::asyncua(&ua.url, "read", &["--drive".into(), "lift".into()])
            .steps()
            .await;
        let read = step(&all, "read").clone();
        let after = api.get("/api/v1/buses/sim").await.expect(200);
        if read["buses"]["sim"]["DrivesOnline"]["value"] == after["drives_online"] {
            break (before, read, after);
        }
        assert!(t0.elapsed() < STEP, "{read}: {after:#}");
    };
    let bus = &read["buses"]["sim"];
    let value = |name: &str| -> &Value {
        assert_eq!(bus[name]["status"], "Good", "{name}: {bus}");
        &bus[name]["value"]
    };
    assert_eq!(value("State"), &after["state"], "{bus}: {after:#}");
    assert_eq!(
        (value("State"), value("Reason")),
        (&"up".into(), &"".into())
    );
    assert!(after["reason"].is_null(), "{after:#}");
    assert_eq!(value("DrivesOnline"), 2, "{bus}");
    assert_eq!(before["drives_online"], 2, "{before:#}");
    for (name, counter) in [
        ("Timeouts", "timeouts"),
        ("Retries", "retries"),
        ("CrcErrors", "crc_errors"),
        ("BadReplies", "bad_replies"),
        ("Reopens", "reopens"),
    ] {
        let opc = value(name)
            .as_u64()
            .unwrap_or_else(|| panic!("{name}: {bus}"));
        let api = after["counters"][counter].as_u64().unwrap_or_default();
        assert!(
            opc <= api,
            "{name} {opc} > {counter} {api}: {bus} {after:#}"
        );
        let counted = matches!(name, "Timeouts" | "Retries");
        assert_eq!(opc > 0, counted, "{name}: {bus}");
    }
    let ratio = metric(
        &ua.d.metrics.render(),
        "drivegate_bus_utilisation_ratio{bus=\"sim\"}",
    );
    let utilisation = value("Utilisation").as_f64().unwrap_or(-1.0);
    assert!(
        utilisation > 0.0 && (utilisation - ratio * 100.0).abs() < 15.0,
        "{utilisation} %, /metrics {ratio}: {bus}"
    );
    let speed = &read["values"]["Speed"];
    assert_eq!(speed["status"], "BadNoCommunication", "{speed}");
    assert_eq!(read["values"]["Online"]["value"], false, "{read}");
}
