//! The OPC UA face's counters and its state, for `/metrics`, `/readyz` and
//! the console. The face updates them; every series exists from start-up,
//! at 0, whether `[opcua]` is configured or not, so an alert needs no
//! `absent()`.

use std::sync::Mutex;
use std::time::SystemTime;

use prometheus::{IntCounter, IntCounterVec, IntGauge, IntGaugeVec, Opts, Registry};

/// How a session signed in.
pub const SIGN_IN_KINDS: &[&str] = &["anonymous", "user", "certificate"];
/// What became of a sign-in.
const SIGN_IN_RESULTS: &[&str] = &["accepted", "refused"];
/// The caps on what sessions hold (`[opcua]`'s `max_<limit>`).
const LIMITS: &[&str] = &[
    "subscriptions_per_session",
    "monitored_items_per_session",
    "monitored_items",
    "queue_size",
    "event_queue_size",
    "queued_values",
];

/// The face's state, as `/readyz` and the console show it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FaceState {
    /// Where it listens; `None`: no `[opcua]`.
    pub listen: Option<String>,
    /// Serving (its certificate is there and the server runs).
    pub serving: bool,
    /// Why it is not serving, in words, and since when.
    pub problem: Option<(SystemTime, String)>,
}

/// The OPC UA face's metrics.
pub struct OpcUaMetrics {
    up: IntGauge,
    sessions: IntGauge,
    sessions_total: IntCounter,
    session_timeouts: IntCounter,
    subscriptions: IntGauge,
    monitored_items: IntGauge,
    values_published: IntCounter,
    notifications: IntCounter,
    events: IntCounter,
    rejected_certificates: IntCounter,
    sign_ins: IntCounterVec,
    limits: IntGaugeVec,
    state: Mutex<FaceState>,
}

impl OpcUaMetrics {
    /// Creates the series and registers them in `registry`.
    pub fn register(registry: &Registry) -> Self {
        let gauge = |name: &str, help: &str| {
            let g = IntGauge::new(name, help)
                .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
            let _ = registry.register(Box::new(g.clone()));
            g
        };
        let counter = |name: &str, help: &str| {
            let c = IntCounter::new(name, help)
                .unwrap_or_else(|e| panic!("invalid metric definition {name}: {e}"));
            let _ = registry.register(Box::new(c.clone()));
            c
        };
        let sign_ins = IntCounterVec::new(
            Opts::new(
                "drivegate_opcua_sign_ins_total",
                "OPC UA session activations, by kind of user (anonymous, user: an [[http.token]]'s \
                 name and token, certificate: an X.509 user certificate) and result (accepted, \
                 refused: the reason is in the log).",
            ),
            &["kind", "result"],
        )
        .unwrap_or_else(|e| {
            panic!("invalid metric definition drivegate_opcua_sign_ins_total: {e}")
        });
        let _ = registry.register(Box::new(sign_ins.clone()));
        for kind in SIGN_IN_KINDS {
            for result in SIGN_IN_RESULTS {
                sign_ins.with_label_values(&[kind, result]);
            }
        }
        let limits = IntGaugeVec::new(
            Opts::new(
                "drivegate_opcua_limit",
                "The OPC UA server's caps, as [opcua] sets them (max_<limit>): subscriptions and \
                 monitored items per session, monitored items in all, the queues of value and \
                 event items, and all queues added together; 0 without [opcua].",
            ),
            &["limit"],
        )
        .unwrap_or_else(|e| panic!("invalid metric definition drivegate_opcua_limit: {e}"));
        let _ = registry.register(Box::new(limits.clone()));
        for limit in LIMITS {
            limits.with_label_values(&[limit]);
        }
        OpcUaMetrics {
            up: gauge(
                "drivegate_opcua_up",
                "1 while the OPC UA server serves (its certificate made and its listener open), \
                 0 otherwise (no [opcua], or its start failed: see /readyz).",
            ),
            sessions: gauge("drivegate_opcua_sessions", "OPC UA sessions open now."),
            sessions_total: counter(
                "drivegate_opcua_sessions_total",
                "OPC UA sessions created since start.",
            ),
            session_timeouts: counter(
                "drivegate_opcua_session_timeouts_total",
                "OPC UA sessions ended by their timeout (a client that went silent); the leases \
                 they held ended with [opcua] comm_loss_action.",
            ),
            subscriptions: gauge(
                "drivegate_opcua_subscriptions",
                "OPC UA subscriptions open now.",
            ),
            monitored_items: gauge(
                "drivegate_opcua_monitored_items",
                "OPC UA monitored items now (values and event notifiers).",
            ),
            values_published: counter(
                "drivegate_opcua_values_published_total",
                "Values put into the OPC UA address space (each poll's values, freshness changes, \
                 bus counters); each reaches the subscriptions that monitor it.",
            ),
            notifications: counter(
                "drivegate_opcua_notifications_total",
                "Notifications sent to OPC UA subscriptions (data changes and events, as put into \
                 the notification messages of every session).",
            ),
            events: counter(
                "drivegate_opcua_events_total",
                "Alarm events sent to OPC UA subscriptions (raised, cleared, acknowledged).",
            ),
            rejected_certificates: counter(
                "drivegate_opcua_rejected_certificates_total",
                "Client certificates refused as not trusted and put in the PKI's rejected/certs \
                 (at most once a second per certificate).",
            ),
            sign_ins,
            limits,
            state: Mutex::new(FaceState::default()),
        }
    }

    /// The server's caps, by name (`subscriptions_per_session`, ...).
    pub fn limits(&self, caps: &[(&str, usize)]) {
        for (name, value) in caps {
            self.limits
                .with_label_values(&[name])
                .set(i64::try_from(*value).unwrap_or(i64::MAX));
        }
    }

    /// The face listens on `listen`, making its certificate or serving.
    pub fn started(&self, listen: String) {
        let mut state = self.lock();
        state.listen = Some(listen);
        state.problem = None;
    }

    /// The face serves now.
    pub fn serving(&self) {
        self.up.set(1);
        let mut state = self.lock();
        state.serving = true;
        state.problem = None;
    }

    /// The face stopped (a reload restarts it, or removed `[opcua]`).
    pub fn stopped(&self, configured: bool) {
        self.up.set(0);
        let mut state = self.lock();
        state.serving = false;
        if !configured {
            *state = FaceState::default();
            for limit in LIMITS {
                self.limits.with_label_values(&[limit]).set(0);
            }
        }
    }

    /// The face could not serve: why.
    pub fn failed(&self, why: String) {
        self.up.set(0);
        let mut state = self.lock();
        state.serving = false;
        state.problem = Some((SystemTime::now(), why));
    }

    /// The state for `/readyz` and the console.
    pub fn state(&self) -> FaceState {
        self.lock().clone()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, FaceState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The server's own counts, read by the face every second.
    pub fn server_counts(&self, counts: ServerCounts) {
        self.sessions.set(i64::from(counts.sessions));
        self.subscriptions.set(i64::from(counts.subscriptions));
        let grow = |c: &IntCounter, delta: u32| c.inc_by(u64::from(delta));
        grow(&self.sessions_total, counts.new_sessions);
        grow(&self.session_timeouts, counts.new_timeouts);
        self.notifications.inc_by(counts.new_notifications);
    }

    /// Sessions open now.
    pub fn sessions(&self) -> i64 {
        self.sessions.get()
    }

    /// Monitored items now.
    pub fn monitored_items(&self, n: i64) {
        self.monitored_items.set(n);
    }

    /// `n` values put into the address space.
    pub fn values_published(&self, n: usize) {
        self.values_published.inc_by(u64::try_from(n).unwrap_or(0));
    }

    /// `n` events sent.
    pub fn events(&self, n: usize) {
        self.events.inc_by(u64::try_from(n).unwrap_or(0));
    }

    /// `n` client certificates refused.
    pub fn rejected_certificates(&self, n: usize) {
        self.rejected_certificates
            .inc_by(u64::try_from(n).unwrap_or(0));
    }

    /// A sign-in of `kind` (one of [`SIGN_IN_KINDS`]).
    pub fn signed_in(&self, kind: &str, accepted: bool) {
        let result = if accepted { "accepted" } else { "refused" };
        self.sign_ins.with_label_values(&[kind, result]).inc();
    }
}

/// What the server counts, as the face reads it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ServerCounts {
    /// Sessions open now.
    pub sessions: u32,
    /// Subscriptions open now.
    pub subscriptions: u32,
    /// Sessions created since the last reading.
    pub new_sessions: u32,
    /// Sessions timed out since the last reading.
    pub new_timeouts: u32,
    /// Notifications sent since the last reading.
    pub new_notifications: u64,
}
