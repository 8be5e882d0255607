//! What the console tests share: the CDP browser ([`cdp`]), a loopback TCP
//! proxy that can freeze (a cut network that closes nothing), a watcher of
//! the daemon's stream, and the drive's state as the daemon knows it.

pub use crate::support::cdp;

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

use drivegate::plant::Plant;

use crate::support::config::ConfigBuilder;

/// Token secrets, one per role.
pub const VIEWER: &str = "viewer-2f6c81d0a9e4b357";
pub const OPERATOR: &str = "operator-7a13c9e04d58b2f6";
pub const ADMIN: &str = "admin-c40e7b29f8a1d653";

/// `FOUR_DRIVES` with the role tokens (dashboard: viewer, panel: operator,
/// commissioning: admin) if `tokens`, `rest` (whole tables) appended, and
/// the jog lease of [`JOG_LEASE_MS`].
pub fn config(tokens: bool, rest: &str) -> String {
    config_with_jog_lease(tokens, rest, JOG_LEASE_MS)
}

/// [`config`] with a jog lease of `jog_lease_ms`.
pub fn config_with_jog_lease(tokens: bool, rest: &str, jog_lease_ms: u64) -> String {
    let builder = ConfigBuilder::four_drives();
    let builder = if tokens {
        builder
            .http_token("dashboard", "viewer", VIEWER)
            .http_token("panel", "operator", OPERATOR)
            .http_token("commissioning", "admin", ADMIN)
    } else {
        builder
    };
    builder
        .section("safety", &format!("jog_lease_ms = {jog_lease_ms}"))
        .tables(rest)
        .toml()
}

/// The console's jog lease in these tests (`[safety] jog_lease_ms`, 300 by
/// default): long enough that a renewal a loaded machine delays (the page
/// renews three times a lease) does not end a jog that is still held.
pub const JOG_LEASE_MS: u64 = 1000;

/// The speed the daemon last polled from `unit` on the first bus, rpm.
pub fn speed(plant: &Plant, unit: u8) -> Option<i16> {
    plant.buses()[0]
        .handle
        .drive(unit)
        .and_then(|d| d.status)
        .map(|s| s.speed_rpm)
}

/// A loopback proxy between the browser and the daemon. `freeze` stops
/// every byte both ways and closes nothing, like a pulled cable or a dead
/// switch: the daemon hears nothing more, and learns of it only by its
/// timeouts.
pub struct Proxy {
    pub addr: SocketAddr,
    frozen: Arc<AtomicBool>,
    thaw: Arc<Notify>,
}

impl Proxy {
    pub async fn start(target: SocketAddr) -> Proxy {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let frozen = Arc::new(AtomicBool::new(false));
        let thaw = Arc::new(Notify::new());
        let (f, t) = (frozen.clone(), thaw.clone());
        tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let Ok(server) = TcpStream::connect(target).await else {
                    continue;
                };
                let (cr, cw) = client.into_split();
                let (sr, sw) = server.into_split();
                tokio::spawn(pipe(cr, sw, f.clone(), t.clone()));
                tokio::spawn(pipe(sr, cw, f.clone(), t.clone()));
            }
        });
        Proxy { addr, frozen, thaw }
    }

    /// Stops carrying bytes (both ways, every connection).
    pub fn freeze(&self) {
        self.frozen.store(true, Ordering::SeqCst);
    }

    /// Carries bytes again.
    pub fn unfreeze(&self) {
        self.frozen.store(false, Ordering::SeqCst);
        self.thaw.notify_waiters();
    }
}

async fn pipe(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    frozen: Arc<AtomicBool>,
    thaw: Arc<Notify>,
) {
    let mut buf = vec![0u8; 16 * 1024];
    loop {
        let n = match from.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        // Bytes read while frozen are held until the thaw, never delivered.
        while frozen.load(Ordering::SeqCst) {
            let thawed = thaw.notified();
            if !frozen.load(Ordering::SeqCst) {
                break;
            }
            thawed.await;
        }
        if to.write_all(&buf[..n]).await.is_err() {
            return;
        }
    }
}

/// A stream client of the test's own, recording every message with the
/// instant it arrived.
pub struct Watcher {
    seen: Arc<Mutex<Vec<(Instant, Value)>>>,
    changed: Arc<Notify>,
}

impl Watcher {
    pub async fn start(addr: SocketAddr, token: Option<&str>) -> Watcher {
        let mut request = format!("ws://{addr}/api/v1/stream?drives=all")
            .into_client_request()
            .unwrap();
        if let Some(t) = token {
            request
                .headers_mut()
                .insert("authorization", format!("Bearer {t}").parse().unwrap());
        }
        let (ws, _) = tokio_tungstenite::connect_async(request).await.unwrap();
        let seen: Arc<Mutex<Vec<(Instant, Value)>>> = Arc::default();
        let changed = Arc::new(Notify::new());
        let (s, c) = (seen.clone(), changed.clone());
        tokio::spawn(async move {
            let (_sink, mut source) = ws.split();
            while let Some(Ok(m)) = source.next().await {
                if let Message::Text(t) = m
                    && let Ok(v) = serde_json::from_str::<Value>(&t)
                {
                    if v["type"] == "status" {
                        continue;
                    }
                    s.lock().unwrap().push((Instant::now(), v));
                    c.notify_waiters();
                }
            }
        });
        Watcher { seen, changed }
    }

    /// Messages so far (statuses left out).
    pub fn all(&self) -> Vec<(Instant, Value)> {
        self.seen.lock().unwrap().clone()
    }

    /// Waits for a message after `since` that `f` accepts, and returns it
    /// with the instant it arrived.
    pub async fn wait(
        &self,
        since: Instant,
        limit: Duration,
        what: &str,
        f: impl Fn(&Value) -> bool,
    ) -> (Instant, Value) {
        let start = Instant::now();
        loop {
            let notified = self.changed.notified();
            if let Some(hit) = self.all().into_iter().find(|(at, v)| *at >= since && f(v)) {
                return hit;
            }
            let left = limit.saturating_sub(start.elapsed());
            assert!(!left.is_zero(), "{what}: not seen within {limit:?}");
            let _ = tokio::time::timeout(left, notified).await;
        }
    }
}

/// Waits until `f` holds for the daemon's state, checking every 10 ms.
pub async fn until(limit: Duration, what: &str, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(start.elapsed() < limit, "{what}: not within {limit:?}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}
