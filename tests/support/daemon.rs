//! The daemon in-process on the built-in simulator, listening on loopback
//! ports chosen by the system: what the end-to-end tests talk to.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use drivegate::config::Config;
use drivegate::daemon::supervisor::{self, Faces};
use drivegate::metrics::Metrics;
use drivegate::plant::{Plant, SimRef};

use tokio_util::sync::CancellationToken;

/// The response timeout and guard time of the test buses. The simulator
/// answers within a few milliseconds, but it is a thread of this process,
/// and on a loaded machine (other builds, other tests) a thread can wait
/// 100 ms and more for a CPU: a timeout in the tens of milliseconds would
/// make a drive that answered look silent. The guard after a timeout is
/// shorter, so a silent unit costs 300 ms an attempt. A test replaces these
/// lines whole to set its own.
pub const WIRE_TIMING: &str = "response_timeout_ms = 250\nguard_ms = 50";

/// A simulated bus of four drives, units 1-4, as fast as the bus allows
/// (the response timeout is [`WIRE_TIMING`]).
pub const FOUR_DRIVES: &str = r#"
[http]
listen = "127.0.0.1:0"
[modbus_tcp]
listen = "127.0.0.1:0"
[[bus]]
name = "sim"
port = "sim"
response_timeout_ms = 250
guard_ms = 50
retries = 1
[bus.sim]
turnaround_ms = 0.5
seed = 7
[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
[[bus.drive]]
unit = 2
name = "lift"
gear_ratio = 10.0
[[bus.drive]]
unit = 3
name = "turntable"
gear_ratio = 3.75
[[bus.drive]]
unit = 4
name = "feeder"
gear_ratio = 1.0
"#;

/// `text` with `from` replaced by `to`; panics if `text` has no `from` (a
/// replacement that silently does nothing would test something else).
pub fn replaced(text: &str, from: &str, to: &str) -> String {
    assert!(
        text.contains(from),
        "no {from:?} in the configuration to replace"
    );
    text.replace(from, to)
}

/// A running daemon.
pub struct TestDaemon {
    pub config: Config,
    pub plant: Arc<Plant>,
    pub metrics: Arc<Metrics>,
    pub http: SocketAddr,
    pub modbus_tcp: Option<SocketAddr>,
    /// Where Modbus/TCP Security listens, if configured.
    pub modbus_tls: Option<SocketAddr>,
    shutdown: CancellationToken,
    faces: Option<Faces>,
    /// The configuration file a reload reads ([`TestDaemon::reloadable`]).
    file: Option<tempfile::NamedTempFile>,
    /// Or the test's own ([`TestDaemon::reloadable_at`]).
    file_at: Option<std::path::PathBuf>,
}

impl TestDaemon {
    /// Starts the daemon with `toml` (listen addresses should use port 0)
    /// and waits until every drive has answered a poll.
    pub async fn start(toml: &str) -> TestDaemon {
        let daemon = Self::start_no_wait(toml).await;
        // Generous: on a loaded machine a first poll can time out, and the
        // drive is then probed again later.
        daemon.wait_all_online(Duration::from_secs(30)).await;
        daemon
    }

    /// Starts the daemon without waiting for the drives.
    pub async fn start_no_wait(toml: &str) -> TestDaemon {
        Self::start_config(Config::parse(toml, "test config").expect("test config")).await
    }

    /// Starts the daemon with `config` as it is, checked or not (a test of
    /// what the checks would have refused), without waiting for the drives.
    pub async fn start_config(config: Config) -> TestDaemon {
        let plant = Arc::new(Plant::start(&config).expect("plant starts"));
        let metrics = Metrics::new(plant.clone());
        let shutdown = CancellationToken::new();
        let faces = supervisor::start(&config, plant.clone(), metrics.clone(), shutdown.clone())
            .await
            .expect("faces start");
        TestDaemon {
            config,
            plant,
            metrics,
            http: faces.http,
            modbus_tcp: faces.modbus_tcp,
            modbus_tls: faces.modbus_tls,
            shutdown,
            faces: Some(faces),
            file: None,
            file_at: None,
        }
    }

    /// Starts the daemon from a configuration file holding `toml`, which
    /// `POST /api/v1/config/reload` (or [`reload`](Self::reload)) reloads
    /// after [`rewrite`](Self::rewrite); waits for every drive.
    pub async fn reloadable(toml: &str) -> TestDaemon {
        let file = tempfile::Builder::new()
            .suffix(".toml")
            .tempfile()
            .expect("a configuration file");
        std::fs::write(file.path(), toml).expect("the configuration written");
        let mut daemon = Self::start(toml).await;
        daemon.reload_from(file.path());
        daemon.file = Some(file);
        daemon
    }

    /// As [`reloadable`](Self::reloadable), from the file at `path`, which
    /// the test makes in a directory of its own (a change through the API
    /// keeps the previous versions beside it).
    pub async fn reloadable_at(path: &std::path::Path, toml: &str) -> TestDaemon {
        std::fs::write(path, toml).expect("the configuration written");
        let mut daemon = Self::start(toml).await;
        daemon.reload_from(path);
        daemon.file_at = Some(path.to_path_buf());
        daemon
    }

    fn reload_from(&self, path: &std::path::Path) {
        drivegate::daemon::reloader::Reloader::start(
            path,
            Arc::new(self.config.clone()),
            self.plant.clone(),
            self.control().clone(),
            self.faces.as_ref().expect("running").running(),
            self.shutdown.clone(),
        );
    }

    /// The configuration file of a [`reloadable`](Self::reloadable) daemon.
    pub fn config_path(&self) -> &std::path::Path {
        match (&self.file, &self.file_at) {
            (Some(f), _) => f.path(),
            (None, Some(p)) => p,
            (None, None) => panic!("not a reloadable daemon"),
        }
    }

    /// Writes `toml` into the configuration file (not reloaded yet).
    pub fn rewrite(&self, toml: &str) {
        std::fs::write(self.config_path(), toml).expect("the configuration written");
    }

    /// Where the listeners are now (a reload may have moved them).
    pub async fn faces_addresses(&self) -> drivegate::daemon::supervisor::Addresses {
        self.faces
            .as_ref()
            .expect("running")
            .running()
            .addresses()
            .await
    }

    /// The control core every face writes through.
    pub fn control(&self) -> &drivegate::control::Control {
        &self.faces.as_ref().expect("running").control
    }

    /// `http://127.0.0.1:port` + `path`.
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{}", self.http, path)
    }

    /// The simulator of the first (or named) simulated bus.
    pub fn sim(&self) -> SimRef {
        self.plant
            .buses()
            .into_iter()
            .find_map(SimRef::of)
            .expect("a simulated bus")
    }

    /// Waits until every drive has a polled status.
    pub async fn wait_all_online(&self, limit: Duration) {
        let start = Instant::now();
        loop {
            let all = self
                .plant
                .buses()
                .iter()
                .all(|b| b.handle.drives().iter().all(|d| d.status.is_some()));
            if all {
                return;
            }
            assert!(
                start.elapsed() < limit,
                "drives did not come online within {limit:?}"
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// Graceful stop, as on SIGTERM.
    pub async fn stop(mut self) {
        self.shutdown.cancel();
        if let Some(faces) = self.faces.take() {
            let _ = tokio::time::timeout(Duration::from_secs(5), faces.wait()).await;
        }
        drivegate::control::shutdown(&self.plant, self.config.safety.on_shutdown).await;
    }
}
