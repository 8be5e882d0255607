//! What the bad-input and security tests share: a daemon configuration with
//! one token per role, a bystander client that must keep getting correct
//! answers while an attack runs, the leak check (the daemon's sockets and
//! the test's tokio tasks back to their baseline), and writes counted on the wire.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use drivegate::plant::Plant;

use crate::support::TestDaemon;
use crate::support::config::ConfigBuilder;
use crate::support::modbus_tcp::{self, Raw};

/// Token secrets, one per role. Long enough that a match in a log or a
/// body cannot be a coincidence.
pub const VIEWER: &str = "viewer-5b9f2e71c4d8a036";
pub const OPERATOR: &str = "operator-0c7e14b95fa2d368";
pub const ADMIN: &str = "admin-e3a8d6f10b47c925";

/// `builder` with one `[[http.token]]` per role: dashboard (viewer), scada
/// (operator), commissioning (admin).
pub fn role_tokens(builder: ConfigBuilder) -> ConfigBuilder {
    builder
        .http_token("dashboard", "viewer", VIEWER)
        .http_token("scada", "operator", OPERATOR)
        .http_token("commissioning", "admin", ADMIN)
}

/// `FOUR_DRIVES` with `http` keys added to `[http]`, `modbus` keys to
/// `[modbus_tcp]`, the role tokens if `tokens`, and `rest` (whole tables)
/// appended.
pub fn config(http: &str, modbus: &str, tokens: bool, rest: &str) -> String {
    let builder = ConfigBuilder::four_drives().http(http).modbus_tcp(modbus);
    let builder = if tokens {
        role_tokens(builder)
    } else {
        builder
    };
    builder.tables(rest).toml()
}

/// `text` (a configuration ending with its bus's drives) with drives at
/// units 5-32 too, so that every unit of a scan's default range (1-32)
/// answers: a silent unit costs a response timeout of bus time, which
/// generated scans would otherwise spend by the second.
pub fn drives_up_to_32(text: &str) -> String {
    let mut text = text.to_string();
    for unit in 5..=32 {
        text.push_str(&format!(
            "\n[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\ngear_ratio = 1.0\n"
        ));
    }
    text
}

/// Function codes the Modbus specification defines as reads (0x2B taken as
/// its device identification read).
pub const READS: [u8; 11] = [
    0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18, 0x2B,
];

/// Writes that reached the wire on every bus: transactions of any function
/// but the reads (polls, fresh status reads and scans are 0x03).
pub fn writes_on_wire(plant: &Plant) -> u64 {
    plant
        .buses()
        .iter()
        .flat_map(|b| b.handle.stats().transactions.into_iter())
        .filter(|((function, _), _)| !READS.contains(function))
        .map(|(_, n)| n)
        .sum()
}

/// This process's TCP sockets with an end on one of `ports`: a daemon's
/// listeners and every connection to or from them, its clients' ends
/// included. The leak check counts these rather than all the process's
/// file descriptors: the other tests of the binary run beside it in the
/// same process, each with its own daemon on its own ports.
pub fn sockets_on(ports: &[u16]) -> Vec<String> {
    let mut inodes = std::collections::HashSet::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let Ok(text) = std::fs::read_to_string(table) else {
            continue;
        };
        // sl local_address rem_address st tx_queue:rx_queue tr:tm->when
        // retrnsmt uid timeout inode ...; addresses are HEXIP:HEXPORT.
        for line in text.lines().skip(1) {
            let fields: Vec<&str> = line.split_whitespace().collect();
            if fields.len() < 10 {
                continue;
            }
            let on_port = |address: &str| {
                address
                    .rsplit(':')
                    .next()
                    .and_then(|p| u16::from_str_radix(p, 16).ok())
                    .is_some_and(|p| ports.contains(&p))
            };
            if on_port(fields[1]) || on_port(fields[2]) {
                inodes.insert(format!("socket:[{}]", fields[9]));
            }
        }
    }
    std::fs::read_dir("/proc/self/fd")
        .map(|d| {
            d.filter_map(|e| e.ok())
                .filter_map(|e| std::fs::read_link(e.path()).ok())
                .map(|p| p.display().to_string())
                .filter(|target| inodes.contains(target))
                .collect()
        })
        .unwrap_or_default()
}

/// Tasks alive in this test's runtime (the daemon's included).
pub fn alive_tasks() -> usize {
    tokio::runtime::Handle::current()
        .metrics()
        .num_alive_tasks()
}

/// The daemon's sockets and the test runtime's tasks before an attack.
#[derive(Debug, Clone)]
pub struct Baseline {
    pub ports: Vec<u16>,
    pub sockets: usize,
    pub tasks: usize,
}

impl Baseline {
    /// Takes the baseline of `daemon` once the figures are steady (the
    /// same over 200 ms), within 5 s.
    pub async fn take(daemon: &TestDaemon) -> Baseline {
        let mut ports = vec![daemon.http.port()];
        ports.extend(daemon.modbus_tcp.map(|a| a.port()));
        let figures = || (sockets_on(&ports).len(), alive_tasks());
        let start = Instant::now();
        let mut last = figures();
        loop {
            tokio::time::sleep(Duration::from_millis(200)).await;
            let now = figures();
            if now == last || start.elapsed() > Duration::from_secs(5) {
                return Baseline {
                    sockets: now.0,
                    tasks: now.1,
                    ports,
                };
            }
            last = now;
        }
    }

    /// Waits (up to `limit`) for the daemon's sockets and the tasks to come
    /// back to the baseline after `what`; panics with the figures if they
    /// do not.
    pub async fn assert_back(&self, limit: Duration, what: &str) {
        let start = Instant::now();
        loop {
            let (sockets, tasks) = (sockets_on(&self.ports), alive_tasks());
            if sockets.len() <= self.sockets && tasks <= self.tasks {
                return;
            }
            if start.elapsed() > limit {
                panic!(
                    "after {what}: {} sockets on ports {:?} (baseline {}) and {tasks} tasks (baseline {}) after {limit:?}; open: {sockets:?}",
                    sockets.len(),
                    self.ports,
                    self.sockets,
                    self.tasks
                );
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// A well-behaved client running beside an attack: it asks once every
/// 20 ms and records every answer that is not the right one.
pub struct Bystander {
    stop: CancellationToken,
    task: JoinHandle<(u64, Vec<String>)>,
    answers: Arc<std::sync::atomic::AtomicU64>,
    slowest: Arc<Mutex<Duration>>,
}

/// How long one bystander request may take before it counts as a failure.
const BYSTANDER_PATIENCE: Duration = Duration::from_secs(5);

/// What the bystander's loop shares with the test.
#[derive(Clone, Default)]
pub struct Tally {
    stop: CancellationToken,
    answers: Arc<std::sync::atomic::AtomicU64>,
    slowest: Arc<Mutex<Duration>>,
}

impl Tally {
    fn stopped(&self) -> bool {
        self.stop.is_cancelled()
    }

    fn answered(&self, took: Duration) {
        self.answers
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut slowest = self.slowest.lock().unwrap();
        *slowest = (*slowest).max(took);
    }
}

impl Bystander {
    /// Reads drive 1's cached status over HTTP with `token`, expecting 200
    /// and the status block each time.
    pub fn http(addr: SocketAddr, token: Option<&str>) -> Bystander {
        let token = token.map(str::to_string);
        Self::run(move |tally| async move {
            let client = reqwest::Client::builder()
                .timeout(BYSTANDER_PATIENCE)
                .build()
                .unwrap();
            let url = format!("http://{addr}/api/v1/drives/conveyor/status");
            let (mut ok, mut failures) = (0, Vec::new());
            while !tally.stopped() {
                let mut request = client.get(&url);
                if let Some(t) = &token {
                    request = request.bearer_auth(t);
                }
                let asked = Instant::now();
                match request.send().await {
                    Ok(r) if r.status() == 200 => match r.json::<serde_json::Value>().await {
                        Ok(v) if v["drive"] == "conveyor" && v["mode"].is_string() => {
                            ok += 1;
                            tally.answered(asked.elapsed());
                        }
                        other => failures.push(format!("status body: {other:?}")),
                    },
                    Ok(r) => failures.push(format!("HTTP {}", r.status())),
                    Err(e) => failures.push(format!("request failed: {e}")),
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            (ok, failures)
        })
    }

    /// Reads the status block of unit 1 over Modbus TCP on one connection,
    /// expecting each reply to carry its request's ids and seven registers.
    pub fn modbus(addr: SocketAddr) -> Bystander {
        Self::run(move |tally| async move {
            let (mut ok, mut failures) = (0, Vec::new());
            let mut raw = Raw::connect(addr).await;
            let mut transaction: u16 = 1;
            while !tally.stopped() {
                transaction = transaction.wrapping_add(1);
                let asked = Instant::now();
                raw.send(transaction, 1, &modbus_tcp::read(0xC0, 7)).await;
                match tokio::time::timeout(BYSTANDER_PATIENCE, raw.recv()).await {
                    Ok(Some((t, 1, pdu)))
                        if t == transaction
                            && pdu.first() == Some(&0x03)
                            && pdu.len() == 2 + 14 =>
                    {
                        ok += 1;
                        tally.answered(asked.elapsed());
                    }
                    other => {
                        failures.push(format!("reply to {transaction}: {other:?}"));
                        break;
                    }
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            (ok, failures)
        })
    }

    fn run<F, Fut>(body: F) -> Bystander
    where
        F: FnOnce(Tally) -> Fut,
        Fut: std::future::Future<Output = (u64, Vec<String>)> + Send + 'static,
    {
        let tally = Tally::default();
        Bystander {
            stop: tally.stop.clone(),
            answers: tally.answers.clone(),
            slowest: tally.slowest.clone(),
            task: tokio::spawn(body(tally)),
        }
    }

    /// Waits until the client has had `n` right answers: it is connected
    /// and served before the attack starts.
    pub async fn wait_for(&self, n: u64) {
        let start = Instant::now();
        while self.answers() < n {
            assert!(
                start.elapsed() < Duration::from_secs(10) && !self.task.is_finished(),
                "the well-behaved client is not served"
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// Right answers so far.
    pub fn answers(&self) -> u64 {
        self.answers.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Stops the client; asserts it never got a wrong answer and got at
    /// least `min` right ones. Returns how many it got, and the longest an
    /// answer took.
    pub async fn finish(self, min: u64, during: &str) -> (u64, Duration) {
        // Still served once the attack is over: two more right answers.
        let target = self.answers() + 2;
        let start = Instant::now();
        while self.answers() < target
            && !self.task.is_finished()
            && start.elapsed() < Duration::from_secs(10)
        {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        let after = self.answers() >= target;
        self.stop.cancel();
        let slowest = self.slowest.clone();
        let (ok, failures) = tokio::time::timeout(Duration::from_secs(10), self.task)
            .await
            .expect("the bystander stops")
            .expect("the bystander did not panic");
        assert!(
            failures.is_empty(),
            "a well-behaved client was disturbed {} times during {during}, first: {:?}",
            failures.len(),
            &failures[..failures.len().min(3)]
        );
        assert!(
            ok >= min,
            "the well-behaved client got only {ok} answers during {during}"
        );
        assert!(
            after,
            "the well-behaved client was not served after {during}"
        );
        let slowest = *slowest.lock().unwrap();
        (ok, slowest)
    }
}

/// An HTTP answer as it came off the socket.
#[derive(Debug)]
pub struct RawAnswer {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl RawAnswer {
    /// The first header called `name` (any case).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// The body as JSON.
    pub fn json(&self) -> Option<serde_json::Value> {
        serde_json::from_slice(&self.body).ok()
    }

    /// The body as text, for messages.
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// Sends `request` (which should say `Connection: close`) on a new
/// connection and reads the whole answer, within 10 s.
pub async fn raw_http(addr: SocketAddr, request: &[u8]) -> Result<RawAnswer, String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let exchange = async {
        let mut stream = tokio::net::TcpStream::connect(addr)
            .await
            .map_err(|e| format!("connect: {e}"))?;
        // The server may answer (and close) before it has read everything:
        // a failed write is not an error as long as an answer comes.
        let _ = stream.write_all(request).await;
        let mut bytes = Vec::new();
        let _ = stream.read_to_end(&mut bytes).await;
        parse_answer(&bytes)
    };
    tokio::time::timeout(Duration::from_secs(10), exchange)
        .await
        .map_err(|_| "no answer within 10 s".to_string())?
}

/// Parses a whole HTTP/1.1 answer (content-length, chunked, or to the end).
pub fn parse_answer(bytes: &[u8]) -> Result<RawAnswer, String> {
    let split = bytes
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| {
            format!(
                "no complete answer head in {:?}",
                String::from_utf8_lossy(bytes)
            )
        })?;
    let head = String::from_utf8_lossy(&bytes[..split]).into_owned();
    let mut lines = head.split("\r\n");
    let status_line = lines.next().unwrap_or("");
    let status = status_line
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| format!("bad status line {status_line:?}"))?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(n, v)| (n.trim().to_string(), v.trim().to_string()))
        .collect();
    let rest = &bytes[split + 4..];
    let chunked = headers.iter().any(|(n, v)| {
        n.eq_ignore_ascii_case("transfer-encoding") && v.eq_ignore_ascii_case("chunked")
    });
    let body = if chunked {
        let mut body = Vec::new();
        let mut at = rest;
        loop {
            let line_end = at
                .windows(2)
                .position(|w| w == b"\r\n")
                .ok_or("bad chunk")?;
            let size = usize::from_str_radix(
                String::from_utf8_lossy(&at[..line_end])
                    .split(';')
                    .next()
                    .unwrap_or("")
                    .trim(),
                16,
            )
            .map_err(|e| format!("bad chunk size: {e}"))?;
            at = &at[line_end + 2..];
            if size == 0 {
                break;
            }
            body.extend_from_slice(at.get(..size).ok_or("short chunk")?);
            at = at.get(size + 2..).ok_or("short chunk")?;
        }
        body
    } else {
        let length = headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case("content-length"))
            .and_then(|(_, v)| v.parse::<usize>().ok());
        match length {
            Some(n) => rest.get(..n).ok_or("short body")?.to_vec(),
            None => rest.to_vec(),
        }
    };
    Ok(RawAnswer {
        status,
        headers,
        body,
    })
}

/// Checks what every answer must be: never a 5xx (the drives are healthy),
/// an error as a well-formed problem document (a 422 with its valid range,
/// a 405 with `Allow`, a 401 with `WWW-Authenticate`), or, for requests the
/// HTTP layer cannot even parse, a bare 400 or 431 before any route.
pub fn check_answer(a: &RawAnswer) -> Result<(), String> {
    let problem = |why: &str| Err(format!("{why}: {} {:?} {}", a.status, a.headers, a.text()));
    if a.status >= 500 {
        return problem("a server error");
    }
    if a.status < 400 {
        return Ok(());
    }
    if a.header("content-type") != Some("application/problem+json") {
        // hyper's own answers to requests it cannot parse: no route ran.
        if matches!(a.status, 400 | 431) && a.body.is_empty() {
            return Ok(());
        }
        return problem("an error that is not a problem document");
    }
    let Some(doc) = a.json() else {
        return problem("a problem document that is not JSON");
    };
    let well_formed = doc["type"]
        .as_str()
        .is_some_and(|t| t.starts_with("urn:drivegate:problem:"))
        && doc["title"].as_str().is_some_and(|t| !t.is_empty())
        && doc["detail"].as_str().is_some_and(|t| !t.is_empty())
        && doc["status"].as_u64() == Some(u64::from(a.status));
    if !well_formed {
        return problem("a malformed problem document");
    }
    match a.status {
        422 => {
            let range = &doc["valid_range"];
            let (min, max) = (range["min"].as_f64(), range["max"].as_f64());
            if !matches!((min, max), (Some(lo), Some(hi)) if lo <= hi) || !range["unit"].is_string()
            {
                return problem("a 422 without its valid range");
            }
        }
        405 if a.header("allow").is_none() => return problem("a 405 without Allow"),
        401 if a.header("www-authenticate").is_none() => {
            return problem("a 401 without WWW-Authenticate");
        }
        _ => {}
    }
    Ok(())
}

/// A request with `Connection: close`, the admin token (unless `token` is
/// `None`) and `extra` header lines, with `body` and its length.
pub fn request(
    method: &str,
    target: &str,
    token: Option<&str>,
    extra: &[&str],
    body: &[u8],
) -> Vec<u8> {
    let mut head =
        format!("{method} {target} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n");
    if let Some(t) = token {
        head.push_str(&format!("Authorization: Bearer {t}\r\n"));
    }
    for line in extra {
        head.push_str(line);
        head.push_str("\r\n");
    }
    if !body.is_empty() || matches!(method, "POST" | "PUT" | "PATCH") {
        head.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    head.push_str("\r\n");
    let mut bytes = head.into_bytes();
    bytes.extend_from_slice(body);
    bytes
}

/// Opens the stream on a raw socket: the WebSocket handshake by hand, so a
/// test can then send frames no client library would.
pub async fn ws_handshake(addr: SocketAddr, query: &str) -> tokio::net::TcpStream {
    ws_upgrade(tokio::net::TcpStream::connect(addr).await.unwrap(), query).await
}

/// As [`ws_handshake`], from a socket with a 4 KiB receive buffer: a
/// server writing to a client that does not read fills it at once.
pub async fn ws_handshake_small_buffer(addr: SocketAddr, query: &str) -> tokio::net::TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    ws_upgrade(socket.connect(addr).await.unwrap(), query).await
}

async fn ws_upgrade(mut stream: tokio::net::TcpStream, query: &str) -> tokio::net::TcpStream {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let request = format!(
        "GET /api/v1/stream{query} HTTP/1.1\r\nHost: localhost\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    );
    stream.write_all(request.as_bytes()).await.unwrap();
    // Byte by byte up to the end of the answer head, so no frame after it
    // is swallowed.
    let mut head = Vec::new();
    while !head.ends_with(b"\r\n\r\n") {
        let mut byte = [0u8; 1];
        let n = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut byte))
            .await
            .expect("handshake answer in time")
            .unwrap();
        assert_eq!(
            n,
            1,
            "closed during the handshake: {:?}",
            String::from_utf8_lossy(&head)
        );
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head);
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    stream
}

/// A WebSocket frame: FIN set, `opcode`, masked with a fixed key as a
/// client's must be (unless `masked` is false, a protocol violation).
pub fn ws_frame(opcode: u8, payload: &[u8], masked: bool) -> Vec<u8> {
    let mut frame = vec![0x80 | opcode];
    let mask_bit = if masked { 0x80 } else { 0 };
    match payload.len() {
        n if n < 126 => frame.push(mask_bit | n as u8),
        n if n <= 0xFFFF => {
            frame.push(mask_bit | 126);
            frame.extend_from_slice(&(n as u16).to_be_bytes());
        }
        n => {
            frame.push(mask_bit | 127);
            frame.extend_from_slice(&(n as u64).to_be_bytes());
        }
    }
    let key = [0x37, 0xFA, 0x21, 0x3D];
    if masked {
        frame.extend_from_slice(&key);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ key[i % 4]));
    } else {
        frame.extend_from_slice(payload);
    }
    frame
}
