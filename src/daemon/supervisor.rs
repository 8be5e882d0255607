//! Starts the network faces (HTTP API with metrics, Modbus TCP, Modbus/TCP
//! Security, MQTT, OPC UA), restarts one of them when a reload changes its section,
//! and waits for them to finish after shutdown.
//!
//! Each face runs under a stop token of its own (a child of the daemon's
//! shutdown), so a reload closes that one listener (or the MQTT client) and
//! starts it again with its new section while the buses, the drives and the
//! other faces run on ([`Running::follow`]). The rules, for a plant engineer:
//!
//! - a listener whose address stays keeps its socket: the new one is served
//!   on the same descriptor, so there is no moment without a listener and
//!   nothing can fail to bind;
//! - a listener that moves binds its new address first, and only then closes
//!   the old one: an address that cannot be bound (in use, no permission)
//!   leaves the face where it was, with its settings, and the reload says
//!   so (a problem in its answer, `/readyz`, the log, the reload metric);
//!   the next reload tries again. Addresses that overlap (the same port on
//!   the wildcard and on one interface) cannot be held at once: the old one
//!   is closed first and opened again if the new one cannot be bound;
//! - a restarted face closes the connections it held, as a stop does: a
//!   client is never kept on a port the file no longer names, nor served
//!   with limits, certificates or roles the file no longer gives. Each
//!   closed connection ends as any disconnect does: its session's leases
//!   (a Modbus TCP client's communication-loss function, a WebSocket's
//!   jog) end with their stop, audited; HTTP requests in progress finish
//!   and get their answers first (the reload's own included).
//!
//! A face whose task crashes (a panic, or an end nobody asked for) is
//! started again alone on its socket (`face_watch`), after a wait that
//! grows while it keeps crashing; meanwhile `/readyz`, the console and the
//! log say it is down and why, and the other faces serve on. A panic while
//! a face starts is its start's error.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::{Duration, SystemTime};

use futures_util::FutureExt;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::face_watch::{self, RestartBook};
use super::listen::{bind, bind_address, overlaps, protocol};
use crate::config::Config;
use crate::config::diff::Face;
use crate::control::Control;
use crate::faces_shared::start::FaceStart;
use crate::history::History;
use crate::metrics::Metrics;
use crate::plant::Plant;

/// The running faces.
pub struct Faces {
    /// Where the HTTP API (REST, WebSocket, metrics) listened at start-up
    /// ([`Running::addresses`] after a reload).
    pub http: SocketAddr,
    /// Where Modbus TCP listened at start-up, if enabled.
    pub modbus_tcp: Option<SocketAddr>,
    /// Where Modbus/TCP Security listened at start-up, if configured.
    pub modbus_tls: Option<SocketAddr>,
    /// Where OPC UA listened at start-up, if configured.
    pub opcua: Option<SocketAddr>,
    /// The control core every face writes through.
    pub control: Control,
    running: Arc<Running>,
}

impl Faces {
    /// The faces as they run now, for the reloader.
    pub fn running(&self) -> Arc<Running> {
        self.running.clone()
    }

    /// Waits until every face has stopped (after the shutdown token fired).
    pub async fn wait(self) {
        self.running.wait().await;
        // Stops of leases still on the wire finish (the daemon's safe stop
        // follows).
        let _ = tokio::time::timeout(Duration::from_secs(2), self.control.wait()).await;
    }
}

/// Where the listeners are now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Addresses {
    /// The HTTP API.
    pub http: Option<SocketAddr>,
    /// Modbus TCP.
    pub modbus_tcp: Option<SocketAddr>,
    /// Modbus/TCP Security.
    pub modbus_tls: Option<SocketAddr>,
    /// OPC UA.
    pub opcua: Option<SocketAddr>,
}

/// What a reload did to the faces, in words.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Followed {
    /// What was restarted, opened or closed, one line each.
    pub changes: Vec<String>,
    /// What could not be done, and where the face stays.
    pub problems: Vec<String>,
}

/// The faces as they run now, each with its own stop; shared by the daemon
/// and the reloader.
pub struct Running {
    shared: Shared,
    started: tokio::sync::Mutex<Started>,
    /// Every listener's task, the ones a reload closed included: a stop
    /// waits for their connections too.
    tasks: TaskTracker,
    /// Itself, for the watch of each face's task.
    me: Weak<Running>,
    /// The last face started's number: a crashed face is restarted only
    /// while it is the one in its slot (not one a reload started since).
    started_count: AtomicU64,
    /// Each face's waits before a restart after a crash.
    restarts: std::sync::Mutex<RestartBook>,
}

/// What every face is started with.
struct Shared {
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    control: Control,
    history: Arc<History>,
    shutdown: CancellationToken,
}

impl Shared {
    /// What a face started with `config` under `stop` is handed.
    fn face_start(&self, config: &Arc<Config>, stop: &CancellationToken) -> FaceStart {
        FaceStart {
            config: config.clone(),
            plant: self.plant.clone(),
            control: self.control.clone(),
            metrics: self.metrics.clone(),
            history: self.history.clone(),
            stop: stop.clone(),
        }
    }
}

#[derive(Default)]
struct Started {
    http: Option<Listening>,
    modbus_tcp: Option<Listening>,
    modbus_tls: Option<Listening>,
    opcua: Option<Listening>,
    mqtt: Option<Client>,
}

impl Started {
    /// The listener of `face`; `None` for the MQTT face, a client.
    fn slot(&mut self, face: Face) -> Option<&mut Option<Listening>> {
        match face {
            Face::Http => Some(&mut self.http),
            Face::ModbusTcp => Some(&mut self.modbus_tcp),
            Face::ModbusTls => Some(&mut self.modbus_tls),
            Face::OpcUa => Some(&mut self.opcua),
            Face::Mqtt => None,
        }
    }
}

/// A listener serving.
struct Listening {
    /// The configuration it was started with.
    config: Arc<Config>,
    /// The address it was asked to bind (port 0 stays 0).
    bind: SocketAddr,
    /// The address it is bound to.
    addr: SocketAddr,
    /// A second descriptor of its socket: served again by a restart at the
    /// same address, and shut to stop listening at once when it closes
    /// (its accept loop notices its stop a moment later).
    socket: std::net::TcpListener,
    stop: CancellationToken,
    /// Which start of the face this is.
    generation: u64,
}

impl Listening {
    /// Stops the face: its accept loop ends and its connections close.
    /// With `shut`, the socket stops listening now (the port then refuses
    /// connections); without, another accept loop serves it on.
    fn close(self, shut: bool) {
        self.stop.cancel();
        if shut {
            let _ = socket2::SockRef::from(&self.socket).shutdown(std::net::Shutdown::Read);
        }
    }
}

/// The MQTT face running.
struct Client {
    config: Arc<Config>,
    stop: CancellationToken,
    task: JoinHandle<()>,
    /// Which start of the face this is.
    generation: u64,
}

/// How long the MQTT face may take to say goodbye to its broker (its
/// NDEATH) before a restart starts the new one anyway.
const MQTT_STOP_LIMIT: Duration = Duration::from_secs(5);

/// Starts the control core, binds every configured listener (so a taken
/// port fails the start) and serves them until `shutdown` fires.
pub async fn start(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> Result<Faces, String> {
    let control = Control::start(plant.clone(), &config.safety, shutdown.clone());
    // The running configuration, which the faces follow for their sections.
    control.set_config(Arc::new(config.clone()));
    metrics.faces().tcp_outcomes(
        crate::modbus_tcp::outcome::Outcome::ALL
            .iter()
            .map(|o| o.label()),
    );
    metrics.faces().tcp_rejections(
        crate::modbus_tcp::refusals::Refused::ALL
            .iter()
            .map(|r| r.label()),
    );
    metrics
        .faces()
        .http_routes(crate::api::health::MONITORED_ROUTES.map(|route| (route, "GET")));
    metrics.watch_control(&control);
    let history = crate::history::History::new(config.history.settings());
    let following = (history.clone(), plant.clone());
    plant.for_each_bus(&shutdown, move |index, bus, stop| {
        // Asked at each status: drives a reload adds are kept too.
        let directory = following.1.clone();
        following.0.follow(
            &bus.handle,
            move |unit| directory.now().drive_on(index, unit).is_some(),
            stop,
        );
    });
    metrics.watch_history(&history);
    // What the last process owed the motors, before any client is taken.
    control.replay().await;
    let running = Arc::new_cyclic(|me| Running {
        shared: Shared {
            plant,
            metrics,
            control: control.clone(),
            history,
            shutdown,
        },
        started: tokio::sync::Mutex::new(Started::default()),
        tasks: TaskTracker::new(),
        me: me.clone(),
        started_count: AtomicU64::new(0),
        restarts: std::sync::Mutex::new(RestartBook::default()),
    });
    // Weak: the core holds the store, and the faces hold the core.
    let faces = Arc::downgrade(&running);
    let restart: super::certificates::Restart = Arc::new(move |face| {
        let faces = faces.clone();
        Box::pin(async move {
            match faces.upgrade() {
                Some(running) => running.restart(face).await,
                None => Err("drivegate is stopping".to_string()),
            }
        })
    });
    control.attach_certificates(
        Arc::new(super::certificates::Store::new(control.clone(), restart)),
        running.shared.shutdown.clone(),
    );
    let config = Arc::new(config.clone());
    let mut started = Started::default();
    for face in [Face::Http, Face::ModbusTls, Face::OpcUa] {
        if let Some(address) = bind_address(face, &config) {
            let listener = bind(face, address).await?;
            let serving = running.serve(face, &config, address, listener).await?;
            if let Some(slot) = started.slot(face) {
                *slot = Some(serving);
            }
        }
    }
    running.start_mqtt(&config, &mut started)?;
    // Modbus TCP last: a PLC that connects finds the others up.
    if let Some(address) = bind_address(Face::ModbusTcp, &config) {
        let listener = bind(Face::ModbusTcp, address).await?;
        started.modbus_tcp = Some(
            running
                .serve(Face::ModbusTcp, &config, address, listener)
                .await?,
        );
    }
    let addr = |l: &Option<Listening>| l.as_ref().map(|l| l.addr);
    let (http, modbus_tcp, modbus_tls, opcua) = (
        addr(&started.http).ok_or("the HTTP API did not start")?,
        addr(&started.modbus_tcp),
        addr(&started.modbus_tls),
        addr(&started.opcua),
    );
    *running.started.lock().await = started;
    Ok(Faces {
        http,
        modbus_tcp,
        modbus_tls,
        opcua,
        control,
        running,
    })
}

impl Running {
    /// Where the listeners are now.
    pub async fn addresses(&self) -> Addresses {
        let started = self.started.lock().await;
        let addr = |l: &Option<Listening>| l.as_ref().map(|l| l.addr);
        Addresses {
            http: addr(&started.http),
            modbus_tcp: addr(&started.modbus_tcp),
            modbus_tls: addr(&started.modbus_tls),
            opcua: addr(&started.opcua),
        }
    }

    /// Restarts `face` with the configuration it runs with, on its own
    /// socket (its connections closed as at a stop), so that what it reads
    /// as it starts is read again (the OPC UA server's certificate after a
    /// renewal). What was done, in words.
    pub async fn restart(&self, face: Face) -> Result<String, String> {
        let mut started = self.started.lock().await;
        let name = face.name();
        let slot = started
            .slot(face)
            .ok_or_else(|| format!("{name} is not a listener"))?;
        let old = slot
            .take()
            .ok_or_else(|| format!("{name} is not running"))?;
        let config = old.config.clone();
        let mut followed = Followed::default();
        *slot = self.reopen(face, &config, old, &mut followed).await;
        match followed.problems.pop() {
            Some(problem) => Err(problem),
            None => Ok(followed.changes.join("; ")),
        }
    }

    /// Restarts each face whose section changed between what it runs with
    /// and `config` (`Face::changed`), opens the ones `config` adds and
    /// closes the ones it removes; the others are not touched. A face that
    /// could not follow stays as it was and is tried again at the next
    /// reload.
    pub async fn follow(&self, config: &Arc<Config>) -> Followed {
        let mut started = self.started.lock().await;
        let mut followed = Followed::default();
        for face in [Face::Http, Face::ModbusTls, Face::OpcUa, Face::ModbusTcp] {
            self.follow_listener(face, config, &mut started, &mut followed)
                .await;
        }
        self.follow_mqtt(config, &mut started, &mut followed).await;
        followed
    }

    /// Follows `config` for one listening face: opened, closed, restarted
    /// on its socket or moved, as its section changed.
    async fn follow_listener(
        &self,
        face: Face,
        config: &Arc<Config>,
        started: &mut Started,
        followed: &mut Followed,
    ) {
        let wanted = bind_address(face, config);
        let Some(slot) = started.slot(face) else {
            return;
        };
        if slot
            .as_ref()
            .is_some_and(|old| !face.changed(&old.config, config))
        {
            return;
        }
        let name = face.name();
        match (slot.take(), wanted) {
            (None, None) => {}
            (Some(old), None) => {
                followed
                    .changes
                    .push(format!("{name} closed (it was on {})", old.addr));
                tracing::info!(addr = %old.addr, "{name} closed by a reload");
                old.close(true);
            }
            (None, Some(address)) => {
                if let Some(new) = self.open(face, config, address, followed).await {
                    *slot = Some(new);
                }
            }
            (Some(old), Some(address)) if address == old.bind => {
                *slot = self.reopen(face, config, old, followed).await;
            }
            (Some(old), Some(address)) => {
                *slot = self.move_to(face, config, old, address, followed).await;
            }
        }
    }

    /// Opens `face`, which a reload adds, on `address`.
    async fn open(
        &self,
        face: Face,
        config: &Arc<Config>,
        address: SocketAddr,
        followed: &mut Followed,
    ) -> Option<Listening> {
        let name = face.name();
        match bind(face, address).await {
            Ok(listener) => match self.serve(face, config, address, listener).await {
                Ok(new) => {
                    followed
                        .changes
                        .push(format!("{name} opened on {}", new.addr));
                    Some(new)
                }
                Err(why) => {
                    followed.problems.push(format!("{name} not opened: {why}"));
                    None
                }
            },
            Err(why) => {
                followed.problems.push(format!(
                    "{name} not opened: {why}; the next reload tries again"
                ));
                None
            }
        }
    }

    /// The same address: the same socket, served with the new settings;
    /// the listener that serves after it (`old` when that failed).
    async fn reopen(
        &self,
        face: Face,
        config: &Arc<Config>,
        old: Listening,
        followed: &mut Followed,
    ) -> Option<Listening> {
        let name = face.name();
        let listener = old
            .socket
            .try_clone()
            .and_then(TcpListener::from_std)
            .map_err(|e| format!("cannot take over its socket: {e}"));
        let served = match listener {
            Ok(listener) => self.serve(face, config, old.bind, listener).await,
            Err(why) => Err(why),
        };
        match served {
            Ok(new) => {
                followed.changes.push(format!(
                    "{name} reopened on {} with the new {}",
                    new.addr,
                    face.section()
                ));
                old.close(false);
                Some(new)
            }
            Err(why) => {
                followed.problems.push(format!(
                    "{name} not reopened: {why}; it stays on {} with its previous settings",
                    old.addr
                ));
                Some(old)
            }
        }
    }

    /// Another address: bound before the old one closes, unless the two
    /// cannot be held at once; the listener that serves after it.
    async fn move_to(
        &self,
        face: Face,
        config: &Arc<Config>,
        old: Listening,
        address: SocketAddr,
        followed: &mut Followed,
    ) -> Option<Listening> {
        let name = face.name();
        let overlapping = overlaps(old.bind, address);
        if overlapping {
            old.stop.cancel();
            let _ = socket2::SockRef::from(&old.socket).shutdown(std::net::Shutdown::Read);
        }
        let moved = match bind(face, address).await {
            Ok(listener) => self.serve(face, config, address, listener).await,
            Err(why) => Err(why),
        };
        match moved {
            Ok(new) => {
                followed.changes.push(format!(
                    "{name} moved to {} (it was on {})",
                    new.addr, old.addr
                ));
                tracing::info!(addr = %new.addr, was = %old.addr, "{name} moved by a reload");
                old.close(true);
                Some(new)
            }
            Err(why) if overlapping => self.restore(face, old, &why, followed).await,
            Err(why) => {
                followed.problems.push(format!(
                    "{name} not moved: {why}; it stays on {} with its previous settings, and the next reload tries again",
                    old.addr
                ));
                Some(old)
            }
        }
    }

    /// A move that stopped `old` first failed (`why`): listening again
    /// where it was, as it was.
    async fn restore(
        &self,
        face: Face,
        old: Listening,
        why: &str,
        followed: &mut Followed,
    ) -> Option<Listening> {
        let name = face.name();
        let back = socket2::SockRef::from(&old.socket)
            .listen(1024)
            .and_then(|()| old.socket.try_clone())
            .and_then(TcpListener::from_std)
            .map_err(|e| e.to_string());
        let previous = old.config.clone();
        let (bind, addr) = (old.bind, old.addr);
        old.close(false);
        let again = match back {
            Ok(listener) => self.serve(face, &previous, bind, listener).await,
            Err(e) => Err(e),
        };
        match again {
            Ok(again) => {
                followed.problems.push(format!(
                    "{name} not moved: {why}; it stays on {addr} with its previous settings, and the next reload tries again"
                ));
                Some(again)
            }
            Err(e) => {
                followed.problems.push(format!(
                    "{name} not moved: {why}; and not opened again on {addr}: {e}"
                ));
                None
            }
        }
    }

    /// Starts `face` with `config` on `listener`, under a stop of its own.
    async fn serve(
        &self,
        face: Face,
        config: &Arc<Config>,
        bind: SocketAddr,
        listener: TcpListener,
    ) -> Result<Listening, String> {
        let std = listener.into_std().map_err(|e| e.to_string())?;
        let socket = std.try_clone().map_err(|e| e.to_string())?;
        let listener = TcpListener::from_std(std).map_err(|e| e.to_string())?;
        let stop = self.shared.shutdown.child_token();
        let start = self.shared.face_start(config, &stop);
        let (addr, task) = std::panic::AssertUnwindSafe(async move {
            match face {
                Face::Http => crate::api::start(start, listener, crate::console::router()).await,
                Face::ModbusTcp => crate::modbus_tcp::start(start, listener),
                Face::OpcUa => crate::opcua::start(start, listener),
                Face::ModbusTls | Face::Mqtt => crate::modbus_tcp::start_tls(start, listener),
            }
        })
        .catch_unwind()
        .await
        .map_err(|panic| {
            format!(
                "it panicked while starting: {}",
                face_watch::panic_words(&*panic)
            )
        })??;
        tracing::info!(addr = %addr, "{} listening", protocol(face));
        let generation = self.face_started(face);
        self.tasks
            .spawn(self.supervised(face, generation, stop.clone(), task));
        Ok(Listening {
            config: config.clone(),
            bind,
            addr,
            socket,
            stop,
            generation,
        })
    }

    /// A face started now: its number, and its waits measured from now.
    fn face_started(&self, face: Face) -> u64 {
        if let Ok(mut restarts) = self.restarts.lock() {
            restarts.started(face, tokio::time::Instant::now());
        }
        self.shared.metrics.face_health().serving(face);
        self.started_count.fetch_add(1, Ordering::Relaxed) + 1
    }

    /// `task`, the face's, watched: a crash (not a stop) has the face
    /// started again, alone, after a wait.
    fn supervised(
        &self,
        face: Face,
        generation: u64,
        stop: CancellationToken,
        task: JoinHandle<()>,
    ) -> impl std::future::Future<Output = ()> + Send + 'static {
        let me = self.me.clone();
        async move {
            if let Some(why) = face_watch::watched(task, &stop).await
                && let Some(running) = me.upgrade()
            {
                let recovering = running.clone();
                running
                    .tasks
                    .spawn(async move { recovering.recover(face, generation, why).await });
            }
        }
    }

    /// A face crashed (`why`): said, waited for, started again; again
    /// while its start fails.
    async fn recover(&self, face: Face, generation: u64, mut why: String) {
        let health = self.shared.metrics.face_health();
        loop {
            let wait = self.restarts.lock().map_or(face_watch::WAIT_MIN, |mut r| {
                r.crashed(face, tokio::time::Instant::now())
            });
            tracing::error!(
                face = face.key(),
                "the {} is down: {why}; it is started again in {} s, the other faces serve on",
                face.name(),
                wait.as_secs()
            );
            health.down(face, why.clone(), SystemTime::now() + wait);
            tokio::select! {
                () = tokio::time::sleep(wait) => {}
                () = self.shared.shutdown.cancelled() => return health.serving(face),
            }
            match self.restart_crashed(face, generation).await {
                face_watch::Restart::Done => {
                    health.restarted(face);
                    tracing::warn!(face = face.key(), "the {} serves again", face.name());
                    return;
                }
                face_watch::Restart::Replaced => return,
                face_watch::Restart::Failed(again) => why = again,
            }
        }
    }

    /// Starts the crashed face `generation` of `face` again with what it
    /// ran with (a listener on its socket), unless it was replaced.
    async fn restart_crashed(&self, face: Face, generation: u64) -> face_watch::Restart {
        let mut started = self.started.lock().await;
        let Some(slot) = started.slot(face) else {
            let Some(old) = started.mqtt.take_if(|c| c.generation == generation) else {
                return face_watch::Restart::Replaced;
            };
            old.stop.cancel();
            let config = old.config.clone();
            return match self.start_mqtt(&config, &mut started) {
                Ok(()) => face_watch::Restart::Done,
                Err(why) => {
                    started.mqtt = Some(old);
                    face_watch::Restart::Failed(why)
                }
            };
        };
        let Some(old) = slot.take_if(|l| l.generation == generation) else {
            return face_watch::Restart::Replaced;
        };
        let listener = match old.socket.try_clone().and_then(TcpListener::from_std) {
            Ok(listener) => listener,
            Err(e) => {
                *slot = Some(old);
                return face_watch::Restart::Failed(format!("cannot take over its socket: {e}"));
            }
        };
        let config = old.config.clone();
        match self.serve(face, &config, old.bind, listener).await {
            Ok(new) => {
                old.close(false);
                *slot = Some(new);
                face_watch::Restart::Done
            }
            Err(why) => {
                *slot = Some(old);
                face_watch::Restart::Failed(why)
            }
        }
    }

    /// Starts the MQTT face of `config`, if it has one.
    fn start_mqtt(&self, config: &Arc<Config>, started: &mut Started) -> Result<(), String> {
        let s = &self.shared;
        let stop = s.shutdown.child_token();
        let face = s.face_start(config, &stop);
        let started_task = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            crate::mqtt::start(
                face,
                crate::mqtt::store::outbox::for_config(config, &s.metrics),
            )
        }))
        .map_err(|panic| {
            format!(
                "it panicked while starting: {}",
                face_watch::panic_words(&*panic)
            )
        })??;
        if let Some(task) = started_task {
            tracing::info!("MQTT face started");
            let generation = self.face_started(Face::Mqtt);
            started.mqtt = Some(Client {
                config: config.clone(),
                task: tokio::spawn(self.supervised(Face::Mqtt, generation, stop.clone(), task)),
                stop,
                generation,
            });
        }
        Ok(())
    }

    /// Restarts the MQTT face when `[mqtt]` changed: the old one says
    /// goodbye to its broker (its session's leases end with
    /// `comm_loss_action`, as for a lost broker) before the new one
    /// connects with the same node id and store.
    async fn follow_mqtt(
        &self,
        config: &Arc<Config>,
        started: &mut Started,
        followed: &mut Followed,
    ) {
        let name = Face::Mqtt.name();
        let was = started.mqtt.as_ref().map(|c| c.config.clone());
        match &was {
            Some(old) if !Face::Mqtt.changed(old, config) => return,
            None if config.mqtt.is_none() => return,
            _ => {}
        }
        if let Some(old) = started.mqtt.take() {
            old.stop.cancel();
            if tokio::time::timeout(MQTT_STOP_LIMIT, old.task)
                .await
                .is_err()
            {
                tracing::warn!(
                    "the MQTT face did not stop within {} s; the new one starts anyway",
                    MQTT_STOP_LIMIT.as_secs()
                );
            }
        }
        if config.mqtt.is_none() {
            self.shared.metrics.mqtt().unconfigured();
        }
        match self.start_mqtt(config, started) {
            Ok(()) => followed.changes.push(match (&was, &started.mqtt) {
                (Some(_), Some(_)) => format!("{name} restarted with the new [mqtt]"),
                (None, Some(_)) => format!("{name} started"),
                _ => format!("{name} stopped ([mqtt] removed)"),
            }),
            Err(why) => followed.problems.push(format!(
                "{name} not started: {why}; the next reload tries again"
            )),
        }
    }

    /// Waits for every face to end (once the shutdown fired).
    async fn wait(&self) {
        let mqtt = self.started.lock().await.mqtt.take();
        self.tasks.close();
        self.tasks.wait().await;
        if let Some(mqtt) = mqtt {
            let _ = mqtt.task.await;
        }
    }
}
