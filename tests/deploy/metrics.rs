//! The Prometheus exposition of a daemon running on the simulator: it passes
//! `promtool check metrics`, and its series carry the simulated drives'
//! true values, faults, flags and link state, and the bus's counters.

use std::collections::BTreeMap;
use std::process::Stdio;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use crate::support::bounded;
use crate::support::config::ConfigBuilder;
use crate::support::{FOUR_DRIVES, TestDaemon, eventually};
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{ConfigCommand, DriveRequest, Fault};
use tokio::io::AsyncWriteExt;

/// Every test ends within this, whatever happens.
const LIMIT: Duration = Duration::from_secs(30);

/// One sample line of the text format.
#[derive(Debug, Clone, PartialEq)]
struct Sample {
    name: String,
    labels: BTreeMap<String, String>,
    value: f64,
}

/// Parses the sample lines of a text exposition (comments skipped).
fn parse(text: &str) -> Vec<Sample> {
    let mut out = Vec::new();
    for line in text
        .lines()
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
    {
        let (series, value) = line.rsplit_once(' ').expect("sample line has a value");
        let value: f64 = match value {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            v => v
                .parse()
                .unwrap_or_else(|_| panic!("bad value in {line:?}")),
        };
        let (name, labels) = match series.split_once('{') {
            None => (series.to_string(), BTreeMap::new()),
            Some((name, rest)) => (name.to_string(), parse_labels(rest.trim_end_matches('}'))),
        };
        out.push(Sample {
            name,
            labels,
            value,
        });
    }
    out
}

fn parse_labels(mut s: &str) -> BTreeMap<String, String> {
    let mut labels = BTreeMap::new();
    while let Some((name, rest)) = s.split_once("=\"") {
        let mut value = String::new();
        let mut chars = rest.char_indices();
        let mut end = rest.len();
        while let Some((i, c)) = chars.next() {
            match c {
                '\\' => {
                    if let Some((_, e)) = chars.next() {
                        value.push(if e == 'n' { '\n' } else { e });
                    }
                }
                '"' => {
                    end = i + 1;
                    break;
                }
                c => value.push(c),
            }
        }
        labels.insert(name.trim_start_matches(',').to_string(), value);
        s = &rest[end..];
    }
    labels
}

/// The value of the first sample of `name` whose labels include `labels`.
fn value(samples: &[Sample], name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    samples
        .iter()
        .find(|s| {
            s.name == name
                && labels
                    .iter()
                    .all(|(k, v)| s.labels.get(*k).map(String::as_str) == Some(*v))
        })
        .map(|s| s.value)
}

fn scrape(d: &TestDaemon) -> Vec<Sample> {
    parse(&d.metrics.render())
}

/// `promtool check metrics` on `text`: its exit status and what it printed.
async fn promtool_check(text: &str) -> (bool, String) {
    let mut child = tokio::process::Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("promtool", &e)));
    let mut stdin = child.stdin.take().unwrap();
    stdin.write_all(text.as_bytes()).await.unwrap();
    drop(stdin);
    let out = child.wait_with_output().await.unwrap();
    let printed = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), printed)
}

async fn run_at_speed(d: &TestDaemon, drive: &str, rpm: i16) {
    let (drive, bus) = d.plant.drive(drive).unwrap();
    for request in [
        DriveRequest::Config(ConfigCommand::Activate),
        DriveRequest::Config(ConfigCommand::SpeedMode),
        DriveRequest::Speed { rpm },
    ] {
        bus.execute(drive.unit, &request, JobOptions::default())
            .await
            .unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_modbus_tcp_outcome_has_its_series_from_start_up() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let samples = scrape(&d);
        let zero = |function: &str, outcome: &str| {
            value(
                &samples,
                "drivegate_modbus_tcp_requests_total",
                &[("function", function), ("outcome", outcome)],
            )
        };
        // The two outcomes a hand-kept list once left out, by name ...
        for outcome in ["forbidden", "moving"] {
            assert_eq!(zero("0x06", outcome), Some(0.0), "{outcome}");
        }
        // ... and every one, for each function code the drives use.
        for outcome in drivegate::modbus_tcp::outcome::Outcome::ALL {
            for function in ["0x03", "0x06", "0x10"] {
                assert_eq!(
                    zero(function, outcome.label()),
                    Some(0.0),
                    "{function} {}",
                    outcome.label()
                );
            }
        }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exposition_passes_promtool_lint() {
    bounded(LIMIT, async {
        // The feeder declares settings, so its drift is exported too.
        let d = TestDaemon::start(
            &ConfigBuilder::four_drives()
                .with_bus("sim", |b| {
                    b.drive_keys("feeder", "settings = { inertia_ratio = 2 }")
                })
                .toml(),
        )
        .await;
        // Writes, a fault and the faces' counters (as the HTTP and Modbus
        // TCP faces count), so every kind of series exists.
        run_at_speed(&d, "conveyor", 50).await;
        eventually(Duration::from_secs(10), "the feeder's drift", || {
            d.control().drift().view("feeder")
        })
        .await;
        let faces = d.metrics.faces();
        faces.http_request(
            "/api/v1/drives/{drive}",
            "GET",
            200,
            Duration::from_millis(3),
        );
        faces.tcp_request(0x03, "ok");
        faces.tcp_rejected("not_allowed");
        let _client = faces.ws_client();
        d.sim().inject_fault(2, Fault::Encoder).unwrap();
        eventually(Duration::from_secs(5), "the fault in the metrics", || {
            value(&scrape(&d), "drivegate_drive_fault_code", &[("unit", "2")]).filter(|v| *v == 2.0)
        })
        .await;
        let text = d.metrics.render();
        let (ok, printed) = promtool_check(&text).await;
        assert!(ok, "promtool check metrics failed:\n{printed}\n---\n{text}");
        assert!(printed.trim().is_empty(), "promtool printed:\n{printed}");
        // Every family is documented with HELP and TYPE, and named drivegate_*.
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            assert!(line.starts_with("drivegate_"), "unprefixed series: {line}");
        }
        let helps = text.lines().filter(|l| l.starts_with("# HELP")).count();
        let types = text.lines().filter(|l| l.starts_with("# TYPE")).count();
        assert_eq!(helps, types);
        assert!(helps > 40, "only {helps} families");

        // Every family is described in the operations guide.
        let guide =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/operations.md"))
                .unwrap();
        for name in text.lines().filter_map(|l| l.strip_prefix("# TYPE ")) {
            let name = name.split(' ').next().unwrap();
            let listed = guide
                .match_indices(&format!("`{name}"))
                .any(|(i, m)| matches!(guide[i + m.len()..].chars().next(), Some('`' | '{' | ' ')));
            assert!(listed, "{name} is not in docs/operations.md");
        }
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drive_series_carry_the_simulated_truth() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        run_at_speed(&d, "conveyor", 60).await;
        // Settled at speed: the exported speed, current and flags are what the
        // simulated drive reports at that moment.
        eventually(
            Duration::from_secs(10),
            "conveyor at speed in the metrics",
            || {
                let s = scrape(&d);
                let truth = d.sim().drive(1)?.status;
                let l = [("bus", "sim"), ("unit", "1"), ("name", "conveyor")];
                let speed = value(&s, "drivegate_drive_speed_rpm", &l)?;
                ((speed - 60.0).abs() <= 2.0 && f64::from(truth.speed_rpm) == speed).then_some(())
            },
        )
        .await;
        let s = scrape(&d);
        let l = [("unit", "1")];
        assert_eq!(value(&s, "drivegate_drive_active", &l), Some(1.0));
        assert_eq!(
            value(
                &s,
                "drivegate_drive_mode",
                &[("unit", "1"), ("mode", "speed")]
            ),
            Some(1.0)
        );
        for mode in ["open_loop", "position", "torque"] {
            assert_eq!(
                value(&s, "drivegate_drive_mode", &[("unit", "1"), ("mode", mode)]),
                Some(0.0),
                "{mode}"
            );
        }
        assert_eq!(value(&s, "drivegate_drive_up", &l), Some(1.0));
        assert_eq!(
            value(&s, "drivegate_drive_poll_interval_seconds", &l),
            Some(0.0)
        );

        // Standing drives: every value equals the simulator's truth.
        for unit in 2..=4u8 {
            let u = unit.to_string();
            eventually(
                Duration::from_secs(5),
                "standing drive equal to its truth",
                || {
                    let s = scrape(&d);
                    let t = d.sim().drive(unit)?.status;
                    let l = [("unit", u.as_str())];
                    let same = value(&s, "drivegate_drive_temperature_celsius", &l)?
                        == f64::from(t.temperature_c)
                        && value(&s, "drivegate_drive_supply_voltage_volts", &l)?
                            == f64::from(t.voltage_v)
                        && value(&s, "drivegate_drive_current_amperes", &l)? == t.current_a()
                        && value(&s, "drivegate_drive_speed_rpm", &l)? == f64::from(t.speed_rpm)
                        && value(&s, "drivegate_drive_angle_degrees", &l)? == t.angle_deg()
                        && value(&s, "drivegate_drive_turns", &l)? == f64::from(t.turns)
                        && value(&s, "drivegate_drive_active", &l)?
                            == f64::from(u8::from(t.active()))
                        && value(&s, "drivegate_drive_calibrated", &l)?
                            == f64::from(u8::from(t.calibrated()))
                        && value(&s, "drivegate_drive_stalled", &l)? == 0.0
                        && value(&s, "drivegate_drive_fault_code", &l)? == 0.0;
                    same.then_some(())
                },
            )
            .await;
        }
        // The last status is recent, in Unix seconds.
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap()
            .as_secs_f64();
        let seen = value(
            &scrape(&d),
            "drivegate_drive_last_status_timestamp_seconds",
            &l,
        )
        .unwrap();
        assert!(
            seen <= now + 1.0 && seen > now - 5.0,
            "seen {seen}, now {now}"
        );
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn simulated_faults_turn_their_series_to_one() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        d.sim().inject_fault(2, Fault::OverTemperature).unwrap();
        eventually(
            Duration::from_secs(5),
            "over-temperature series at 1",
            || {
                let s = scrape(&d);
                let l = [("unit", "2"), ("fault", "over_temperature")];
                (value(&s, "drivegate_drive_fault", &l)? == 1.0).then_some(())
            },
        )
        .await;
        let s = scrape(&d);
        assert_eq!(
            value(&s, "drivegate_drive_fault_code", &[("unit", "2")]),
            Some(4.0)
        );
        for kind in [
            "current_sense",
            "encoder",
            "power_stage",
            "under_voltage",
            "over_voltage",
        ] {
            assert_eq!(
                value(
                    &s,
                    "drivegate_drive_fault",
                    &[("unit", "2"), ("fault", kind)]
                ),
                Some(0.0),
                "{kind}"
            );
        }
        // The other drives are untouched.
        assert_eq!(
            value(&s, "drivegate_drive_fault_code", &[("unit", "1")]),
            Some(0.0)
        );

        // A sagging supply: the drive trips on under-voltage, and the exported
        // voltage is the simulated one.
        d.sim().set_supply_voltage(3, 15.0).unwrap();
        eventually(Duration::from_secs(5), "under-voltage on drive 3", || {
            let s = scrape(&d);
            let truth = d.sim().drive(3)?.status;
            let l = [("unit", "3")];
            let tripped = value(
                &s,
                "drivegate_drive_fault",
                &[("unit", "3"), ("fault", "under_voltage")],
            )? == 1.0;
            let volts = value(&s, "drivegate_drive_supply_voltage_volts", &l)?;
            (tripped && volts == f64::from(truth.voltage_v) && volts < 18.0).then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_drive_goes_down_and_loses_its_values() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        let l = [("unit", "4")];
        d.sim().set_silent(4, true);
        eventually(Duration::from_secs(5), "drive 4 down", || {
            (value(&scrape(&d), "drivegate_drive_up", &l)? == 0.0).then_some(())
        })
        .await;
        let s = scrape(&d);
        assert_eq!(value(&s, "drivegate_drive_temperature_celsius", &l), None);
        assert_eq!(value(&s, "drivegate_drive_fault_code", &l), None);
        assert!(value(&s, "drivegate_drive_last_status_timestamp_seconds", &l).is_some());
        assert!(value(&s, "drivegate_drive_consecutive_poll_failures", &l).unwrap() >= 1.0);
        assert_eq!(value(&s, "drivegate_drive_up", &[("unit", "1")]), Some(1.0));

        d.sim().set_silent(4, false);
        eventually(Duration::from_secs(10), "drive 4 back up", || {
            let s = scrape(&d);
            (value(&s, "drivegate_drive_up", &l)? == 1.0
                && value(&s, "drivegate_drive_temperature_celsius", &l).is_some())
            .then_some(())
        })
        .await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bus_series_count_the_wire() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(FOUR_DRIVES).await;
        run_at_speed(&d, "lift", 20).await;
        // The utilisation ratio needs half a second of samples.
        let s = eventually(Duration::from_secs(5), "utilisation", || {
            let s = scrape(&d);
            value(&s, "drivegate_bus_utilisation_ratio", &[("bus", "sim")])?;
            Some(s)
        })
        .await;
        let bus = [("bus", "sim")];
        let ok_reads = value(
            &s,
            "drivegate_bus_transactions_total",
            &[("bus", "sim"), ("function", "0x03"), ("outcome", "ok")],
        )
        .unwrap();
        let polls = value(&s, "drivegate_bus_polls_total", &bus).unwrap();
        assert!(
            polls >= 4.0 && ok_reads >= 4.0,
            "polls {polls}, reads {ok_reads}"
        );
        assert_eq!(
            value(
                &s,
                "drivegate_bus_transactions_total",
                &[("function", "0x06"), ("outcome", "ok")]
            ),
            Some(3.0),
            "activate, speed mode, setpoint"
        );
        // Outcomes not seen yet are exported at 0, so rate() sees the first one.
        assert_eq!(
            value(
                &s,
                "drivegate_bus_transactions_total",
                &[("function", "0x10"), ("outcome", "timeout")]
            ),
            Some(0.0)
        );
        let count = value(&s, "drivegate_bus_transaction_duration_seconds_count", &bus).unwrap();
        let inf = value(
            &s,
            "drivegate_bus_transaction_duration_seconds_bucket",
            &[("bus", "sim"), ("le", "+Inf")],
        )
        .unwrap();
        assert!(
            count >= ok_reads && inf == count,
            "count {count}, +Inf {inf}"
        );
        assert!(value(&s, "drivegate_bus_job_latency_seconds_count", &bus).unwrap() >= 3.0);
        for priority in ["emergency", "command", "poll"] {
            assert!(
                value(
                    &s,
                    "drivegate_bus_queue_depth",
                    &[("bus", "sim"), ("priority", priority)]
                )
                .is_some(),
                "{priority}"
            );
        }
        assert_eq!(value(&s, "drivegate_bus_port_open", &bus), Some(1.0));
        assert_eq!(
            value(
                &s,
                "drivegate_bus_info",
                &[("bus", "sim"), ("port", "sim"), ("baud", "115200")]
            ),
            Some(1.0)
        );
        assert!(value(&s, "drivegate_bus_busy_seconds_total", &bus).unwrap() > 0.0);
        assert_eq!(
            value(&s, "drivegate_sim_gap_violations_total", &bus),
            Some(0.0)
        );
        assert!(value(&s, "drivegate_sim_requests_total", &bus).unwrap() >= polls);
        assert!(value(&s, "drivegate_sim_stalled_replies_total", &bus).is_some());
        assert_eq!(
            value(
                &s,
                "drivegate_sim_injected_faults_total",
                &[("kind", "dropped")]
            ),
            Some(0.0)
        );
        // Polling as fast as the bus allows keeps the wire busy.
        let utilisation = value(&s, "drivegate_bus_utilisation_ratio", &bus).unwrap();
        assert!(
            (0.1..=1.0).contains(&utilisation),
            "utilisation {utilisation}"
        );
        // Faces and process.
        assert_eq!(value(&s, "drivegate_websocket_clients", &[]), Some(0.0));
        assert_eq!(
            value(&s, "drivegate_modbus_tcp_connections", &[]),
            Some(0.0)
        );
        assert_eq!(
            value(
                &s,
                "drivegate_build_info",
                &[("version", env!("CARGO_PKG_VERSION"))]
            ),
            Some(1.0)
        );
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap()
            .as_secs_f64();
        let start = value(&s, "drivegate_process_start_time_seconds", &[]).unwrap();
        assert!(start <= now && start > now - 3600.0, "start {start}");
        d.stop().await;
    })
    .await;
}

/// One drive polled once an hour: after its first poll the wire is silent,
/// so any request the simulator sees during scrapes would be the scrapes'.
fn quiet_bus() -> String {
    ConfigBuilder::new()
        .bus("quiet", |b| {
            b.keys("poll_interval_ms = 3600000").drive(1, "idle")
        })
        .toml()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scrapes_never_touch_the_bus() {
    bounded(LIMIT, async {
        let d = TestDaemon::start(&quiet_bus()).await;
        let sim = d.sim();
        // Let the first poll's reply settle.
        tokio::time::sleep(Duration::from_millis(100)).await;
        let before = (
            sim.stats().requests,
            d.plant.buses()[0].handle.stats().on_wire(),
        );
        assert!(before.0 >= 1, "the drive was polled once");
        for _ in 0..100 {
            let s = scrape(&d);
            assert_eq!(
                value(&s, "drivegate_drive_up", &[("name", "idle")]),
                Some(1.0)
            );
        }
        let after = (
            sim.stats().requests,
            d.plant.buses()[0].handle.stats().on_wire(),
        );
        assert_eq!(before, after, "(simulator requests, bus transactions)");
        // An idle wire shows a low utilisation (the first poll is ~6 ms).
        tokio::time::sleep(Duration::from_millis(600)).await;
        let s = scrape(&d);
        let u = value(&s, "drivegate_bus_utilisation_ratio", &[("bus", "quiet")]).unwrap();
        assert!(u < 0.1, "idle utilisation {u}");
        assert_eq!(
            value(
                &s,
                "drivegate_drive_poll_interval_seconds",
                &[("name", "idle")]
            ),
            Some(3600.0)
        );
        d.stop().await;
    })
    .await;
}

/// A bus whose adapter is not there.
fn missing_adapter() -> String {
    ConfigBuilder::new()
        .bus("unplugged", |b| {
            b.port("/nonexistent/ttyUSB-drivegate-test").drive(7, "far")
        })
        .toml()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_missing_adapter_shows_the_bus_down() {
    bounded(LIMIT, async {
        let d = TestDaemon::start_no_wait(&missing_adapter()).await;
        let bus = [("bus", "unplugged")];
        let s = eventually(Duration::from_secs(5), "a port error counted", || {
            let s = scrape(&d);
            (value(&s, "drivegate_bus_port_errors_total", &bus)? >= 1.0).then_some(s)
        })
        .await;
        assert_eq!(value(&s, "drivegate_bus_port_open", &bus), Some(0.0));
        assert_eq!(
            value(&s, "drivegate_drive_up", &[("name", "far")]),
            Some(0.0)
        );
        assert_eq!(
            value(
                &s,
                "drivegate_drive_temperature_celsius",
                &[("name", "far")]
            ),
            None
        );
        assert_eq!(
            value(
                &s,
                "drivegate_drive_last_status_timestamp_seconds",
                &[("name", "far")]
            ),
            None
        );
        assert_eq!(
            value(&s, "drivegate_sim_requests_total", &bus),
            None,
            "not simulated"
        );
        // A drive never sent a request has its silence from start: the
        // spec's t3.5, and no fallback.
        let drive = [("bus", "unplugged"), ("unit", "7")];
        assert_eq!(
            value(&s, "drivegate_bus_interframe_gap_seconds", &drive),
            Some(0.00175)
        );
        assert_eq!(
            value(&s, "drivegate_bus_interframe_fallbacks_total", &drive),
            Some(0.0)
        );
        let (ok, printed) = promtool_check(&d.metrics.render()).await;
        assert!(ok && printed.trim().is_empty(), "{printed}");
        d.stop().await;
    })
    .await;
}
