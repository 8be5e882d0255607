//! One connection to the broker: rumqttc's client with options built from
//! `[mqtt]` (keepalive, credentials, TLS, the will), and its event loop
//! polled in a task of its own, whose events (or its error, in words) come
//! to the node over a channel. The event loop is never asked to reconnect:
//! each connection has its own will (its bdSeq), so the node opens a new
//! one instead.

use std::time::Duration;

use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Transport};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

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

impl EventLoop for rumqttc::EventLoop {
    type Event = Event;
    async fn next(&mut self) -> Result<Event, String> {
        self.poll().await.map_err(|e| describe(&e))
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

/// When to connect again: at once at first; after a failure, after a wait
/// that doubles from [`BACKOFF_MIN`] to [`BACKOFF_MAX`] while connections
/// keep failing, and starts over once the broker accepted one.
#[derive(Debug)]
pub(in crate::mqtt) struct Backoff {
    at: Instant,
    wait: Duration,
}

impl Backoff {
    /// Connect now.
    pub(in crate::mqtt) fn new() -> Self {
        Backoff {
            at: Instant::now(),
            wait: BACKOFF_MIN,
        }
    }

    /// When the next connection is due.
    pub(in crate::mqtt) fn at(&self) -> Instant {
        self.at
    }

    /// A connection failed (or could not be opened): the next one after
    /// the wait, which doubles.
    pub(in crate::mqtt) fn failed(&mut self) {
        self.at = Instant::now() + self.wait;
        self.wait = (self.wait * 2).min(BACKOFF_MAX);
    }

    /// The broker accepted a connection: the wait starts over.
    pub(in crate::mqtt) fn accepted(&mut self) {
        self.wait = BACKOFF_MIN;
    }

    /// The next connection at once (the wait unchanged).
    pub(in crate::mqtt) fn at_once(&mut self) {
        self.at = Instant::now();
    }
}

/// One Sparkplug connection to the broker.
pub(super) type Connection = Link<AsyncClient, Event>;

impl Connection {
    /// Starts connecting to `config`'s broker as `client_id` with `will`.
    /// Fails only on what is wrong before any network traffic (the
    /// password file, the TLS files).
    pub(super) fn open(
        config: &MqttConfig,
        client_id: &str,
        will: LastWill,
    ) -> Result<Connection, String> {
        let mut options =
            MqttOptions::new(client_id, config.broker.host.clone(), config.broker.port);
        options.set_keep_alive(config.keepalive());
        // Sparkplug: a clean session each time, nothing left from before.
        options.set_clean_session(true);
        options.set_max_packet_size(256 * 1024, 256 * 1024);
        options.set_last_will(will);
        if let Some((user, password)) = credentials(config)? {
            options.set_credentials(user, password);
        }
        if let Some(tls) = tls_transport(config)? {
            options.set_transport(tls);
        }
        let (client, eventloop) = AsyncClient::new(options, REQUEST_CAPACITY);
        Ok(Link::new(client, eventloop))
    }
}

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
    let identity = match (&config.client_cert, &config.client_key) {
        (Some(cert), Some(key)) => Some((cert.get_ref().as_path(), key.as_path())),
        _ => None,
    };
    let tls = crate::tls::client_config(config.ca.as_deref(), identity)
        .map_err(|e| format!("[mqtt] TLS: {e}"))?;
    Ok(Some(Transport::tls_with_config(
        rumqttc::TlsConfiguration::Rustls(tls),
    )))
}

fn read_password(path: &std::path::Path) -> Result<String, String> {
    std::fs::read_to_string(path)
        .map(|s| s.lines().next().unwrap_or("").to_string())
        .map_err(|e| format!("[mqtt] password_file {}: {e}", path.display()))
}

/// A connection error in words a plant engineer can act on.
fn describe(e: &rumqttc::ConnectionError) -> String {
    use rumqttc::ConnectionError as E;
    match e {
        E::Io(io) if io.kind() == std::io::ErrorKind::ConnectionRefused => {
            "the broker refused the TCP connection (is it running, on this port?)".to_string()
        }
        E::Io(io) => format!("connection to the broker: {io}"),
        E::ConnectionRefused(code) => format!("the broker refused the connection: {code:?}"),
        E::Tls(tls) => format!("TLS with the broker: {tls}"),
        E::NetworkTimeout => "the broker did not answer in time".to_string(),
        other => other.to_string(),
    }
}
