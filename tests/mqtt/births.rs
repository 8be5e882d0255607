//! Births, bdSeq, seq, rebirth and DDATA by exception.

use std::time::Duration;

use drivegate::mqtt::metric::Value;

use super::{GROUP, NODE, config};
use crate::support::api::Api;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::{Host, Msg, number};
use crate::support::{TestDaemon, bounded};

const DRIVES: [&str; 4] = ["conveyor", "lift", "turntable", "feeder"];
const WAIT: Duration = Duration::from_secs(20);

/// NBIRTH then a DBIRTH per drive; returns the NBIRTH's bdSeq.
async fn births(host: &mut Host) -> (i64, Vec<Msg>) {
    let nbirth = host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
    assert_eq!(nbirth.topic, format!("spBv1.0/{GROUP}/NBIRTH/{NODE}"));
    assert_eq!(nbirth.seq(), Some(0), "an NBIRTH has seq 0");
    assert_eq!(
        nbirth.value("Node Control/Rebirth"),
        Some(Value::Bool(false))
    );
    let Some(Value::Int(bd_seq)) = nbirth.value("bdSeq") else {
        panic!("NBIRTH without an Int64 bdSeq: {:?}", nbirth.names());
    };
    // The bus's state as it is: on a loaded machine the node may be born
    // before the port has opened, and an NDATA says "up" once it has.
    let up = Some(Value::Text("up".into()));
    let mut bus_up = nbirth.value("buses/sim/state") == up;
    let mut dbirths = Vec::new();
    let mut seq = 0;
    while dbirths.len() < DRIVES.len() || !bus_up {
        let m = host
            .next(WAIT, "DBIRTH, or NDATA with the bus up", |m| {
                m.kind == "DBIRTH" || m.kind == "NDATA"
            })
            .await;
        seq += 1;
        assert_eq!(m.seq(), Some(seq), "seq counts on from the NBIRTH");
        if m.kind == "NDATA" {
            bus_up |= m.value("buses/sim/state") == up;
        } else {
            dbirths.push(m);
        }
    }
    let mut devices: Vec<String> = dbirths.iter().filter_map(|m| m.device.clone()).collect();
    devices.sort();
    let mut want: Vec<String> = DRIVES.iter().map(|d| d.to_string()).collect();
    want.sort();
    assert_eq!(
        devices, want,
        "one device per configured drive, named as it"
    );
    (bd_seq, dbirths)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn births_carry_bdseq_every_drive_and_units() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "births-host", None).await;
        let d = TestDaemon::start(&config(&broker.url(), "")).await;
        let (bd_seq, dbirths) = births(&mut host).await;
        assert_eq!(bd_seq, 0, "the first connection's bdSeq");
        let dbirth = &dbirths[0];
        for name in [
            "status/speed_rpm",
            "status/angle_deg",
            "status/turns",
            "status/current_a",
            "status/voltage_v",
            "status/temperature_c",
            "status/active",
            "status/stalled",
            "status/mode",
            "status/fault",
            "status/fault_code",
            "command/activate",
            "command/deactivate",
            "command/brake",
            "command/fault_reset",
            "mode",
            "setpoint/speed_rpm",
            "setpoint/position_deg",
            "setpoint/torque_a",
            "command/last_result",
        ] {
            assert!(dbirth.metric(name).is_some(), "DBIRTH lacks {name}");
        }
        // Units in the metric's properties, as SCADA hosts read them.
        let speed = dbirth.metric("status/speed_rpm").unwrap();
        let props = speed.properties.as_ref().expect("properties");
        let unit = props
            .keys
            .iter()
            .position(|k| k == "engUnit")
            .expect("an engUnit property");
        assert_eq!(
            props.values[unit].value,
            Some(
                drivegate::mqtt::sparkplug_b::payload::property_value::Value::StringValue(
                    "rpm".into()
                )
            )
        );
        assert!(matches!(
            dbirth.value("status/voltage_v"),
            Some(Value::UInt(v)) if v > 0
        ));
        assert_eq!(
            drivegate_metric(&d, "drivegate_mqtt_connected"),
            1.0,
            "/metrics says connected"
        );
        let ready: serde_json::Value = reqwest::get(d.url("/readyz"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        assert_eq!(ready["mqtt"]["publishing"], true, "{ready:#}");
        assert_eq!(ready["mqtt"]["broker"], broker.url(), "{ready:#}");
        d.stop().await;
        // A graceful stop says goodbye with the same bdSeq.
        let ndeath = host.next(WAIT, "NDEATH", |m| m.is("NDEATH", None)).await;
        assert_eq!(ndeath.value("bdSeq"), Some(Value::Int(bd_seq)));
        assert_eq!(ndeath.seq(), None, "an NDEATH has no seq");
    })
    .await;
}

fn drivegate_metric(d: &TestDaemon, name: &str) -> f64 {
    crate::support::metrics::counter(d, name)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rebirth_republishes_the_births_with_the_same_bdseq() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "rebirth-host", None).await;
        let d = TestDaemon::start(&config(&broker.url(), "")).await;
        let (bd_seq, _) = births(&mut host).await;
        host.rebirth(GROUP, NODE).await;
        let (again, _) = births(&mut host).await;
        assert_eq!(again, bd_seq, "a rebirth keeps the bdSeq");
        assert!(
            !host.seen.iter().any(|m| m.kind == "NDEATH"),
            "a rebirth does not disconnect"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ddata_carries_only_what_moved_past_its_deadband() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "ddata-host", None).await;
        // Deadbands wide enough that a drive at rest publishes nothing.
        let d = TestDaemon::start(&config(
            &broker.url(),
            "[mqtt.deadbands]\nspeed_rpm = 5.0\nangle_deg = 1.0\ncurrent_a = 0.5\nvoltage_v = 2.0\ntemperature_c = 2.0",
        ))
        .await;
        let (_, dbirths) = births(&mut host).await;
        let born = |device: &str, name: &str| {
            dbirths
                .iter()
                .find(|m| m.device.as_deref() == Some(device))
                .and_then(|m| m.value(name))
                .and_then(|v| number(&v))
        };
        // Run the conveyor through the HTTP API: its speed, angle and turns
        // change; the other drives stay at rest.
        let api = Api::new(d.http, None);
        api.activate_in("conveyor", "speed").await;
        api.put(
            "/api/v1/drives/conveyor/setpoint",
            serde_json::json!({"speed_rpm": 100}),
        )
        .await
        .expect(200);
        let fast = host
            .next(WAIT, "the conveyor's speed in a DDATA", |m| {
                m.is("DDATA", Some("conveyor"))
                    && m.value("status/speed_rpm")
                        .and_then(|v| number(&v))
                        .is_some_and(|s| s > 50.0)
            })
            .await;
        assert!(fast.metric("status/fault").is_none(), "an unchanged fault is not sent again");
        // Every DDATA so far: only metrics that moved past their band since
        // the value last published for that device.
        let mut last: std::collections::BTreeMap<(String, String), f64> = Default::default();
        for m in host.seen.iter().filter(|m| m.kind == "DDATA") {
            let device = m.device.clone().unwrap();
            assert_ne!(device, "lift", "a drive at rest publishes nothing: {:?}", m.names());
            for metric in &m.payload.as_ref().unwrap().metrics {
                let name = metric.name.clone().unwrap();
                let value = drivegate::mqtt::metric::value_of(metric);
                let Some(now) = number(&value) else { continue };
                let band = match name.as_str() {
                    "status/speed_rpm" => 5.0,
                    "status/angle_deg" => 1.0,
                    "status/current_a" => 0.5,
                    "status/voltage_v" => 2.0,
                    "status/temperature_c" => 2.0,
                    _ => 0.0,
                };
                let before = last
                    .get(&(device.clone(), name.clone()))
                    .copied()
                    .or_else(|| born(&device, &name));
                if let Some(before) = before {
                    assert!(
                        (now - before).abs() > band,
                        "{device} {name}: {before} -> {now} is within its deadband {band}"
                    );
                }
                last.insert((device.clone(), name), now);
            }
        }
        // Seq keeps counting, 0-255, across the births and the data.
        let seqs: Vec<u64> = host.seen.iter().filter_map(|m| m.seq()).collect();
        for pair in seqs.windows(2) {
            assert_eq!(pair[1], (pair[0] + 1) % 256, "seq in order: {seqs:?}");
        }
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_that_stops_answering_dies_and_is_born_again() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "ddeath-host", None).await;
        let toml = crate::support::config::ConfigBuilder::four_drives()
            .modbus_tcp_off()
            .with_bus("sim", |b| b.keys("offline_backoff_max_ms = 300"))
            .section(
                "mqtt",
                &format!(
                    "broker = \"{}\"\ngroup_id = \"{GROUP}\"\nnode_id = \"{NODE}\"",
                    broker.url()
                ),
            )
            .toml();
        let d = TestDaemon::start(&toml).await;
        births(&mut host).await;
        d.sim().set_silent(2, true);
        let ddeath = host
            .next(WAIT, "the lift's DDEATH", |m| m.is("DDEATH", Some("lift")))
            .await;
        assert!(ddeath.seq().is_some(), "a DDEATH has a seq");
        d.sim().set_silent(2, false);
        let dbirth = host
            .next(WAIT, "the lift's DBIRTH again", |m| {
                m.is("DBIRTH", Some("lift"))
            })
            .await;
        assert!(matches!(dbirth.value("status/voltage_v"), Some(Value::UInt(v)) if v > 0));
        d.stop().await;
    })
    .await;
}
