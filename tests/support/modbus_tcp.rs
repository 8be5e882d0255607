//! What the Modbus TCP tests share: daemon configs, a raw MBAP client for
//! byte-exact checks, and runners for the third-party clients (pymodbus,
//! mbpoll).

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::support::config::ConfigBuilder;

/// Longest any single client exchange may take in a test.
pub(crate) const STEP: Duration = Duration::from_secs(10);

/// `FOUR_DRIVES` with extra `[modbus_tcp]` keys.
pub(crate) fn four_drives_with(modbus_tcp: &str) -> String {
    ConfigBuilder::four_drives().modbus_tcp(modbus_tcp).toml()
}

/// One simulated bus of `n` drives (units 1..=n, named `d1`...), with extra
/// `[modbus_tcp]` and `[[bus]]` keys.
pub(crate) fn drives(n: u8, modbus_tcp: &str, bus: &str) -> String {
    ConfigBuilder::new()
        .modbus_tcp(modbus_tcp)
        .bus("sim", |b| b.keys(bus).sim("seed = 11").drives(1..=n))
        .toml()
}

/// A Modbus TCP client that speaks raw MBAP, for checks no library allows
/// (pipelining, malformed frames, transaction ids).
pub(crate) struct Raw {
    pub(crate) stream: TcpStream,
    buf: Vec<u8>,
}

/// A reply: transaction id, unit id, PDU.
pub(crate) type Reply = (u16, u8, Vec<u8>);

/// The MBAP frame of a request.
pub(crate) fn frame(transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = transaction.to_be_bytes().to_vec();
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
    out.push(unit);
    out.extend_from_slice(pdu);
    out
}

impl Raw {
    /// Connects to `addr`.
    pub(crate) async fn connect(addr: SocketAddr) -> Raw {
        let stream = tokio::time::timeout(STEP, TcpStream::connect(addr))
            .await
            .expect("connect in time")
            .expect("connect");
        Raw {
            stream,
            buf: Vec::new(),
        }
    }

    /// A client over `stream`, already connected (from an address of the
    /// test's choosing: a network's role depends on it).
    pub(crate) fn from_stream(stream: TcpStream) -> Raw {
        Raw {
            stream,
            buf: Vec::new(),
        }
    }

    /// Sends one request.
    pub(crate) async fn send(&mut self, transaction: u16, unit: u8, pdu: &[u8]) {
        self.send_bytes(&frame(transaction, unit, pdu)).await;
    }

    /// Sends raw bytes.
    pub(crate) async fn send_bytes(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).await.expect("send");
    }

    /// The next reply, or `None` when the server closed the connection.
    pub(crate) async fn recv(&mut self) -> Option<Reply> {
        tokio::time::timeout(STEP, self.recv_inner())
            .await
            .expect("a reply or a close in time")
    }

    async fn recv_inner(&mut self) -> Option<Reply> {
        loop {
            if self.buf.len() >= 6 {
                let total = 6 + usize::from(u16::from_be_bytes([self.buf[4], self.buf[5]]));
                if self.buf.len() >= total {
                    let frame: Vec<u8> = self.buf.drain(..total).collect();
                    assert_eq!(&frame[2..4], &[0, 0], "protocol id of a reply");
                    return Some((
                        u16::from_be_bytes([frame[0], frame[1]]),
                        frame[6],
                        frame[7..].to_vec(),
                    ));
                }
            }
            let mut chunk = [0u8; 512];
            match self.stream.read(&mut chunk).await {
                Ok(0) | Err(_) => {
                    assert!(
                        self.buf.is_empty(),
                        "connection closed mid-frame: {:?}",
                        self.buf
                    );
                    return None;
                }
                Ok(n) => self.buf.extend_from_slice(&chunk[..n]),
            }
        }
    }

    /// Sends one request and returns the reply PDU, checking that the reply
    /// carries the request's transaction and unit ids.
    pub(crate) async fn ask(&mut self, unit: u8, pdu: &[u8]) -> Vec<u8> {
        self.ask_as(rand_transaction(), unit, pdu).await
    }

    /// [`ask`](Self::ask) with the transaction id `transaction`, for tests
    /// that look for it where the daemon reports the request's source.
    pub(crate) async fn ask_as(&mut self, transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
        self.send(transaction, unit, pdu).await;
        let (t, u, reply) = self.recv().await.expect("a reply, not a close");
        assert_eq!((t, u), (transaction, unit), "reply ids for {pdu:02X?}");
        reply
    }

    /// True once the server has closed the connection (within `STEP`).
    pub(crate) async fn closed_by_server(&mut self) -> bool {
        self.recv().await.is_none()
    }
}

fn rand_transaction() -> u16 {
    use std::sync::atomic::{AtomicU16, Ordering};
    static NEXT: AtomicU16 = AtomicU16::new(0x4000);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

/// A read of `count` registers at `address`.
pub(crate) fn read(address: u16, count: u16) -> Vec<u8> {
    let mut pdu = vec![0x03];
    pdu.extend_from_slice(&address.to_be_bytes());
    pdu.extend_from_slice(&count.to_be_bytes());
    pdu
}

/// A write of `value` to the register at `address`.
pub(crate) fn write(address: u16, value: u16) -> Vec<u8> {
    let mut pdu = vec![0x06];
    pdu.extend_from_slice(&address.to_be_bytes());
    pdu.extend_from_slice(&value.to_be_bytes());
    pdu
}

/// The registers of a 0x03 reply.
pub(crate) fn registers(reply: &[u8]) -> Vec<u16> {
    assert_eq!(reply.first(), Some(&0x03), "not a read reply: {reply:02X?}");
    assert_eq!(
        usize::from(reply[1]),
        reply.len() - 2,
        "byte count of {reply:02X?}"
    );
    reply[2..]
        .chunks(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect()
}

/// Runs the pymodbus client script with `args`; its JSON output. Fails the
/// test, saying what to install, when python3 or pymodbus is missing.
pub(crate) async fn pymodbus(addr: SocketAddr, args: &[&str]) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/modbus_client.py");
    let mut cmd = tokio::process::Command::new("python3");
    cmd.arg(script)
        .arg(addr.ip().to_string())
        .arg(addr.port().to_string())
        .args(args)
        .kill_on_drop(true);
    let output = match cmd.output_within(Duration::from_secs(60)).await {
        Ok(o) => o,
        Err(e) => panic!(
            "cannot run python3 ({e}): {}",
            crate::support::tools::how_to_get("pymodbus")
        ),
    };
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_ne!(
        output.status.code(),
        Some(3),
        "pymodbus is missing: {} ({stderr})",
        crate::support::tools::how_to_get("pymodbus")
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| {
        panic!("pymodbus client printed no JSON ({e}): stdout {stdout:?} stderr {stderr:?}")
    })
}

/// A PLC: the pymodbus client of `tests/python/plc_client.py` in a process
/// of its own, told what to do line by line (write, poll in the
/// background, fall silent, close).
pub(crate) struct Plc {
    child: tokio::process::Child,
    stdin: tokio::process::ChildStdin,
    lines: tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
}

impl Plc {
    /// Starts the client and connects it to `addr`. Fails the test, saying
    /// what to install, when python3 or pymodbus is missing.
    pub(crate) async fn connect(addr: SocketAddr) -> Plc {
        use tokio::io::AsyncBufReadExt;
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/plc_client.py");
        let mut child = tokio::process::Command::new("python3")
            .arg(script)
            .arg(addr.ip().to_string())
            .arg(addr.port().to_string())
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot run python3 ({e}): {}",
                    crate::support::tools::how_to_get("pymodbus")
                )
            });
        let stdin = child.stdin.take().expect("stdin");
        let stdout = child.stdout.take().expect("stdout");
        let mut plc = Plc {
            child,
            stdin,
            lines: tokio::io::BufReader::new(stdout).lines(),
        };
        let hello = plc.answer().await;
        assert_eq!(hello["connected"], true, "{hello}");
        plc
    }

    async fn answer(&mut self) -> serde_json::Value {
        let line = tokio::time::timeout(STEP, self.lines.next_line())
            .await
            .expect("the PLC client answers in time")
            .expect("the PLC client's output");
        let Some(line) = line else {
            let status = self.child.try_wait().ok().flatten();
            assert_ne!(
                status.and_then(|s| s.code()),
                Some(3),
                "pymodbus is missing: {}",
                crate::support::tools::how_to_get("pymodbus")
            );
            panic!("the PLC client ended ({status:?})");
        };
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("not JSON ({e}): {line:?}"))
    }

    /// Sends one command line; its JSON answer.
    pub(crate) async fn tell(&mut self, command: &str) -> serde_json::Value {
        self.stdin
            .write_all(format!("{command}\n").as_bytes())
            .await
            .expect("the PLC client reads its commands");
        self.answer().await
    }

    /// Writes `value` to `address` of `unit`, expecting the echo.
    pub(crate) async fn write(&mut self, unit: u8, address: u16, value: u16) {
        let answer = self.tell(&format!("write {unit} {address} {value}")).await;
        assert_eq!(
            answer["written"], true,
            "write {address:#06x} = {value}: {answer}"
        );
    }

    /// Kills the process (SIGKILL) and waits for it.
    pub(crate) async fn kill(mut self) {
        self.child.kill().await.expect("the PLC client killed");
    }
}

/// Runs mbpoll with `options` against `addr` (writing `values` if any); its
/// exit success and stdout+stderr. Fails the test, saying what to install,
/// when mbpoll is missing.
pub(crate) async fn mbpoll(addr: SocketAddr, options: &[&str], values: &[&str]) -> (bool, String) {
    let mut cmd = tokio::process::Command::new("mbpoll");
    cmd.args(["-m", "tcp", "-p", &addr.port().to_string(), "-1", "-o", "3"])
        .args(options)
        .arg(addr.ip().to_string())
        .args(values)
        .kill_on_drop(true);
    let output = match cmd.output_within(Duration::from_secs(30)).await {
        Ok(o) => o,
        Err(e) => panic!("{}", crate::support::tools::cannot_run("mbpoll", &e)),
    };
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    (output.status.success(), text)
}

/// `Command::output` with a time limit.
trait OutputWithin {
    async fn output_within(&mut self, limit: Duration) -> std::io::Result<std::process::Output>;
}

impl OutputWithin for tokio::process::Command {
    async fn output_within(&mut self, limit: Duration) -> std::io::Result<std::process::Output> {
        match tokio::time::timeout(limit, self.output()).await {
            Ok(r) => r,
            Err(_) => panic!("{self:?} did not finish within {limit:?}"),
        }
    }
}

/// Writes (function 0x06) the bus has dealt with: sent, failed or dropped.
pub fn writes_handled(bus: &drivegate::bus::BusHandle) -> u64 {
    bus.stats()
        .transactions
        .iter()
        .filter(|((function, _), _)| *function == 0x06)
        .map(|(_, n)| n)
        .sum()
}

/// A SCADA that models each drive as a device with a connection of its
/// own: the pymodbus client of `tests/python/scada_client.py` in a process
/// of its own, every connection from one loopback address.
pub(crate) struct Scada {
    _child: tokio::process::Child,
    stdin: tokio::process::ChildStdin,
    lines: tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
}

impl Scada {
    /// Opens `units` connections to `addr` from `source` (units 1 to
    /// `units`); what the client said of them.
    pub(crate) async fn connect(
        addr: SocketAddr,
        source: &str,
        units: u8,
    ) -> (Scada, serde_json::Value) {
        use tokio::io::AsyncBufReadExt;
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/scada_client.py");
        let mut child = tokio::process::Command::new("python3")
            .arg(script)
            .arg(addr.ip().to_string())
            .arg(addr.port().to_string())
            .arg(source)
            .arg(units.to_string())
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot run python3 ({e}): {}",
                    crate::support::tools::how_to_get("pymodbus")
                )
            });
        let stdin = child.stdin.take().expect("stdin");
        let stdout = child.stdout.take().expect("stdout");
        let mut scada = Scada {
            _child: child,
            stdin,
            lines: tokio::io::BufReader::new(stdout).lines(),
        };
        let hello = scada.answer().await;
        (scada, hello)
    }

    async fn answer(&mut self) -> serde_json::Value {
        let line = tokio::time::timeout(Duration::from_secs(30), self.lines.next_line())
            .await
            .expect("the SCADA client answers in time")
            .expect("the SCADA client's output")
            .unwrap_or_else(|| {
                panic!(
                    "the SCADA client ended without a word (pymodbus missing? {})",
                    crate::support::tools::how_to_get("pymodbus")
                )
            });
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("not JSON ({e}): {line:?}"))
    }

    /// Every connection reads its drive's status block at once; the
    /// client's account (`answered`, `failed`, `slowest_ms`).
    pub(crate) async fn round(&mut self) -> serde_json::Value {
        self.stdin
            .write_all(b"round\n")
            .await
            .expect("the SCADA client reads its commands");
        self.answer().await
    }
}
