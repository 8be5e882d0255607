//! The async-opcua server of `[opcua]`: its endpoints (one per security
//! policy, each signing and encrypting, and `none` when asked), its users,
//! its limits, its certificates in the PKI directory, and the node
//! managers: the core namespace (with conditions), the diagnostics, and
//! the drives'. It runs on the daemon's runtime, on the socket `faces.rs`
//! bound, and stops with the face's token.

use std::net::SocketAddr;
use std::sync::atomic::AtomicI64;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use opcua::core::config::Config as _;
use opcua::server::address_space::AddressSpace;
use opcua::server::diagnostics::DiagnosticsNodeManagerBuilder;
use opcua::server::node_manager::memory::{CoreNodeManagerBuilder, InMemoryNodeManagerBuilder};
use opcua::server::node_manager::{NodeManagerBuilder, ServerContext};
use opcua::server::{Server, ServerBuilder, ServerEndpoint, ServerHandle};
use tokio_util::sync::CancellationToken;

use super::address::Nodes;
use super::alarms::AlarmEvents;
use super::conditions::CoreWithConditions;
use super::nodes::Drives;
use super::pki::Pki;
use super::sessions::Sessions;
use super::spec::NAMESPACE;
use super::users::Users;
use crate::config::OpcUaConfig;
use crate::config::opcua::Security;
use crate::control::Control;
use crate::history::History;
use crate::metrics::Metrics;

/// What the server is built from.
pub struct Parts {
    /// The section.
    pub section: OpcUaConfig,
    /// Where it is bound.
    pub bound: SocketAddr,
    /// The host's name (endpoint URLs on a wildcard address, the
    /// application URI).
    pub host: String,
    /// The certificates.
    pub pki: Pki,
    /// The core.
    pub control: Control,
    /// The trends.
    pub history: Arc<History>,
    /// The metrics.
    pub metrics: Arc<Metrics>,
    /// Who sessions are.
    pub users: Arc<Users>,
    /// The sessions' callers.
    pub sessions: Arc<Sessions>,
    /// The server's stop.
    pub stop: CancellationToken,
    /// Its connections and sessions, shared out as every listener's are
    /// (made at the face's start: the listener is in the book from then).
    pub gate: Arc<super::gate::Gate>,
}

/// The server, its handle, and the alarms' events (whose namespace the
/// build decided).
pub struct Built {
    /// The server, to run on the listener.
    pub server: Server,
    /// Its handle.
    pub handle: ServerHandle,
    /// The alarms' events.
    pub events: Arc<AlarmEvents>,
}

/// The application URI of the server on `host`.
pub fn application_uri(host: &str) -> String {
    format!("urn:{host}:drivegate")
}

fn endpoint(security: Security) -> ServerEndpoint {
    let ids: Vec<String> = Vec::new();
    match security {
        Security::None => {
            let mut none = ServerEndpoint::new_none("/", &ids);
            // Passwords are encrypted even without a secure channel.
            none.password_security_policy = Some("Basic256Sha256".to_string());
            none
        }
        Security::Basic256sha256 => ServerEndpoint::new_basic256sha256_sign_encrypt("/", &ids),
        Security::Aes128Sha256Rsaoaep => {
            ServerEndpoint::new_aes128_sha256_rsaoaep_sign_encrypt("/", &ids)
        }
        Security::Aes256Sha256Rsapss => {
            ServerEndpoint::new_aes256_sha256_rsapss_sign_encrypt("/", &ids)
        }
    }
}

/// The host clients reach the server by, for its endpoint URLs: the
/// address it listens on, or the host's name on a wildcard address.
fn endpoint_host(bound: SocketAddr, host: &str) -> String {
    let ip = bound.ip();
    if ip.is_unspecified() {
        host.to_string()
    } else if ip.is_ipv6() {
        format!("[{ip}]")
    } else {
        ip.to_string()
    }
}

/// The least sampling interval and subscription tick: a tick every few
/// milliseconds would cost CPU for nothing (no drive is polled that often
/// but alone on a fast line).
pub const FLOOR: Duration = Duration::from_millis(10);

/// The tick and the least publishing interval at most: the crate's own,
/// so that a plant of slow polls does not slow publishing.
pub const CEILING: Duration = Duration::from_millis(100);

/// The fastest poll of the plant now (see
/// [`crate::bus::BusHandle::poll_period`]), at least [`FLOOR`]; 100 ms in
/// a plant without drives.
pub fn fastest_poll(control: &Control) -> Duration {
    let directory = control.plant().now();
    directory
        .drives()
        .filter_map(|d| Some(directory.handle_of(d)?.poll_period(d.unit)))
        .min()
        .unwrap_or(CEILING)
        .max(FLOOR)
}

/// The subscriptions' timing for `fastest`, the fastest poll: the least
/// sampling interval, the least publishing interval, and the tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// The minimum sampling interval: the poll's period (a client asking
    /// for less, or 0, gets it: every poll, each with its source
    /// timestamp).
    pub sampling_ms: f64,
    /// The least publishing interval: the poll's period too, at most
    /// [`CEILING`].
    pub publishing_ms: f64,
    /// How often the crate looks at the subscriptions (it samples held
    /// values and publishes at its ticks only): half the least publishing
    /// interval, so that a subscription publishing at the poll's period
    /// is not late by a whole tick when a tick comes a little early.
    pub tick_ms: u64,
}

impl Timing {
    /// The timing for polls every `fastest` at best.
    pub fn of(fastest: Duration) -> Timing {
        let fastest = fastest.max(FLOOR);
        let publishing = fastest.min(CEILING);
        let tick = (publishing / 2).max(FLOOR);
        Timing {
            sampling_ms: fastest.as_secs_f64() * 1000.0,
            publishing_ms: publishing.as_secs_f64() * 1000.0,
            tick_ms: u64::try_from(tick.as_millis()).unwrap_or(100),
        }
    }

    /// `builder` with this timing.
    fn apply(self, builder: ServerBuilder) -> ServerBuilder {
        let mut builder = builder.subscription_poll_interval_ms(self.tick_ms);
        let limits = &mut builder.limits_mut().subscriptions;
        limits.min_sampling_interval_ms = self.sampling_ms;
        limits.min_publishing_interval_ms = self.publishing_ms;
        builder
    }
}

/// The server of `parts`, checked but not built: its configuration is
/// valid (so a bad section fails at start), its node managers are not made
/// yet (the core namespace alone is about 10 MB).
pub struct Prepared {
    builder: ServerBuilder,
    gate: Arc<super::gate::Gate>,
    events: Arc<OnceLock<Arc<AlarmEvents>>>,
    stop: CancellationToken,
}

/// Builds the server of `parts`.
pub fn build(parts: Parts) -> Result<Built, String> {
    prepare(parts)?.build()
}

/// The server of `parts`, its configuration checked; [`Prepared::build`]
/// makes it.
pub fn prepare(parts: Parts) -> Result<Prepared, String> {
    let monitored = Arc::new(AtomicI64::new(0));
    let events: Arc<OnceLock<Arc<AlarmEvents>>> = Arc::new(OnceLock::new());
    let core = {
        let (control, users, sessions, metrics, monitored, events) = (
            parts.control.clone(),
            parts.users.clone(),
            parts.sessions.clone(),
            parts.metrics.clone(),
            monitored.clone(),
            events.clone(),
        );
        move |context: ServerContext| CoreWithConditions {
            core: Box::new(InMemoryNodeManagerBuilder::new(CoreNodeManagerBuilder)).build(context),
            control,
            users,
            sessions,
            events,
            monitored,
            metrics,
        }
    };
    let drives = {
        let (control, users, sessions, history, metrics, events) = (
            parts.control.clone(),
            parts.users.clone(),
            parts.sessions.clone(),
            parts.history.clone(),
            parts.metrics.clone(),
            events.clone(),
        );
        InMemoryNodeManagerBuilder::new(move |context: ServerContext, space: &mut AddressSpace| {
            let ns = context
                .type_tree
                .write()
                .namespaces_mut()
                .add_namespace(NAMESPACE);
            space.add_namespace(NAMESPACE, ns);
            let nodes = Nodes { ns };
            nodes.build_types(space);
            let _ = events.set(Arc::new(AlarmEvents::new(nodes)));
            Drives::new(
                nodes,
                control,
                (users, sessions),
                history,
                metrics,
                monitored,
            )
        })
    };
    let section = &parts.section;
    let gate = parts.gate;
    let mut builder = ServerBuilder::new()
        .without_node_managers()
        .with_node_manager(core)
        .with_node_manager(DiagnosticsNodeManagerBuilder)
        .with_node_manager(drives)
        .application_name("drivegate")
        .application_uri(application_uri(&parts.host))
        .product_uri("urn:drivegate")
        .pki_dir(parts.pki.stack_dir())
        .certificate_path(parts.pki.cert_path())
        .private_key_path(parts.pki.key_path())
        .create_sample_keypair(false)
        .trust_client_certs(false)
        .host(endpoint_host(parts.bound, &parts.host))
        .port(parts.bound.port())
        .discovery_urls(vec!["/".to_string()])
        .with_authenticator(parts.users.clone())
        .max_session_timeout_ms(section.session_timeout_max_ms)
        .max_sessions(section.max_sessions)
        .connection_gate(gate.clone())
        .diagnostics_enabled(true)
        .token(parts.stop.clone());
    for security in section.endpoints() {
        builder = builder.add_endpoint(security.name(), endpoint(security));
    }
    let mut builder = Timing::of(fastest_poll(&parts.control)).apply(builder);
    caps(section).apply(&mut builder.limits_mut().subscriptions);
    builder
        .config()
        .validate()
        .map_err(|e| format!("Builder configuration is invalid: {}", e.join(", ")))?;
    Ok(Prepared {
        builder,
        gate,
        events,
        stop: parts.stop,
    })
}

impl Prepared {
    /// Makes the server: its node managers, the address space.
    pub fn build(self) -> Result<Built, String> {
        let (server, handle) = self.builder.build()?;
        self.gate.follow(handle.clone(), self.stop);
        let events = self
            .events
            .get()
            .cloned()
            .ok_or("the server built no namespace for the drives")?;
        Ok(Built {
            server,
            handle,
            events,
        })
    }
}

/// The caps on what sessions may hold, from `[opcua]`: subscriptions per
/// session, monitored items per session and in all, the queues of value
/// and event items, and the queues added together (what can wait for a
/// Publish request at once). Queues were once raised to 1000 for every
/// item so that a `ConditionRefresh` (every retained alarm at once) fits
/// an event item's queue; value items now keep the stack's 10 unless
/// configured, and event items have their own cap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Caps {
    /// Subscriptions of one session.
    pub subscriptions_per_session: usize,
    /// Monitored items of one session.
    pub monitored_items_per_session: usize,
    /// Monitored items of all sessions.
    pub monitored_items: usize,
    /// A value item's queue.
    pub queue_size: usize,
    /// An event item's queue.
    pub event_queue_size: usize,
    /// The queues of all items added together.
    pub queued_values: usize,
}

/// The caps of `section`.
pub fn caps(section: &OpcUaConfig) -> Caps {
    Caps {
        subscriptions_per_session: section.max_subscriptions_per_session,
        monitored_items_per_session: section.max_monitored_items_per_session,
        monitored_items: section.max_monitored_items,
        queue_size: section.max_queue_size,
        event_queue_size: section.max_event_queue_size,
        queued_values: section.max_queued_values,
    }
}

/// Notifications in one publish message, at most. A sent message is kept
/// for `Republish` until its client acknowledges it, up to twice the
/// session's pending Publish requests (20): without this bound one message
/// could carry every queued value, and a client that publishes without
/// acknowledging would hold 40 times `max_queued_values`.
pub const NOTIFICATIONS_PER_PUBLISH: u64 = 1000;

impl Caps {
    fn apply(self, limits: &mut opcua::server::SubscriptionLimits) {
        limits.max_notifications_per_publish = NOTIFICATIONS_PER_PUBLISH;
        limits.max_subscriptions_per_session = self.subscriptions_per_session;
        limits.max_monitored_items_per_session = self.monitored_items_per_session;
        limits.max_monitored_items = self.monitored_items;
        limits.max_monitored_item_queue_size = self.queue_size;
        limits.max_event_queue_size = self.event_queue_size;
        limits.max_queued_values = self.queued_values;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_caps_bound_every_queue_and_each_publish_message() {
        let section = OpcUaConfig::default();
        let mut limits = opcua::server::SubscriptionLimits::default();
        caps(&section).apply(&mut limits);
        assert_eq!(limits.max_queued_values, 100_000);
        assert_eq!(limits.max_monitored_item_queue_size, 10);
        // The stack's default is 0, no bound: a message could carry every
        // queued value, and 40 of them wait for acknowledgements.
        assert_eq!(limits.max_notifications_per_publish, 1000);
        assert_eq!(limits.max_pending_publish_requests, 20);
    }

    #[test]
    fn subscriptions_sample_and_publish_at_the_fastest_poll_and_tick_twice_as_often() {
        let ms = Duration::from_millis;
        // Four drives polled flat out at 115200 baud: a round of 16.4 ms.
        let four = Timing::of(Duration::from_micros(16_375));
        assert_eq!(
            four,
            Timing {
                sampling_ms: 16.375,
                publishing_ms: 16.375,
                tick_ms: 10,
            }
        );
        // Eight drives: ticks of half the round.
        let eight = Timing::of(Duration::from_micros(32_750));
        assert_eq!((eight.sampling_ms, eight.tick_ms), (32.75, 16));
        // Slow polls: sampling at their period, publishing and the tick
        // no slower than the crate's own.
        let slow = Timing::of(ms(1000));
        assert_eq!(
            (slow.sampling_ms, slow.publishing_ms, slow.tick_ms),
            (1000.0, 100.0, 50)
        );
        // A lone drive on a fast line: the floor.
        let lone = Timing::of(ms(4));
        assert_eq!(
            (lone.sampling_ms, lone.publishing_ms, lone.tick_ms),
            (10.0, 10.0, 10)
        );
    }
}
