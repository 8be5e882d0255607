//! Who reaches plain Modbus TCP by default: a peer on a plant network, in a
//! network namespace of the test's own behind a veth pair (private-range
//! addresses inside it), against a daemon listening on every address with
//! the default configuration. It is refused at connect and logged once per
//! burst with the key to set; the start-up says why; opened with a role
//! (`[[modbus_tcp.clients]]`), it gets that role and no more.
//!
//! Making a namespace needs root (CAP_NET_ADMIN) and `ip` (iproute2):
//! where it cannot be made, the test says so and checks nothing else.

use std::process::Output;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use serde_json::json;

use crate::support::api::Api;
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::metrics::metric;
use crate::support::{TestDaemon, bounded, eventually};

const LIMIT: Duration = Duration::from_secs(120);

/// A plant-network peer: a network namespace joined to this one by a veth
/// pair, the gateway's end at `gateway` and the peer's at `peer`, in a /30
/// of 10.254.0.0/16 no interface here uses. Removed on drop.
struct PlantPeer {
    namespace: String,
    link: String,
    gateway: String,
    peer: String,
    network: String,
}

fn ip(args: &[&str]) -> Result<Output, String> {
    std::process::Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("cannot run ip (iproute2): {e}"))
}

fn ip_ok(args: &[&str]) -> Result<(), String> {
    let out = ip(args)?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

impl PlantPeer {
    fn make() -> Result<PlantPeer, String> {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let pid = std::process::id();
        let used = String::from_utf8_lossy(&ip(&["-o", "-4", "addr", "show"])?.stdout).into_owned();
        // A /30 of 10.254/16 not in use here (other runs may hold some).
        let third = (0..256u32)
            .map(|k| (pid + 7 * n + k) % 256)
            .find(|t| !used.contains(&format!("10.254.{t}.")))
            .ok_or("no free /30 in 10.254.0.0/16")?;
        let peer = PlantPeer {
            namespace: format!("drivegate-test-{pid}-{n}"),
            link: format!("dgt{}n{n}", pid % 100_000),
            gateway: format!("10.254.{third}.1"),
            peer: format!("10.254.{third}.2"),
            network: format!("10.254.{third}.0/30"),
        };
        let inside = format!("{}i", peer.link);
        ip_ok(&["netns", "add", &peer.namespace])?;
        // From here on, drop removes what was made.
        ip_ok(&[
            "link", "add", &peer.link, "type", "veth", "peer", "name", &inside,
        ])?;
        ip_ok(&["link", "set", &inside, "netns", &peer.namespace])?;
        ip_ok(&[
            "addr",
            "add",
            &format!("{}/30", peer.gateway),
            "dev",
            &peer.link,
        ])?;
        ip_ok(&["link", "set", &peer.link, "up"])?;
        let ns = |args: &[&str]| {
            let mut all = vec!["netns", "exec", &peer.namespace, "ip"];
            all.extend(args);
            ip_ok(&all)
        };
        ns(&["addr", "add", &format!("{}/30", peer.peer), "dev", &inside])?;
        ns(&["link", "set", &inside, "up"])?;
        ns(&["link", "set", "lo", "up"])?;
        Ok(peer)
    }

    /// Runs `program` with `args` inside the namespace.
    async fn run(&self, program: &str, args: &[&str]) -> Output {
        let run = tokio::process::Command::new("ip")
            .args(["netns", "exec", &self.namespace, program])
            .args(args)
            .kill_on_drop(true)
            .output();
        tokio::time::timeout(Duration::from_secs(60), run)
            .await
            .expect("the peer's program ends within 60 s")
            .expect("ip netns exec runs")
    }

    /// The pymodbus client of the tests, run by the peer against the
    /// daemon's `port` on the gateway's address; its JSON output.
    async fn pymodbus(&self, port: u16, args: &[&str]) -> serde_json::Value {
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/modbus_client.py");
        let port = port.to_string();
        let mut all = vec![script, self.gateway.as_str(), port.as_str()];
        all.extend(args);
        let out = self.run("python3", &all).await;
        let stdout = String::from_utf8_lossy(&out.stdout);
        serde_json::from_str(stdout.trim()).unwrap_or_else(|e| {
            panic!(
                "pymodbus in the namespace printed no JSON ({e}): {stdout:?} {}",
                String::from_utf8_lossy(&out.stderr)
            )
        })
    }

    /// `count` connections from the peer that send a status read each and
    /// wait for the server to close them; how many were closed without a
    /// reply.
    async fn connections(&self, port: u16, count: usize) -> usize {
        let code = format!(
            "import socket\n\
             closed = 0\n\
             for i in range({count}):\n\
             \x20   s = socket.create_connection(('{}', {port}), timeout=10)\n\
             \x20   try:\n\
             \x20       s.sendall(bytes([0, i % 256, 0, 0, 0, 6, 1, 3, 0, 0xC0, 0, 7]))\n\
             \x20       closed += s.recv(64) == b''\n\
             \x20   except (ConnectionResetError, BrokenPipeError):\n\
             \x20       closed += 1\n\
             \x20   s.close()\n\
             print(closed)\n",
            self.gateway
        );
        let out = self.run("python3", &["-c", &code]).await;
        let text = String::from_utf8_lossy(&out.stdout);
        text.trim().parse().unwrap_or_else(|_| {
            panic!(
                "the peer's connections: {text:?} {}",
                String::from_utf8_lossy(&out.stderr)
            )
        })
    }
}

impl Drop for PlantPeer {
    fn drop(&mut self) {
        // Deleting one end of a veth pair deletes both.
        let _ = ip(&["link", "del", &self.link]);
        let _ = ip(&["netns", "del", &self.namespace]);
    }
}

/// The daemon's log lines that name `peer` and say "refused".
fn refusals_of(peer: &str) -> Vec<String> {
    log_text()
        .lines()
        .filter(|l| l.contains("connection refused") && l.contains(&format!("{peer}:")))
        .map(str::to_string)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plant_network_peer_is_refused_by_default_and_let_in_with_its_role() {
    capture_logs();
    let peer = match PlantPeer::make() {
        Ok(peer) => peer,
        Err(why) => {
            eprintln!(
                "SKIPPED a_plant_network_peer_is_refused_by_default_and_let_in_with_its_role: \
                 no network namespace can be made here ({why}); it needs root and iproute2"
            );
            return;
        }
    };
    bounded(LIMIT, async {
        // The default configuration, listening on every address.
        let every = || ConfigBuilder::four_drives().modbus_tcp_listen("0.0.0.0:0");
        let plain = every().toml();
        let d = TestDaemon::reloadable(&plain).await;
        let port = d.modbus_tcp.unwrap().port();
        // The start said what is admitted and what to set.
        let start = format!("listens on 0.0.0.0:{port} but admits loopback only");
        let said: Vec<String> = log_text()
            .lines()
            .filter(|l| l.contains(&start))
            .map(str::to_string)
            .collect();
        assert_eq!(said.len(), 1, "{said:#?}");
        assert!(
            said[0].contains("WARN")
                && said[0].contains("no longer defaults to the private networks")
                && said[0].contains("[[modbus_tcp.clients]]"),
            "{}",
            said[0]
        );

        // The peer's pymodbus read: refused at connect, nothing answered.
        let burst = std::time::Instant::now();
        let out = peer.pymodbus(port, &["read", "1", "0xC0", "7"]).await;
        assert!(out.get("error").is_some(), "{out}");
        // A burst of 40 more connections: each closed, one line in the log
        // for each second the burst lasted (one on a quiet machine).
        assert_eq!(peer.connections(port, 40).await, 40);
        let seconds = burst.elapsed().as_secs() as usize;
        let text = d.metrics.render();
        let refused = "drivegate_modbus_tcp_connections_rejected_total{reason=\"not_allowed\"}";
        assert!(metric(&text, refused) >= 41.0, "{text}");
        assert_eq!(
            metric(&text, "drivegate_modbus_tcp_connections_accepted_total"),
            0.0
        );
        let lines = refusals_of(&peer.peer);
        assert!(
            !lines.is_empty() && lines.len() <= 1 + seconds,
            "one line a second for a burst of {seconds} s: {lines:#?}"
        );
        assert!(
            lines[0].contains("allowed_networks") && lines[0].contains("[[modbus_tcp.clients]]"),
            "{}",
            lines[0]
        );

        // Opened with a role: the peer's network as an operator's.
        d.rewrite(
            &every()
                .modbus_tcp(&format!(
                    "[[modbus_tcp.clients]]\nnetwork = \"{}\"\nrole = \"operator\"",
                    peer.network
                ))
                .toml(),
        );
        let api = Api::new(d.http, None);
        api.post_empty("/api/v1/config/reload").await.expect(200);
        let out = peer.pymodbus(port, &["read", "1", "0xC0", "7"]).await;
        assert_eq!(out["registers"].as_array().map(Vec::len), Some(7), "{out}");
        // An operator runs the drives (activate), and may not commission
        // them: a saved inertia is refused with 0x01, and nothing reaches
        // the drive.
        let out = peer.pymodbus(port, &["write", "1", "2", "0"]).await;
        assert_eq!(out, json!({"written": true}));
        let out = peer
            .pymodbus(port, &["write-multiple", "1", "0x24", "7,1"])
            .await;
        assert_eq!(out, json!({"exception": 1}));
        eventually(Duration::from_secs(10), "the conveyor active", || {
            d.sim().drive(1)?.active.then_some(())
        })
        .await;
        assert_ne!(d.sim().drive(1).unwrap().flash.settings.inertia_ratio, 7);
        d.stop().await;
    })
    .await;
}
