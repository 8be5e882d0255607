//! One connection to the broker: rumqttc's client with options built from
//! `[mqtt]` (keepalive, credentials, TLS, the will, the largest message
//! taken), and its event loop polled in a task of its own, whose events
//! (or its error, in words) come to the node over a channel. The event
//! loop is never asked to reconnect: each connection has its own will (its
//! bdSeq), so the node opens a new one instead. The Sparkplug connection
//! reaches the broker through [`relay`](super::relay), which cuts messages
//! above `max_message_bytes` (the JSON format's MQTT 5 tells the broker).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Transport};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tokio_util::sync::DropGuard;

use super::relay::{self, TooLarge};
use crate::config::MqttConfig;

/// How many requests (publishes, subscriptions) may wait in the client
/// for the event loop.
const REQUEST_CAPACITY: usize = 4096;

/// One connection to the broker, of either client (MQTT 3.1.1 for
/// Sparkplug, MQTT 5 for the JSON format).
pub(in crate::mqtt) struct Link<C, E> {
    /// Publishes and subscribes.
    pub(in crate::mqtt) client: C,
    /// The event loop's events; an error ends them.
    pub(in crate::mqtt) events: mpsc::Receiver<Result<E, String>>,
    poller: JoinHandle<()>,
    /// The relay's life, ended with the connection's.
    relay: Option<DropGuard>,
    /// The broker accepted it (CONNACK).
    pub(in crate::mqtt) accepted: bool,
}

impl<C, E> Drop for Link<C, E> {
    fn drop(&mut self) {
        self.poller.abort();
    }
}

/// An event loop polled in the link's task: its next event, or its error
/// in words.
pub(in crate::mqtt) trait EventLoop: Send + 'static {
    /// What it yields.
    type Event: Send + 'static;
    /// The next event.
    fn next(&mut self) -> impl std::future::Future<Output = Result<Self::Event, String>> + Send;
}

/// The Sparkplug client's event loop, whose broker is the relay's: an
/// error is the relay's, if it had one (the client only saw its socket
/// close).
struct Relayed {
    eventloop: rumqttc::EventLoop,
    error: Arc<Mutex<Option<String>>>,
}

impl EventLoop for Relayed {
    type Event = Event;
    async fn next(&mut self) -> Result<Event, String> {
        self.eventloop.poll().await.map_err(|e| {
            self.error
                .lock()
                .ok()
                .and_then(|mut relayed| relayed.take())
                .unwrap_or_else(|| describe(&e))
        })
    }
}

impl<C, E: Send + 'static> Link<C, E> {
    /// `client` with its event loop polled in a task of its own.
    pub(in crate::mqtt) fn new<L: EventLoop<Event = E>>(client: C, mut eventloop: L) -> Self {
        let (tx, events) = mpsc::channel(256);
        let poller = tokio::spawn(async move {
            loop {
                let event = eventloop.next().await;
                let end = event.is_err();
                if tx.send(event).await.is_err() || end {
                    break;
                }
            }
        });
        Link {
            client,
            events,
            poller,
            relay: None,
            accepted: false,
        }
    }
}

/// The next event of `link`; never, without a connection.
pub(in crate::mqtt) async fn next_event<C, E>(
    link: &mut Option<Link<C, E>>,
) -> Option<Result<E, String>> {
    match link {
        Some(l) => l.events.recv().await,
        None => std::future::pending().await,
    }
}

/// The first wait before reconnecting; it doubles up to [`BACKOFF_MAX`].
const BACKOFF_MIN: Duration = Duration::from_millis(250);
const BACKOFF_MAX: Duration = Duration::from_secs(15);
/// A connection the broker accepted that lasted this long was a working
/// one: the wait starts over after it.
const STABLE: Duration = Duration::from_secs(10);

/// When to connect again: at once at first; after a failure, after a wait
/// that doubles from [`BACKOFF_MIN`] to [`BACKOFF_MAX`] while connections
/// keep failing, and starts over once one lasted [`STABLE`]. A connection
/// the broker accepts and then loses at once (a message it cannot take, a
/// client taking its client id) counts as failed: it never loops faster.
#[derive(Debug)]
pub(in crate::mqtt) struct Backoff {
    at: Instant,
    wait: Duration,
    /// When the broker accepted the current connection.
    since: Option<Instant>,
}

impl Backoff {
    /// Connect now.
    pub(in crate::mqtt) fn new() -> Self {
        Backoff {
            at: Instant::now(),
            wait: BACKOFF_MIN,
            since: None,
        }
    }

    /// When the next connection is due.
    pub(in crate::mqtt) fn at(&self) -> Instant {
        self.at
    }

    /// A connection failed (or could not be opened): the next one after
    /// the wait, which doubles (and starts over after a stable one).
    pub(in crate::mqtt) fn failed(&mut self) {
        let now = Instant::now();
        if self
            .since
            .take()
            .is_some_and(|since| now.duration_since(since) >= STABLE)
        {
            self.wait = BACKOFF_MIN;
        }
        self.at = now + self.wait;
        self.wait = (self.wait * 2).min(BACKOFF_MAX);
    }

    /// The broker accepted the connection (said again at each of its
    /// events: the first time counts).
    pub(in crate::mqtt) fn accepted(&mut self) {
        self.since.get_or_insert_with(Instant::now);
    }

    /// The next connection at once (the wait unchanged).
    pub(in crate::mqtt) fn at_once(&mut self) {
        self.at = Instant::now();
    }
}

/// One Sparkplug connection to the broker.
pub(super) type Connection = Link<AsyncClient, Event>;

impl Connection {
    /// Starts connecting to `config`'s broker as `client_id` with `will`,
    /// through a relay that cuts messages above `max_message_bytes` (and
    /// tells `too_large`). Fails only on what is wrong before any network
    /// traffic (the password file, the TLS files, the relay's socket).
    pub(super) fn open(
        config: &MqttConfig,
        client_id: &str,
        will: LastWill,
        too_large: &Arc<TooLarge>,
    ) -> Result<Connection, String> {
        let tls = match config.broker.tls {
            true => Some(tls_config(config)?),
            false => None,
        };
        let relay = relay::open(config, tls, too_large.clone())?;
        let mut options = MqttOptions::new(client_id, relay.path.display().to_string(), 0);
        options.set_transport(Transport::Unix);
        options.set_keep_alive(config.keepalive());
        // Sparkplug: a clean session each time, nothing left from before.
        options.set_clean_session(true);
        // What is larger is cut by the relay before it gets here.
        options.set_max_packet_size(config.max_message_bytes as usize, MAX_OUTGOING);
        options.set_last_will(will);
        if let Some((user, password)) = credentials(config)? {
            options.set_credentials(user, password);
        }
        let (client, eventloop) = AsyncClient::new(options, REQUEST_CAPACITY);
        let mut link = Link::new(
            client,
            Relayed {
                eventloop,
                error: relay.error,
            },
        );
        link.relay = Some(relay.guard);
        Ok(link)
    }
}

/// The largest packet the node sends (a DBIRTH of every metric of a drive
/// is a few kilobytes).
const MAX_OUTGOING: usize = 256 * 1024;

/// `[mqtt] username` and the first line of its `password_file`, if a user
/// is configured (both the Sparkplug and the JSON connection use them).
pub(super) fn credentials(config: &MqttConfig) -> Result<Option<(String, String)>, String> {
    let Some(user) = &config.username else {
        return Ok(None);
    };
    let password = match &config.password_file {
        Some(path) => read_password(path)?,
        None => String::new(),
    };
    Ok(Some((user.clone(), password)))
}

/// The TLS transport to an `mqtts://` broker: its CA (or the system's
/// roots) and the client's certificate, if configured.
pub(super) fn tls_transport(config: &MqttConfig) -> Result<Option<Transport>, String> {
    if !config.broker.tls {
        return Ok(None);
    }
    Ok(Some(Transport::tls_with_config(
        rumqttc::TlsConfiguration::Rustls(tls_config(config)?),
    )))
}

/// The rustls configuration for an `mqtts://` broker.
fn tls_config(config: &MqttConfig) -> Result<Arc<rustls::ClientConfig>, String> {
    let identity = match (&config.client_cert, &config.client_key) {
        (Some(cert), Some(key)) => Some((cert.get_ref().as_path(), key.as_path())),
        _ => None,
    };
    crate::tls::client_config(config.ca.as_deref(), identity)
        .map_err(|e| format!("[mqtt] TLS: {e}"))
}

fn read_password(path: &std::path::Path) -> Result<String, String> {
    std::fs::read_to_string(path)
        .map(|s| s.lines().next().unwrap_or("").to_string())
        .map_err(|e| format!("[mqtt] password_file {}: {e}", path.display()))
}

/// A message above `max_message_bytes` that reached the client: the
/// connection ends (rumqttc cannot skip it).
pub(super) fn too_large_words(bytes: usize) -> String {
    format!(
        "the broker sent a message of {bytes} bytes, above [mqtt] max_message_bytes: the client \
         cannot skip it and drops the connection. Limit the broker's messages \
         (mosquitto: max_packet_size; docs/mqtt.md) or raise max_message_bytes"
    )
}

/// A connection error in words a plant engineer can act on.
fn describe(e: &rumqttc::ConnectionError) -> String {
    use rumqttc::ConnectionError as E;
    match e {
        E::Io(io) => relay::io_words(io),
        E::MqttState(rumqttc::StateError::Deserialization(
            rumqttc::Error::PayloadSizeLimitExceeded(bytes),
        )) => too_large_words(*bytes),
        E::ConnectionRefused(code) => format!("the broker refused the connection: {code:?}"),
        E::Tls(tls) => format!("TLS with the broker: {tls}"),
        E::NetworkTimeout => "the broker did not answer in time".to_string(),
        other => other.to_string(),
    }
}
