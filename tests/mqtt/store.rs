//! Store and forward through a real broker: mosquitto stopped for 5 s
//! while a drive turns; the data of those seconds reaches the host after
//! the births, marked historical, and the drive's data has no gap. Then
//! the store across a restart of the daemon, and a drive offline at the
//! reconnect whose kept data waits for its birth.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::{GROUP, NODE};
use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::metrics::counter;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{Host, Msg};
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The plant of the MQTT tests (`super::config`'s) with its state
/// directory in `dir`.
fn with_store(broker: &Mosquitto, dir: &std::path::Path) -> String {
    ConfigBuilder::four_drives()
        .modbus_tcp_off()
        .section("safety", &format!("state_dir = \"{}\"", dir.display()))
        .section(
            "mqtt",
            &format!(
                "broker = \"{}\"\ngroup_id = \"{GROUP}\"\nnode_id = \"{NODE}\"",
                broker.url()
            ),
        )
        .toml()
}

/// The conveyor's angle samples in a DDATA: (data timestamp, historical).
fn angles(m: &Msg) -> Vec<(u64, bool)> {
    if !m.is("DDATA", Some("conveyor")) {
        return Vec::new();
    }
    m.payload
        .iter()
        .flat_map(|p| &p.metrics)
        .filter(|x| x.name.as_deref() == Some("status/angle_deg"))
        .filter_map(|x| Some((x.timestamp?, x.is_historical == Some(true))))
        .collect()
}

/// Notes the conveyor's angle samples in `m`: every one in `seen`
/// (timestamp -> historical), the live ones in `live` too.
fn note(m: &Msg, seen: &mut BTreeMap<u64, bool>, live: &mut BTreeSet<u64>) {
    for (t, historical) in angles(m) {
        if !historical {
            live.insert(t);
        }
        seen.insert(t, historical);
    }
}

/// Activates the conveyor and turns it (no lease: nothing ends it).
async fn turn(d: &TestDaemon) {
    let api = Api::new(d.http, None);
    api.activate_in("conveyor", "speed").await;
    api.put(
        "/api/v1/drives/conveyor/setpoint",
        serde_json::json!({ "speed_rpm": 100 }),
    )
    .await
    .expect(200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broker_outage_is_replayed_as_historical_data_without_a_gap() {
    bounded(Duration::from_secs(120), async {
        let mut broker = Mosquitto::start();
        let state = tempfile::tempdir().unwrap();
        let mut host = Host::connect(broker.port, "store-host", None).await;
        let d = TestDaemon::start(&with_store(&broker, state.path())).await;
        turn(&d).await;
        // The host's view of the conveyor: data timestamp -> historical;
        // and the timestamps it had live.
        let mut seen: BTreeMap<u64, bool> = BTreeMap::new();
        let mut live: BTreeSet<u64> = BTreeSet::new();
        while seen.len() < 20 {
            let m = host
                .next(WAIT, "the conveyor's live DDATA", |m| !angles(m).is_empty())
                .await;
            note(&m, &mut seen, &mut live);
        }
        let first = seen.keys().next().copied().unwrap_or(0);

        let before = unix_ms();
        broker.stop();
        eventually(WAIT, "the face to see the broker gone", || {
            (counter(&d, "drivegate_mqtt_connected") == 0.0).then_some(())
        })
        .await;
        let cut = tokio::time::Instant::now();
        eventually(WAIT, "the conveyor's data kept in the store", || {
            (counter(&d, "drivegate_mqtt_store_messages") >= 20.0).then_some(())
        })
        .await;
        // The outage the scenario is about: 5 s without a broker.
        tokio::time::sleep_until(cut + Duration::from_secs(5)).await;
        let stored = counter(&d, "drivegate_mqtt_store_messages");
        assert!(counter(&d, "drivegate_mqtt_store_bytes") > 0.0);
        broker.resume();
        let back = unix_ms();

        // Until the store is empty and live data follows what it replayed.
        let mut emptied_at = None;
        loop {
            let m = host
                .next(WAIT, "the conveyor's DDATA after the outage", |m| {
                    !angles(m).is_empty()
                })
                .await;
            note(&m, &mut seen, &mut live);
            if emptied_at.is_none()
                && counter(&d, "drivegate_mqtt_connected") == 1.0
                && counter(&d, "drivegate_mqtt_store_messages") == 0.0
            {
                emptied_at = Some(unix_ms());
            }
            if let Some(t) = emptied_at
                && seen.range(t..).any(|(_, h)| !h)
            {
                break;
            }
        }
        let after = emptied_at.unwrap();
        let historical: Vec<u64> = seen.iter().filter(|(_, h)| **h).map(|(t, _)| *t).collect();
        assert!(
            historical.len() as f64 >= stored.min(20.0),
            "{} historical samples at the host; the store held {stored} messages",
            historical.len()
        );
        // The historical data is what the host did not have live (a busy
        // machine may keep data in flight for a second or more, and keeps
        // it too), polled in this run before the broker was back.
        assert!(
            historical
                .iter()
                .all(|t| !live.contains(t) && *t >= first && *t <= back + 5000),
            "historical samples the host had live, or from outside {first}..{back}: {historical:?}"
        );
        // Nothing lost: from before the outage to after the replay the
        // drive's data, live and historical together, has no gap longer
        // than a few polls; a lost second of the outage would leave one.
        let ts: Vec<u64> = seen.range(before - 500..=after).map(|(t, _)| *t).collect();
        let gap = ts.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(u64::MAX);
        assert!(
            gap < 1000,
            "a gap of {gap} ms in the conveyor's data around the outage"
        );
        assert_eq!(counter(&d, "drivegate_mqtt_store_dropped_total"), 0.0);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn data_kept_while_the_broker_was_away_survives_a_restart_of_the_daemon() {
    bounded(Duration::from_secs(120), async {
        let mut broker = Mosquitto::start();
        let state = tempfile::tempdir().unwrap();
        let toml = with_store(&broker, state.path());
        let mut host = Host::connect(broker.port, "store-restart-host", None).await;
        let d = TestDaemon::start(&toml).await;
        turn(&d).await;
        host.next(WAIT, "the conveyor's live DDATA", |m| !angles(m).is_empty())
            .await;
        broker.stop();
        let cut = unix_ms();
        eventually(WAIT, "the conveyor's data kept in the store", || {
            (counter(&d, "drivegate_mqtt_store_messages") >= 20.0).then_some(())
        })
        .await;
        d.stop().await;
        let stopped = unix_ms();
        broker.resume();

        // The next daemon on the same state directory replays the first
        // one's data after its births.
        let d = TestDaemon::start(&toml).await;
        let m = host
            .next(WAIT, "historical DDATA from before the restart", |m| {
                angles(m).iter().any(|(_, h)| *h)
            })
            .await;
        let (t, _) = angles(&m)[0];
        assert!(
            (cut - 1000..=stopped).contains(&t),
            "{t} not in {cut}..{stopped}"
        );
        eventually(WAIT, "the store replayed", || {
            (counter(&d, "drivegate_mqtt_store_messages") == 0.0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drives_kept_data_waits_for_its_birth_when_it_is_offline_at_the_reconnect() {
    bounded(Duration::from_secs(120), async {
        let mut broker = Mosquitto::start();
        let state = tempfile::tempdir().unwrap();
        let mut host = Host::connect(broker.port, "wait-host", None).await;
        let d = TestDaemon::start(&with_store(&broker, state.path())).await;
        turn(&d).await;
        host.next(WAIT, "the conveyor's live DDATA", |m| !angles(m).is_empty())
            .await;
        broker.stop();
        let cut = unix_ms();
        eventually(WAIT, "the conveyor's data kept in the store", || {
            (counter(&d, "drivegate_mqtt_store_messages") >= 20.0).then_some(())
        })
        .await;
        // The conveyor stops answering before the broker is back: it is
        // not born at the reconnect.
        d.sim().set_silent(1, true);
        eventually(WAIT, "the conveyor offline", || {
            let link = d.plant.buses()[0].handle.drive(1)?.link;
            (link == drivegate::bus::cache::Link::Offline).then_some(())
        })
        .await;
        let silenced = unix_ms();
        let kept = counter(&d, "drivegate_mqtt_store_messages");
        broker.resume();
        host.next(WAIT, "the NBIRTH after the outage", |m| {
            m.is("NBIRTH", None)
        })
        .await;
        // (What came before, the start-up's own kept data included, is not
        // this outage's.)
        let reborn_at = host.seen.len() - 1;
        // The store is read while the conveyor is still offline: its data
        // waits for the birth instead of being dropped.
        eventually(WAIT, "the store read for the replay", || {
            (counter(&d, "drivegate_mqtt_store_messages") == 0.0).then_some(())
        })
        .await;
        d.sim().set_silent(1, false);
        let birth = host
            .next(WAIT, "the conveyor's DBIRTH", |m| {
                m.is("DBIRTH", Some("conveyor"))
            })
            .await;
        let birth_at = host.seen.len() - 1;
        let mut historical = 0;
        while (historical as f64) < kept.min(20.0) {
            let m = host
                .next(WAIT, "the conveyor's kept data, replayed", |m| {
                    angles(m).iter().any(|(_, h)| *h)
                })
                .await;
            for (t, h) in angles(&m) {
                if h {
                    assert!(
                        (cut - 1000..=silenced).contains(&t),
                        "historical data from {t}, outside the outage {cut}..{silenced}"
                    );
                    historical += 1;
                }
            }
        }
        // None of it reached the host before the conveyor's birth.
        let first = reborn_at
            + host.seen[reborn_at..]
                .iter()
                .position(|m| angles(m).iter().any(|(_, h)| *h))
                .unwrap();
        assert!(
            first > birth_at,
            "historical data of the conveyor at {first}, before its DBIRTH at {birth_at} ({})",
            birth.topic
        );
        assert_eq!(counter(&d, "drivegate_mqtt_replay_dropped_total"), 0.0);
        d.stop().await;
    })
    .await;
}
