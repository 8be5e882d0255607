//! Loopback ports for servers the tests start as separate programs
//! (mosquitto, Prometheus), which need a port number before they bind.

use std::collections::BTreeSet;
use std::sync::Mutex;

/// The ports this process has handed out: a test that asks for two (a
/// broker's plain and TLS listeners) gets two, never the same one twice
/// (found free both times, as nothing listened on it yet).
static GIVEN: Mutex<BTreeSet<u16>> = Mutex::new(BTreeSet::new());

/// A loopback port nobody listens on now, below the range the kernel hands
/// out for outgoing connections and `:0` (32768 and up, Linux's default
/// `ip_local_port_range`): no other test's connection can take it while
/// the server starts, or while it is stopped and started again. Never one
/// this process handed out before.
pub fn free_port() -> u16 {
    use rand::Rng;
    let mut rng = rand::rng();
    let mut given = GIVEN.lock().unwrap_or_else(|p| p.into_inner());
    let port = (0..1000)
        .map(|_| rng.random_range(20_000..32_000))
        .find(|&port| {
            !given.contains(&port) && std::net::TcpListener::bind(("127.0.0.1", port)).is_ok()
        })
        .expect("a free loopback port between 20000 and 32000");
    given.insert(port);
    port
}
