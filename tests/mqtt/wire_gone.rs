//! The truth when the wire is gone: the daemon runs on an external
//! simulator (`drivegate sim --link`, a process of its own, as a USB
//! adapter would be), with every face on; the simulator is killed (its pty
//! goes, the link is left dangling) and started again at the same link.
//! Each face is watched at once, side by side, and must say within 3 s
//! that the data is not live (and again that it is, once the adapter is
//! back): REST (`freshness`), the stream's `freshness` messages,
//! `/readyz`, `/metrics`, Modbus TCP (exception 0x0A), and MQTT, Sparkplug
//! (DDEATH per drive, `buses/<bus>/state`) in one test and the JSON format
//! (retained status, event) in its sibling. The time each face took is
//! printed (`--nocapture`).

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use drivegate::mqtt::metric::Value as MetricValue;
use futures_util::StreamExt;
use serde_json::Value;
use tokio_tungstenite::tungstenite::Message;

use super::{GROUP, NODE};
use crate::support::api::{Api, connect};
use crate::support::config::ConfigBuilder;
use crate::support::faults::Scrape;
use crate::support::modbus_tcp::Raw;
use crate::support::mosquitto::{Mosquitto, Sub};
use crate::support::sim_process::ExternalSim;
use crate::support::sparkplug::Host;
use crate::support::{TestDaemon, bounded};

/// What every face must show the cut (and the return) within.
const FACE_LIMIT: Duration = Duration::from_secs(3);
const BUS: &str = "line1";
const DRIVES: [(&str, u8); 2] = [("conveyor", 1), ("belt", 2)];
/// The status block's read (manual 1.7): 7 registers at 0x00C0.
const STATUS_READ: [u8; 5] = [0x03, 0x00, 0xC0, 0x00, 0x07];

/// The daemon on `link` with every face on and `[mqtt]` with `mqtt`.
fn config(link: &Path, broker: &str, mqtt: &str) -> String {
    ConfigBuilder::new()
        .bus(BUS, |b| {
            b.port(&link.display().to_string())
                .drive(1, "conveyor")
                .drive(2, "belt")
        })
        .section(
            "mqtt",
            &format!("broker = \"{broker}\"\ngroup_id = \"{GROUP}\"\nnode_id = \"{NODE}\"\n{mqtt}"),
        )
        .toml()
}

/// Polls `check` every 20 ms until it holds; the time since `t0` when it
/// did. Fails naming `what` (and the last thing seen) after `limit`.
async fn until<F, Fut>(t0: Instant, limit: Duration, what: &str, mut check: F) -> Duration
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<(), String>>,
{
    loop {
        let last = match check().await {
            Ok(()) => return t0.elapsed(),
            Err(last) => last,
        };
        assert!(
            t0.elapsed() < limit,
            "{what}: not shown within {limit:?} (last seen: {last})"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Whether the wire is cut (every drive's data `bus-down`) or back (every
/// drive `live`).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Cut,
    Back,
}

impl Phase {
    fn freshness(self) -> &'static str {
        match self {
            Phase::Cut => "bus-down",
            Phase::Back => "live",
        }
    }
}

/// REST: every drive's `freshness`, `link`, why and since when, and the
/// status's age kept.
async fn rest(api: &Api, phase: Phase) -> Result<(), String> {
    let drives = api.get("/api/v1/drives").await.expect(200);
    for d in drives.as_array().into_iter().flatten() {
        let ok = match phase {
            Phase::Cut => {
                d["freshness"] == "bus-down"
                    && d["link"] == "offline"
                    && d["online"] == false
                    && d["freshness_since"].is_string()
                    && d["age_ms"].is_u64()
                    && d["status"].is_object()
                    && d["freshness_reason"]
                        .as_str()
                        .is_some_and(|r| r.starts_with(&format!("bus {BUS} is down: ")))
            }
            Phase::Back => {
                d["freshness"] == "live"
                    && d["link"] == "online"
                    && d["freshness_reason"].is_null()
                    && d["freshness_since"].is_null()
            }
        };
        if !ok {
            return Err(d.to_string());
        }
    }
    // The status route says the same, the last value with its age.
    let s = api.get("/api/v1/drives/conveyor/status").await.expect(200);
    if s["freshness"] != phase.freshness() || !s["speed_rpm"].is_i64() {
        return Err(s.to_string());
    }
    Ok(())
}

/// `/readyz`: only live drives count.
async fn readyz(api: &Api, phase: Phase) -> Result<(), String> {
    let r = api.get("/readyz").await;
    let body = r.body;
    let bus = &body["buses"][0];
    let ok = match phase {
        Phase::Cut => {
            r.status == 503
                && bus["drives_online"] == 0
                && bus["port_open"] == false
                && body["reasons"].as_array().is_some_and(|rs| {
                    rs.iter().any(|x| {
                        x.as_str()
                            .is_some_and(|x| x.starts_with(&format!("bus {BUS}: the port is down")))
                    })
                })
        }
        Phase::Back => r.status == 200 && bus["drives_online"] == 2,
    };
    if ok {
        Ok(())
    } else {
        Err(format!("{} {body}", r.status))
    }
}

/// `/metrics`: `drive_up` 0 and the freshness `bus-down` (or back), the
/// values gone while not live.
async fn metrics(api: &Api, phase: Phase) -> Result<(), String> {
    let text = reqwest::get(api.url("/metrics"))
        .await
        .map_err(|e| e.to_string())?
        .text()
        .await
        .map_err(|e| e.to_string())?;
    let s = Scrape::parse(&text);
    for (name, unit) in DRIVES {
        let unit = unit.to_string();
        let l = [("bus", BUS), ("unit", unit.as_str()), ("name", name)];
        let up = s.get("drivegate_drive_up", &l);
        let mut with = l.to_vec();
        with.push(("freshness", phase.freshness()));
        let state = s.get("drivegate_drive_freshness", &with);
        let speeds =
            s.0.iter()
                .filter(|x| {
                    x.name == "drivegate_drive_speed_rpm"
                        && x.labels.get("name").map(String::as_str) == Some(name)
                })
                .count();
        let ok = match phase {
            Phase::Cut => up == 0.0 && state == 1.0 && speeds == 0,
            Phase::Back => up == 1.0 && state == 1.0 && speeds == 1,
        };
        if !ok {
            return Err(format!(
                "{name}: up {up}, {} {state}, speed series {speeds}",
                phase.freshness()
            ));
        }
    }
    Ok(())
}

/// Modbus TCP: a status read of unit 1 answered by the drive, or with
/// exception 0x0A (the gateway's path is gone) while the bus is down.
async fn modbus(addr: std::net::SocketAddr, phase: Phase) -> Result<(), String> {
    let mut raw = Raw::connect(addr).await;
    let reply = raw.ask(1, &STATUS_READ).await;
    let ok = match phase {
        Phase::Cut => reply == [0x83, 0x0A],
        Phase::Back => reply.len() == 2 + 14 && reply[0] == 0x03,
    };
    if ok {
        Ok(())
    } else {
        Err(format!("{reply:02X?}"))
    }
}

/// The stream's messages other than statuses, with when they came.
type Heard = Arc<Mutex<Vec<(Instant, Value)>>>;

/// Reads the stream (subscribed to every drive) in a task of its own.
async fn listen(addr: std::net::SocketAddr) -> Heard {
    let mut ws = connect(addr, "?drives=all", None).await;
    let heard: Heard = Arc::default();
    let keep = heard.clone();
    tokio::spawn(async move {
        while let Some(Ok(m)) = ws.next().await {
            if let Message::Text(t) = m
                && let Ok(v) = serde_json::from_str::<Value>(t.as_str())
                && v["type"] != "status"
            {
                keep.lock().unwrap().push((Instant::now(), v));
            }
        }
    });
    heard
}

/// The stream: a `freshness` message per drive since `t0`, saying
/// `bus-down` with why (or `live`).
fn stream(heard: &Heard, t0: Instant, phase: Phase) -> Result<(), String> {
    let heard = heard.lock().unwrap();
    let told = |drive: &str| {
        heard.iter().any(|(at, m)| {
            *at >= t0
                && m["type"] == "freshness"
                && m["drive"] == drive
                && m["freshness"] == phase.freshness()
                && match phase {
                    Phase::Cut => {
                        m["freshness_reason"]
                            .as_str()
                            .is_some_and(|r| r.contains("is down"))
                            && m["age_ms"].is_u64()
                    }
                    Phase::Back => m["freshness_reason"].is_null(),
                }
        })
    };
    if DRIVES.iter().all(|(d, _)| told(d)) {
        Ok(())
    } else {
        let last: Vec<&Value> = heard.iter().rev().take(4).map(|(_, m)| m).collect();
        Err(format!("{last:?}"))
    }
}

/// Sparkplug: a DDEATH per drive and `buses/line1/state` down (or a
/// DBIRTH per drive and the state up), since the host's last look.
async fn sparkplug(host: &mut Host, t0: Instant, phase: Phase) -> Duration {
    let (kind, state) = match phase {
        Phase::Cut => ("DDEATH", "down"),
        Phase::Back => ("DBIRTH", "up"),
    };
    let metric = format!("buses/{BUS}/state");
    let mut devices: Vec<String> = Vec::new();
    let mut state_seen = false;
    while devices.len() < DRIVES.len() || !state_seen {
        let left = FACE_LIMIT.saturating_sub(t0.elapsed());
        let m = host
            .next(
                left,
                &format!("{kind} of every drive and {metric} {state}"),
                |m| m.kind == kind || (m.kind == "NDATA" && m.metric(&metric).is_some()),
            )
            .await;
        if m.kind == kind {
            devices.extend(m.device.clone());
        } else if m.value(&metric) == Some(MetricValue::Text(state.into())) {
            state_seen = true;
        }
    }
    devices.sort();
    assert_eq!(devices, ["belt", "conveyor"], "one {kind} per drive");
    t0.elapsed()
}

/// The JSON format: each drive's retained status republished with its
/// freshness, and its `freshness` event.
async fn json_face(sub: &mut Sub, t0: Instant, phase: Phase) -> Duration {
    let mut status = Vec::new();
    let mut events = Vec::new();
    while status.len() < DRIVES.len() || events.len() < DRIVES.len() {
        let left = FACE_LIMIT.saturating_sub(t0.elapsed());
        let m = sub
            .next(
                left,
                &format!("statuses and events saying {}", phase.freshness()),
                |m| m.json()["freshness"] == phase.freshness(),
            )
            .await;
        let v = m.json();
        let drive = v["drive"].as_str().unwrap_or("").to_string();
        if m.topic.ends_with("/status") && !m.retained {
            assert!(v["speed_rpm"].is_i64(), "{v}");
            if !status.contains(&drive) {
                status.push(drive);
            }
        } else if m.topic.ends_with("/event")
            && v["type"] == "freshness"
            && !events.contains(&drive)
        {
            events.push(drive);
        }
    }
    t0.elapsed()
}

/// Each face's time, printed and checked against [`FACE_LIMIT`].
fn report(what: &str, times: &[(&str, Duration)]) {
    let line: Vec<String> = times
        .iter()
        .map(|(f, t)| format!("{f} {} ms", t.as_millis()))
        .collect();
    eprintln!("{what}: {}", line.join(", "));
    for (face, t) in times {
        assert!(*t <= FACE_LIMIT, "{what}: {face} took {t:?}");
    }
}

/// The faces but MQTT, side by side, since `t0`.
async fn common_faces(
    api: &Api,
    modbus_addr: std::net::SocketAddr,
    heard: &Heard,
    t0: Instant,
    phase: Phase,
) -> Vec<(&'static str, Duration)> {
    let (r, y, m, t, s) = tokio::join!(
        until(t0, FACE_LIMIT, "REST", || rest(api, phase)),
        until(t0, FACE_LIMIT, "/readyz", || readyz(api, phase)),
        until(t0, FACE_LIMIT, "/metrics", || metrics(api, phase)),
        until(t0, FACE_LIMIT, "Modbus TCP", || modbus(modbus_addr, phase)),
        until(t0, FACE_LIMIT, "the stream", || std::future::ready(stream(
            heard, t0, phase
        ))),
    );
    vec![
        ("REST", r),
        ("readyz", y),
        ("metrics", m),
        ("Modbus TCP", t),
        ("stream", s),
    ]
}

/// The plant as it runs, ready: every face live.
struct Rig {
    _dir: tempfile::TempDir,
    link: PathBuf,
    sim: Option<ExternalSim>,
    daemon: TestDaemon,
    api: Api,
    heard: Heard,
}

impl Rig {
    async fn start(broker: &Mosquitto, mqtt: &str) -> Rig {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-drives");
        let sim = ExternalSim::start(&link, "1-2", &[]).await;
        let daemon = TestDaemon::start(&config(&link, &broker.url(), mqtt)).await;
        let api = Api::new(daemon.http, None);
        let heard = listen(daemon.http).await;
        let t0 = Instant::now();
        let modbus_addr = daemon.modbus_tcp.expect("Modbus TCP on");
        // Live everywhere first (generously: this is the start, not the
        // cut).
        let slow = Duration::from_secs(20);
        until(t0, slow, "REST live", || rest(&api, Phase::Back)).await;
        until(t0, slow, "ready", || readyz(&api, Phase::Back)).await;
        until(t0, slow, "metrics live", || metrics(&api, Phase::Back)).await;
        until(t0, slow, "Modbus TCP", || modbus(modbus_addr, Phase::Back)).await;
        Rig {
            _dir: dir,
            link,
            sim: Some(sim),
            daemon,
            api,
            heard,
        }
    }

    fn modbus(&self) -> std::net::SocketAddr {
        self.daemon.modbus_tcp.expect("Modbus TCP on")
    }

    /// Kills the simulator: the moment of the cut.
    async fn cut(&mut self) -> Instant {
        let sim = self.sim.take().expect("the simulator runs");
        let t0 = Instant::now();
        sim.kill().await;
        t0
    }

    /// Starts the simulator again at the same link: the moment it serves.
    async fn plug_back(&mut self) -> Instant {
        self.sim = Some(ExternalSim::start(&self.link, "1-2", &[]).await);
        Instant::now()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_adapter_unplugged_is_shown_by_every_face_and_sparkplug_within_3_s() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "wire-gone-host", None).await;
        let mut rig = Rig::start(&broker, "").await;
        // Both drives born at the host.
        let mut born = Vec::new();
        while born.len() < DRIVES.len() {
            let m = host
                .next(Duration::from_secs(20), "the DBIRTHs", |m| {
                    m.kind == "DBIRTH"
                })
                .await;
            born.extend(m.device);
        }

        let t0 = rig.cut().await;
        let (common, spb) = tokio::join!(
            common_faces(&rig.api, rig.modbus(), &rig.heard, t0, Phase::Cut),
            sparkplug(&mut host, t0, Phase::Cut),
        );
        let mut times = common;
        times.push(("Sparkplug", spb));
        report("cut", &times);
        // While down, the status route keeps the last value with its age,
        // and a drive never read would say why.
        let s = rig.api.get("/api/v1/drives/belt/status").await.expect(200);
        assert_eq!(s["freshness"], "bus-down", "{s}");
        assert_eq!(s["link"], "offline", "{s}");

        let t1 = rig.plug_back().await;
        let (common, spb) = tokio::join!(
            common_faces(&rig.api, rig.modbus(), &rig.heard, t1, Phase::Back),
            sparkplug(&mut host, t1, Phase::Back),
        );
        let mut times = common;
        times.push(("Sparkplug", spb));
        report("back", &times);
        rig.daemon.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_adapter_unplugged_is_shown_by_every_face_and_mqtt_json_within_3_s() {
    bounded(Duration::from_secs(90), async {
        let broker = Mosquitto::start();
        let prefix = format!("drivegate/{NODE}");
        let state = format!("{prefix}/state");
        let (status, event) = (format!("{prefix}/+/status"), format!("{prefix}/+/event"));
        let mut sub = Sub::start(broker.port, &[&state, &status, &event]);
        let mut rig = Rig::start(&broker, "format = \"json\"").await;
        sub.next(Duration::from_secs(20), "a live status", |m| {
            m.topic.ends_with("/status") && m.json()["freshness"] == "live"
        })
        .await;

        let t0 = rig.cut().await;
        let (common, json) = tokio::join!(
            common_faces(&rig.api, rig.modbus(), &rig.heard, t0, Phase::Cut),
            json_face(&mut sub, t0, Phase::Cut),
        );
        let mut times = common;
        times.push(("MQTT JSON", json));
        report("cut", &times);

        let t1 = rig.plug_back().await;
        let (common, json) = tokio::join!(
            common_faces(&rig.api, rig.modbus(), &rig.heard, t1, Phase::Back),
            json_face(&mut sub, t1, Phase::Back),
        );
        let mut times = common;
        times.push(("MQTT JSON", json));
        report("back", &times);
        // A client that subscribes now gets the truth retained.
        let mut late = Sub::start(broker.port, &[&status]);
        let m = late
            .next(Duration::from_secs(10), "the retained status", |m| {
                m.retained
            })
            .await;
        assert_eq!(m.json()["freshness"], "live", "{}", m.payload);
        rig.daemon.stop().await;
    })
    .await;
}
