//! A reload touches only what it changes: with a motor turning at 100 rpm,
//! a poll-rate change, a rename of another drive, a drive added and one
//! removed are applied to the running bus without closing its port. The
//! motor turns on through each (the simulator's own state, or the status
//! the drive itself reports on an external `drivegate sim --link`), and
//! its REST status answers 200, live, at every read made every 50 ms;
//! MQTT kills and births only the devices that changed. A reload that
//! reopens the bus (the baud rate of the built-in simulator) finds its
//! drives as they were, with the pause said in `paused`; one that does
//! stop the motor (the drive removed, its bus moved to another port) says
//! so in `stopped`, as the drive then shows. One daemon per simulator
//! through every reload.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::support::api::{Api, Reply};
use crate::support::config::ConfigBuilder;
use crate::support::mosquitto::Mosquitto;
use crate::support::sim_process::ExternalSim;
use crate::support::sparkplug::{Host, Msg};
use crate::support::{TestDaemon, bounded, eventually};
use drivegate::plant::SimRef;

const LIMIT: Duration = Duration::from_secs(120);
/// Longest wait for an event the design says must come.
const EVENT: Duration = Duration::from_secs(20);
const ADMIN: &str = "in-place-admin-token";
/// How often the turning motor's status is read through the reloads.
const EVERY: Duration = Duration::from_millis(50);

/// Reads `drive`'s REST status every [`EVERY`] until stopped, checking
/// each read: 200, live, at 100 rpm as the drive reports it and, on the
/// built-in simulator, as the simulated drive itself turns.
struct Watch {
    done: Arc<AtomicBool>,
    task: tokio::task::JoinHandle<Vec<String>>,
    started: Instant,
    /// Reads made so far.
    made: tokio::sync::watch::Receiver<usize>,
}

impl Watch {
    fn start(api: &Api, drive: &str, sim: Option<SimRef>) -> Watch {
        let (api, path) = (api.clone(), format!("/api/v1/drives/{drive}/status"));
        let done = Arc::new(AtomicBool::new(false));
        let stop = done.clone();
        let (count, made) = tokio::sync::watch::channel(0);
        let task = tokio::spawn(async move {
            let mut reads = Vec::new();
            let mut tick = tokio::time::interval(EVERY);
            while !stop.load(Ordering::Relaxed) {
                tick.tick().await;
                let reply = api.get(&path).await;
                let own = sim.as_ref().and_then(|s| s.drive(1));
                reads.push(read_fault(&reply, own.as_ref()).unwrap_or_default());
                count.send_replace(reads.len());
            }
            reads
        });
        Watch {
            done,
            task,
            started: Instant::now(),
            made,
        }
    }

    /// Waits for `n` more reads: each reload is read through, with reads
    /// before and after it.
    async fn more(&mut self, n: usize) {
        let at = *self.made.borrow_and_update() + n;
        tokio::time::timeout(EVENT, self.made.wait_for(|&made| made >= at))
            .await
            .expect("the reads go on")
            .expect("the reader runs");
    }

    /// Stops reading; fails on any read that was not as it should be, or
    /// too few reads for the time (a read held up by a reload is one).
    async fn finish(self, what: &str) -> usize {
        self.done.store(true, Ordering::Relaxed);
        let reads = self.task.await.unwrap();
        let bad: Vec<&String> = reads.iter().filter(|r| !r.is_empty()).collect();
        assert!(
            bad.is_empty(),
            "{what}: reads that were not 200 at 100 rpm: {bad:?}"
        );
        // A loaded machine may run the reader late; never a tenth as often.
        let due = self.started.elapsed().as_millis() / EVERY.as_millis();
        assert!(
            reads.len() as u128 * 10 >= due,
            "{what}: {} reads in {:?}",
            reads.len(),
            self.started.elapsed()
        );
        reads.len()
    }
}

/// What is wrong with one read of the turning motor's status, if anything.
fn read_fault(reply: &Reply, own: Option<&drivegate::sim::SimDriveView>) -> Option<String> {
    let v = &reply.body;
    let reported = v["speed_rpm"].as_i64().unwrap_or(0);
    if reply.status != 200 || v["freshness"] != "live" || !(98..=102).contains(&reported) {
        return Some(format!("{} {v}", reply.status));
    }
    let own = own?;
    let turning = own.active
        && own.mode == drivegate::drive::Mode::Speed
        && (own.speed_rpm - 100.0).abs() <= 2.0;
    (!turning).then(|| {
        format!(
            "the simulated drive: active {}, {:?}, {:.1} rpm",
            own.active, own.mode, own.speed_rpm
        )
    })
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

/// Writes `toml` and reloads it: the answer.
async fn reload(d: &TestDaemon, api: &Api, toml: &str) -> Value {
    d.rewrite(toml);
    api.post_empty("/api/v1/config/reload").await.expect(200)
}

fn lines(reply: &Value, key: &str) -> Vec<String> {
    reply[key]
        .as_array()
        .unwrap_or_else(|| panic!("no {key} in {reply}"))
        .iter()
        .map(|l| l.as_str().unwrap().to_string())
        .collect()
}

/// Waits until `drive`'s REST status reports it at 100 rpm (its polls
/// caught up with the motor).
async fn reported_turning(api: &Api, drive: &str) {
    let path = format!("/api/v1/drives/{drive}/status");
    let start = Instant::now();
    let at_speed = |v: &Value| {
        v["speed_rpm"]
            .as_i64()
            .is_some_and(|r| (98..=102).contains(&r))
    };
    while !at_speed(&api.get(&path).await.body) {
        assert!(start.elapsed() < EVENT, "{drive} not reported at 100 rpm");
        tokio::time::sleep(EVERY).await;
    }
}

/// Activates `drive` in speed mode at 100 rpm under a ten-minute lease.
async fn turn(api: &Api, drive: &str) {
    api.activate_in(drive, "speed").await;
    api.put(
        &format!("/api/v1/drives/{drive}/setpoint"),
        json!({"speed_rpm": 100, "lease_ms": 600000}),
    )
    .await
    .expect(200);
}

/// The drives' plant: the conveyor turning, a lift, a feeder, on `port`.
fn plant(port: &str, bus: impl FnOnce(ConfigBuilder) -> ConfigBuilder) -> ConfigBuilder {
    bus(ConfigBuilder::new())
        .http_token("admin", "admin", ADMIN)
        .section(
            "safety",
            "lease_max_ms = 600000\non_shutdown = \"zero-speed\"",
        )
        .bus("line1", |b| b.port(port))
}

/// The four in-place reloads, one after the other, each checked: their
/// answers change in place, stop nothing and pause nothing. The names are
/// `prefix`-ed (the log is shared by the tests of this binary).
async fn four_reloads_in_place(
    d: &TestDaemon,
    api: &Api,
    watch: &mut Watch,
    config: impl Fn(&[(u8, &str)], &str) -> String,
    p: &str,
) {
    let (lift, hoist, feeder, mixer) = (
        format!("{p}_lift"),
        format!("{p}_hoist"),
        format!("{p}_feeder"),
        format!("{p}_mixer"),
    );
    let conveyor = format!("{p}_conveyor");
    let three = [(1, conveyor.as_str()), (2, &lift), (3, &feeder)];
    let renamed = [(1, conveyor.as_str()), (2, &hoist), (3, &feeder)];
    let added = [
        (1, conveyor.as_str()),
        (2, &hoist),
        (3, &feeder),
        (4, &mixer),
    ];
    let removed = [(1, conveyor.as_str()), (2, &hoist), (4, &mixer)];
    let in_place = |why: &str| format!("bus line1 changed in place ({why}), its port kept open");
    let steps: [(&str, String, Vec<String>); 4] = [
        (
            "a poll-rate change",
            config(&three, "poll_interval_ms = 20"),
            vec![in_place("poll rates")],
        ),
        (
            "a rename of another drive",
            config(&renamed, "poll_interval_ms = 20"),
            vec![
                format!("drives renamed: {lift} to {hoist}"),
                in_place("drives"),
            ],
        ),
        (
            "a drive added",
            config(&added, "poll_interval_ms = 20"),
            vec![format!("drives added: {mixer}"), in_place("drives")],
        ),
        (
            "a drive removed",
            config(&removed, "poll_interval_ms = 20"),
            vec![format!("drives removed: {feeder}"), in_place("drives")],
        ),
    ];
    let mut renamed_at = 0;
    for (what, toml, changes) in steps {
        watch.more(3).await;
        if what.starts_with("a rename") {
            renamed_at = unix_ms();
        }
        let asked = Instant::now();
        let reply = reload(d, api, &toml).await;
        eprintln!("{p}: {what} answered in {:?}", asked.elapsed());
        assert_eq!(lines(&reply, "changes"), changes, "{what}: {reply}");
        for key in ["stopped", "paused", "problems"] {
            assert_eq!(reply[key], json!([]), "{what}: {reply}");
        }
    }
    watch.more(3).await;
    // The renamed drive is the same motor: its status and its trends from
    // before the rename answer under its new name; the old name is gone.
    api.get(&format!("/api/v1/drives/{lift}/status"))
        .await
        .expect_problem(404, "unknown-drive");
    let history = api
        .get(&format!("/api/v1/drives/{hoist}/history"))
        .await
        .expect(200);
    let before_rename = history["t_ms"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|t| t.as_u64().is_some_and(|t| t < renamed_at))
        .count();
    assert!(before_rename > 0, "{history}");
    // The drive added answers; the one removed is no longer polled.
    eventually(EVENT, "the added drive polled", || {
        let (_, bus) = d.plant.drive(&mixer).ok()?;
        bus.drive(4)?.status.map(|_| ())
    })
    .await;
    let bus = d.plant.bus("line1").unwrap();
    assert!(bus.handle.drive(3).is_none(), "unit 3 still polled");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_the_built_in_simulator_a_turning_motor_turns_on_through_changes_in_place_and_a_reopen()
{
    bounded(LIMIT, async {
        let started = Instant::now();
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "in-place-host", None).await;
        let mqtt = format!(
            "broker = \"{}\"\ngroup_id = \"plant\"\nnode_id = \"inplace\"",
            broker.url()
        );
        let config = |drives: &[(u8, &str)], keys: &str| {
            plant("sim", |c| c.section("mqtt", &mqtt))
                .with_bus("line1", |mut b| {
                    b = b.keys(keys);
                    for (unit, name) in drives {
                        b = b.drive(*unit, name);
                    }
                    b
                })
                .toml()
        };
        let first = [(1, "sim_conveyor"), (2, "sim_lift"), (3, "sim_feeder")];
        let d = TestDaemon::reloadable(&config(&first, "poll_interval_ms = 0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        for device in ["sim_conveyor", "sim_lift", "sim_feeder"] {
            host.next(EVENT, "the DBIRTHs", |m| m.is("DBIRTH", Some(device)))
                .await;
        }
        turn(&api, "sim_conveyor").await;
        let sim = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        eventually(EVENT, "the conveyor at 100 rpm", || {
            ((sim.drive(1)?.speed_rpm - 100.0).abs() <= 2.0).then_some(())
        })
        .await;

        reported_turning(&api, "sim_conveyor").await;
        let mut watch = Watch::start(&api, "sim_conveyor", Some(sim));
        four_reloads_in_place(&d, &api, &mut watch, config, "sim").await;
        let reads = watch.finish("changes in place").await;

        // MQTT: the renamed device's death and birth, the added one's
        // birth, the removed one's death; nothing of the others.
        for (kind, device) in [
            ("DDEATH", "sim_feeder"),
            ("DDEATH", "sim_lift"),
            ("DBIRTH", "sim_hoist"),
            ("DBIRTH", "sim_mixer"),
        ] {
            if !host.seen.iter().any(|m| m.is(kind, Some(device))) {
                host.next(EVENT, &format!("{kind} {device}"), |m| {
                    m.is(kind, Some(device))
                })
                .await;
            }
        }
        let said = |m: &Msg| {
            let kind = matches!(m.kind.as_str(), "DDEATH" | "DBIRTH" | "NDEATH" | "NBIRTH");
            kind.then(|| format!("{} {}", m.kind, m.device.as_deref().unwrap_or("")))
        };
        let mut births: Vec<String> = host.seen.iter().filter_map(said).collect();
        // The start's births.
        births.retain(|b| !b.starts_with("NBIRTH"));
        births.drain(..3);
        births.sort();
        assert_eq!(
            births,
            [
                "DBIRTH sim_hoist",
                "DBIRTH sim_mixer",
                "DDEATH sim_feeder",
                "DDEATH sim_lift"
            ],
            "{:?}",
            host.seen
                .iter()
                .filter(|m| m.kind != "DDATA")
                .map(|m| &m.topic)
                .collect::<Vec<_>>()
        );

        // The baud rate reopens the port: the simulated drives are the
        // plant's, found as they were; the pause is said, nothing stopped.
        let now = [(1, "sim_conveyor"), (2, "sim_hoist"), (4, "sim_mixer")];
        let reply = reload(
            &d,
            &api,
            &config(&now, "poll_interval_ms = 20\nbaud = 57600"),
        )
        .await;
        assert_eq!(
            lines(&reply, "changes"),
            ["bus line1 reopened (baud changed)"],
            "{reply}"
        );
        assert_eq!(reply["stopped"], json!([]), "{reply}");
        let paused = lines(&reply, "paused");
        eprintln!("built-in simulator, baud changed: {paused:?}");
        assert!(
            paused.len() == 1
                && paused[0].starts_with("polling of sim_conveyor, sim_hoist, sim_mixer paused ")
                && paused[0].ends_with(" ms while bus line1 reopened"),
            "{reply}"
        );
        let sim = SimRef::of(d.plant.bus("line1").unwrap()).unwrap();
        let own = sim.drive(1).unwrap();
        assert!(
            own.active && own.mode == drivegate::drive::Mode::Speed && own.speed_rpm > 98.0,
            "{own:?}"
        );
        eventually(EVENT, "the conveyor's status at 100 rpm again", || {
            let s = d.plant.bus("line1")?.handle.drive(1)?.status?;
            (s.speed_rpm == 100).then_some(())
        })
        .await;

        // Removing the turning drive stops it, and says so.
        let reply = reload(
            &d,
            &api,
            &config(&now[1..], "poll_interval_ms = 20\nbaud = 57600"),
        )
        .await;
        let stopped = lines(&reply, "stopped");
        assert!(
            stopped.len() == 1
                && stopped[0].starts_with("drive sim_conveyor's lease ended with its stop"),
            "{reply}"
        );
        eventually(EVENT, "the removed conveyor at standstill", || {
            (sim.drive(1)?.speed_rpm.abs() < 1.0).then_some(())
        })
        .await;
        d.stop().await;
        eprintln!(
            "built-in simulator: {reads} reads through four reloads in place, {:?} in all",
            started.elapsed()
        );
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_an_external_simulator_a_turning_motor_turns_on_through_changes_in_place_and_a_port_change_stops_it()
 {
    bounded(LIMIT, async {
        let started = Instant::now();
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("ttyA"), dir.path().join("ttyB"));
        let sim_a = ExternalSim::start(&a, "1-4", &[]).await;
        let sim_b = ExternalSim::start(&b, "1-4", &[]).await;
        let (port_a, port_b) = (a.display().to_string(), b.display().to_string());
        let on = |port: &str, drives: &[(u8, &str)], keys: &str| {
            plant(port, |c| c)
                .with_bus("line1", |mut b| {
                    b = b.keys(keys);
                    for (unit, name) in drives {
                        b = b.drive(*unit, name);
                    }
                    b
                })
                .toml()
        };
        let first = [(1, "ext_conveyor"), (2, "ext_lift"), (3, "ext_feeder")];
        let d = TestDaemon::reloadable(&on(&port_a, &first, "poll_interval_ms = 0")).await;
        let api = Api::new(d.http, Some(ADMIN));
        turn(&api, "ext_conveyor").await;
        eventually(EVENT, "the conveyor at 100 rpm", || {
            let s = d.plant.bus("line1")?.handle.drive(1)?.status?;
            (s.speed_rpm == 100).then_some(())
        })
        .await;

        reported_turning(&api, "ext_conveyor").await;
        let mut watch = Watch::start(&api, "ext_conveyor", None);
        four_reloads_in_place(&d, &api, &mut watch, |d, k| on(&port_a, d, k), "ext").await;
        let reads = watch.finish("changes in place").await;

        // The bus moved to another adapter: other motors are behind it, so
        // the turning one is stopped before its port closes, and said so.
        let now = [(1, "ext_conveyor"), (2, "ext_hoist"), (4, "ext_mixer")];
        let reply = reload(&d, &api, &on(&port_b, &now, "poll_interval_ms = 20")).await;
        assert_eq!(
            lines(&reply, "changes"),
            ["bus line1 reopened (port changed)"],
            "{reply}"
        );
        let stopped = lines(&reply, "stopped");
        assert!(
            stopped.len() == 1
                && stopped[0].starts_with("drive ext_conveyor's lease ended with its stop")
                && stopped[0].ends_with("(its bus moved to another port)"),
            "{reply}"
        );
        // The conveyor behind the new port is another motor: no lease.
        let drive = api.get("/api/v1/drives/ext_conveyor").await.expect(200);
        assert!(drive["lease"].is_null(), "{drive}");
        // Back on the first adapter, the conveyor itself says it stopped.
        let reply = reload(&d, &api, &on(&port_a, &now, "poll_interval_ms = 20")).await;
        assert_eq!(reply["stopped"], json!([]), "{reply}");
        eventually(
            EVENT,
            "the first conveyor's own status at standstill",
            || {
                let s = d.plant.bus("line1")?.handle.drive(1)?.status?;
                (s.speed_rpm == 0).then_some(())
            },
        )
        .await;
        d.stop().await;
        sim_a.kill().await;
        sim_b.kill().await;
        eprintln!(
            "external simulator: {reads} reads through four reloads in place, {:?} in all",
            started.elapsed()
        );
    })
    .await;
}
