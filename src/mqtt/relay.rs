//! The Sparkplug connection's way to the broker: rumqttc's MQTT 3.1.1
//! client speaks to a UNIX socket of this process, and this relay carries
//! its bytes to the broker (over TCP, or TLS with the configured CA and
//! client certificate) and the broker's back through [`Filter`], which
//! cuts every PUBLISH above `[mqtt] max_message_bytes` down to its topic.
//!
//! Why: rumqttc's 3.1.1 client can only drop its connection on a packet
//! above its limit, and MQTT 3.1.1 has no way to tell the broker a limit
//! (MQTT 5 has, and the JSON format uses it). A 400 kB retained DCMD then
//! knocked the node off the broker at every reconnect, for as long as it
//! stayed retained. Through the relay such a message costs itself, not
//! the connection: the client acknowledges an empty message, and
//! [`TooLarge`] counts and audits it.
//!
//! The socket is in a directory of its own (mode 0700) in the temporary
//! directory, taken by the first connection only if it comes from this
//! process, and removed once taken; one relay serves one connection.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpStream, UnixListener, UnixStream};
use tokio_util::sync::{CancellationToken, DropGuard};

use super::too_large::{Cut, Filter};
use crate::config::MqttConfig;
use crate::metrics::Metrics;

/// How long the relay carries what the client sent last (its DISCONNECT)
/// once the connection is dropped.
const LINGER: Duration = Duration::from_secs(2);

/// The messages cut for their size: counted always, audited once each.
pub(super) struct TooLarge {
    metrics: Arc<Metrics>,
    /// Who sends what comes over the broker, as the audit log names it.
    who: Arc<str>,
    limit: u64,
    /// The messages already audited (topic and size): a retained one comes
    /// again at every connection, and is audited only the first time.
    audited: Mutex<Vec<(String, u64)>>,
}

/// How many cut messages are remembered as audited.
const AUDITED_KEPT: usize = 64;

impl TooLarge {
    /// The record of one face, for all its connections.
    pub(super) fn new(metrics: Arc<Metrics>, who: Arc<str>, config: &MqttConfig) -> Arc<Self> {
        Arc::new(TooLarge {
            metrics,
            who,
            limit: u64::from(config.max_message_bytes),
            audited: Mutex::new(Vec::new()),
        })
    }

    /// A message `cut` for its size.
    fn cut(&self, cut: &Cut) {
        self.metrics.mqtt().too_large();
        let key = (cut.topic.clone(), cut.bytes);
        let first = match self.audited.lock() {
            Ok(mut audited) if !audited.contains(&key) => {
                if audited.len() == AUDITED_KEPT {
                    audited.remove(0);
                }
                audited.push(key);
                true
            }
            _ => false,
        };
        if first {
            crate::control::audit::message_too_large(
                "mqtt",
                &self.who,
                &cut.topic,
                cut.bytes,
                self.limit,
                cut.retained,
            );
        } else {
            tracing::debug!(topic = %cut.topic, bytes = cut.bytes, "MQTT: a message above max_message_bytes dropped again");
        }
    }
}

/// One connection's relay: where the client connects, and what went wrong
/// on the broker's side.
pub(super) struct Relay {
    /// The socket the client connects to.
    pub(super) path: PathBuf,
    /// Why the broker could not be reached, in words, for the client's
    /// error (which only sees its socket closed).
    pub(super) error: Arc<Mutex<Option<String>>>,
    /// Stops the relay once the connection is dropped.
    pub(super) guard: DropGuard,
}

/// Opens a relay to `config`'s broker for one connection (`tls`: the
/// rustls configuration of an `mqtts://` broker).
pub(super) fn open(
    config: &MqttConfig,
    tls: Option<Arc<rustls::ClientConfig>>,
    too_large: Arc<TooLarge>,
) -> Result<Relay, String> {
    let dir = private_dir().map_err(|e| {
        format!(
            "cannot make the MQTT client's socket in {}: {e}",
            std::env::temp_dir().display()
        )
    })?;
    let path = dir.join("broker");
    let listener = std::os::unix::net::UnixListener::bind(&path)
        .and_then(|l| {
            l.set_nonblocking(true)?;
            UnixListener::from_std(l)
        })
        .map_err(|e| format!("cannot listen on {}: {e}", path.display()))?;
    let error = Arc::new(Mutex::new(None));
    let stop = CancellationToken::new();
    let broker = Broker {
        host: config.broker.host.clone(),
        port: config.broker.port,
        tls,
        limit: u64::from(config.max_message_bytes),
        error: error.clone(),
        too_large,
    };
    tokio::spawn(run(listener, dir, broker, stop.clone()));
    Ok(Relay {
        path,
        error,
        guard: stop.drop_guard(),
    })
}

/// A fresh directory only this user may enter.
fn private_dir() -> std::io::Result<PathBuf> {
    use std::os::unix::fs::DirBuilderExt;
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let base = std::env::temp_dir();
    loop {
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = base.join(format!("drivegate-mqtt-{}-{n}", std::process::id()));
        match std::fs::DirBuilder::new().mode(0o700).create(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
    }
}

/// Where and how the relay reaches the broker.
struct Broker {
    host: String,
    port: u16,
    tls: Option<Arc<rustls::ClientConfig>>,
    limit: u64,
    error: Arc<Mutex<Option<String>>>,
    too_large: Arc<TooLarge>,
}

impl Broker {
    /// The broker's side could not be opened: said for the client's error.
    fn failed(&self, why: String) {
        if let Ok(mut e) = self.error.lock() {
            *e = Some(why);
        }
    }
}

/// Takes the client's connection (this process's only), then carries its
/// bytes to and from the broker until either side closes, or until
/// [`LINGER`] after `stop`.
async fn run(listener: UnixListener, dir: PathBuf, broker: Broker, stop: CancellationToken) {
    let client = tokio::select! {
        _ = stop.cancelled() => None,
        client = accept_own(&listener) => client,
    };
    drop(listener);
    remove(&dir);
    let Some(client) = client else { return };
    let carried = async {
        let tcp = match TcpStream::connect((broker.host.as_str(), broker.port)).await {
            Ok(tcp) => tcp,
            Err(e) => return broker.failed(io_words(&e)),
        };
        let _ = tcp.set_nodelay(true);
        match &broker.tls {
            None => carry(client, tcp, &broker).await,
            Some(config) => {
                let name = match rustls::pki_types::ServerName::try_from(broker.host.clone()) {
                    Ok(name) => name,
                    Err(e) => return broker.failed(format!("TLS with the broker: {e}")),
                };
                match tokio_rustls::TlsConnector::from(config.clone())
                    .connect(name, tcp)
                    .await
                {
                    Ok(tls) => carry(client, tls, &broker).await,
                    Err(e) => broker.failed(format!("TLS with the broker: {e}")),
                }
            }
        }
    };
    tokio::select! {
        () = carried => {}
        () = async {
            stop.cancelled().await;
            tokio::time::sleep(LINGER).await;
        } => {}
    }
}

/// An I/O error reaching the broker, in words a plant engineer can act on
/// (both formats' connections say it so).
pub(super) fn io_words(io: &std::io::Error) -> String {
    if io.kind() == std::io::ErrorKind::ConnectionRefused {
        "the broker refused the TCP connection (is it running, on this port?)".to_string()
    } else {
        format!("connection to the broker: {io}")
    }
}

/// The first connection from this process; others are closed unread.
async fn accept_own(listener: &UnixListener) -> Option<UnixStream> {
    loop {
        let (stream, _) = listener.accept().await.ok()?;
        let own = stream
            .peer_cred()
            .ok()
            .and_then(|c| c.pid())
            .is_some_and(|pid| u32::try_from(pid).ok() == Some(std::process::id()));
        if own {
            return Some(stream);
        }
        tracing::warn!("MQTT: a connection to the client's socket from another process, closed");
    }
}

fn remove(dir: &Path) {
    let _ = std::fs::remove_file(dir.join("broker"));
    let _ = std::fs::remove_dir(dir);
}

/// The client's bytes to the broker as they are; the broker's to the
/// client through the filter.
async fn carry<S: AsyncRead + AsyncWrite>(client: UnixStream, server: S, broker: &Broker) {
    let (mut client_in, mut client_out) = client.into_split();
    let (mut server_in, mut server_out) = tokio::io::split(server);
    let up = async {
        let _ = tokio::io::copy(&mut client_in, &mut server_out).await;
        let _ = server_out.shutdown().await;
    };
    let down = async {
        let mut filter = Filter::new(broker.limit);
        let mut buf = vec![0u8; 16 * 1024];
        let mut out = Vec::with_capacity(16 * 1024);
        loop {
            let n = match server_in.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => n,
            };
            out.clear();
            for cut in filter.feed(&buf[..n], &mut out) {
                broker.too_large.cut(&cut);
            }
            if client_out.write_all(&out).await.is_err() {
                break;
            }
        }
    };
    tokio::select! {
        () = up => {}
        () = down => {}
    }
}
