//! What the daemon costs a small box: the CPU and memory of a `drivegate
//! serve` process (a child of the benchmark, the built binary), from
//! `/proc/<pid>/stat` (user + system time of all its threads) over the
//! window and `VmRSS` at its end.
//!
//! Scenarios (`DRIVEGATE_BENCH_ONLY=full,polling,serve`):
//! - `full`: 16 Modbus TCP clients (tokio-modbus, in this process) read the
//!   status block of 8 drives back to back, keeping the bus full; the
//!   drives are an external wire-timed simulator (`drivegate sim --link`,
//!   another process, 0.5 ms turnaround), the daemon polls at 1 Hz. CPU per
//!   bus transaction (every transaction the daemon made in the window, its
//!   polls included), the wire's use (answered transactions against the
//!   limit, 157.6 a second), the clients' p50 / p99 and the master's
//!   silence before a request (p50 / p99, `drivegate_bus_interframe_idle_seconds`);
//! - `polling`: the same bus polled at the wire's rate
//!   (`poll_interval_ms = 0`), nobody connected: share of a core, memory;
//! - `serve`: the built-in configuration (`config/default.toml`: one
//!   simulated bus of 4 drives polled at the wire's rate, HTTP, Modbus TCP
//!   and OPC UA on loopback, here on free ports), nobody connected: share of
//!   a core (the simulator's thread included), memory.
//!
//! The machine's load average is printed with every run: on a shared
//! machine CPU time is what to compare, not wall time.
//!
//! `cargo bench --bench footprint`; `DRIVEGATE_BENCH_SECS` sets the window
//! (default 20 s); `DRIVEGATE_BENCH_MBUSD=/path/to/mbusd` adds mbusd on
//! the same simulator with the same clients (`full` only);
//! `DRIVEGATE_BENCH_BIN=/path/to/drivegate` measures another build (the
//! simulator is that build's too, or `DRIVEGATE_BENCH_SIM_BIN`'s);
//! `DRIVEGATE_BENCH_PERF=<dir>` records the daemon with `perf record -e
//! cpu-clock --call-graph dwarf` over each window
//! (`<dir>/<scenario>.perf.data`; the sampling costs the daemon CPU, so
//! its figures are not to be compared then);
//! `DRIVEGATE_BENCH_WRAP="valgrind --tool=callgrind ..."` runs the daemon
//! under a tool (instruction counts do not depend on the machine's load;
//! the timing does, so only the counts mean anything then).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::collections::BTreeMap;
use std::io::BufRead;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use drivegate::modbus::timing::LineTiming;
use tokio_modbus::client::Reader;
use tokio_modbus::{Slave, client::tcp};

const CLIENTS: usize = 16;
const DRIVES: u8 = 8;
const BAUD: u32 = 115_200;
const TURNAROUND_MS: f64 = 0.5;

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .unwrap_or_default()
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ")
}

/// CPU seconds (user + system, every thread) of process `pid` so far.
fn cpu_s(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0)
        + f.get(12).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // The kernel counts in USER_HZ, 100 a second on Linux.
    ticks / 100.0
}

/// Time on the CPU of every thread of `pid` so far, seconds, to the
/// nanosecond (`/proc/<pid>/task/*/schedstat`): a cross-check of
/// [`cpu_s`], whose ticks are 10 ms.
fn run_time_s(pid: u32) -> f64 {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return 0.0;
    };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e9
}

/// Times the threads of `pid` went to sleep so far (voluntary context
/// switches): each is a wake-up, which costs far more than the work most
/// of them do, and their count does not depend on the machine's load.
fn sleeps(pid: u32) -> BTreeMap<String, u64> {
    let mut by_name = BTreeMap::new();
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return by_name;
    };
    for status in tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("status")).ok())
    {
        let field = |key: &str| {
            status
                .lines()
                .find_map(|l| l.strip_prefix(key))
                .map(|v| v.trim().to_string())
        };
        let n = field("voluntary_ctxt_switches:")
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(0);
        *by_name
            .entry(field("Name:").unwrap_or_default())
            .or_insert(0) += n;
    }
    by_name
}

/// The wake-ups of each kind of thread between two [`sleeps`].
fn sleeps_since(
    before: &BTreeMap<String, u64>,
    after: &BTreeMap<String, u64>,
) -> Vec<(String, u64)> {
    after
        .iter()
        .map(|(name, n)| {
            (
                name.clone(),
                n - before.get(name).copied().unwrap_or(0).min(*n),
            )
        })
        .filter(|(_, n)| *n > 0)
        .collect()
}

/// Resident memory of `pid`, MiB: all of it (`VmRSS`), its anonymous part
/// (the heap, stacks) and its file part (the binary's and libraries' pages).
fn rss_mib(pid: u32) -> [f64; 3] {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    ["VmRSS:", "RssAnon:", "RssFile:"].map(|key| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|kb| kb.parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    })
}

/// The sum of the samples of `name` whose labels contain every `labels`
/// pair (`key="value"`), in a Prometheus text exposition.
fn metric(text: &str, name: &str, labels: &[&str]) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (head, value) = l.rsplit_once(' ')?;
            let (n, rest) = head.split_once('{').unwrap_or((head, ""));
            (n == name && labels.iter().all(|p| rest.contains(p))).then_some(value)
        })
        .filter_map(|v| v.parse::<f64>().ok())
        .sum()
}

/// A quantile of a histogram between two scrapes, ms (linear inside a
/// bucket, as Prometheus does).
fn histogram_ms(before: &str, after: &str, name: &str, bus: &str, p: f64) -> f64 {
    let bucket = format!("{name}_bucket");
    let buckets = |text: &str| -> Vec<(f64, f64)> {
        text.lines()
            .filter(|l| l.starts_with(&bucket) && l.contains(bus))
            .filter_map(|l| {
                let le = l.split("le=\"").nth(1)?.split('"').next()?;
                let le = if le == "+Inf" {
                    f64::INFINITY
                } else {
                    le.parse().ok()?
                };
                Some((le, l.rsplit_once(' ')?.1.parse().ok()?))
            })
            .collect()
    };
    let (b, a) = (buckets(before), buckets(after));
    let counts: Vec<(f64, f64)> = a
        .iter()
        .map(|&(le, n)| {
            let was = b.iter().find(|(l, _)| *l == le).map_or(0.0, |x| x.1);
            (le, n - was)
        })
        .collect();
    let total = counts.last().map_or(0.0, |c| c.1);
    if total == 0.0 {
        return f64::NAN;
    }
    let rank = p * total;
    let mut lower = (0.0, 0.0);
    for &(le, cumulative) in &counts {
        if cumulative >= rank {
            if le.is_infinite() {
                return lower.0 * 1e3;
            }
            let inside = cumulative - lower.1;
            let share = if inside > 0.0 {
                (rank - lower.1) / inside
            } else {
                1.0
            };
            return (lower.0 + (le - lower.0) * share) * 1e3;
        }
        lower = (le, cumulative);
    }
    lower.0 * 1e3
}

fn percentile_ms(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e3
}

/// The wire's limit of status reads a second (request and reply on the
/// wire, two t3.5 silences, the drives' turnaround).
fn limit_per_s() -> f64 {
    let line = LineTiming::new_8n1(BAUD);
    1.0 / line
        .transaction_time(8, 19, Duration::from_secs_f64(TURNAROUND_MS / 1e3))
        .as_secs_f64()
}

/// The binary measured: `DRIVEGATE_BENCH_BIN` (another build, to compare
/// with), else the one built with the benchmark.
fn binary() -> PathBuf {
    std::env::var_os("DRIVEGATE_BENCH_BIN").map_or_else(
        || PathBuf::from(env!("CARGO_BIN_EXE_drivegate")),
        PathBuf::from,
    )
}

/// The external simulator's binary: `DRIVEGATE_BENCH_SIM_BIN`, else
/// [`binary`].
fn sim_binary() -> PathBuf {
    std::env::var_os("DRIVEGATE_BENCH_SIM_BIN").map_or_else(binary, PathBuf::from)
}

/// `drivegate sim --link`: the process and the link.
fn external_sim(dir: &Path) -> (Child, PathBuf) {
    let link = dir.join("ttyDRIVES");
    let mut child = Command::new(sim_binary())
        .arg("sim")
        .arg("--link")
        .arg(&link)
        .arg("--units")
        .arg(format!("1-{DRIVES}"))
        .arg("--turnaround-ms")
        .arg(TURNAROUND_MS.to_string())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
    out.read_line(&mut line).unwrap();
    assert!(!line.is_empty(), "the simulator did not start");
    child.stdout = Some(out.into_inner());
    (child, link)
}

/// The simulator's counters line, printed when it ends.
fn stop_sim(mut sim: Child) -> String {
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(sim.id().to_string())
        .status();
    let mut line = String::new();
    if let Some(out) = sim.stdout.take() {
        let _ = std::io::BufReader::new(out).read_line(&mut line);
    }
    let _ = sim.wait();
    line.trim().to_string()
}

struct Daemon {
    child: Child,
    http: u16,
    modbus: u16,
}

impl Daemon {
    /// Starts `drivegate serve` on `toml` (which listens on `http` and
    /// `modbus`), under `DRIVEGATE_BENCH_WRAP` if set.
    fn spawn(dir: &Path, toml: &str, http: u16, modbus: u16) -> Daemon {
        let file = dir.join("drivegate.toml");
        std::fs::write(&file, toml).unwrap();
        let wrap: Vec<String> = std::env::var("DRIVEGATE_BENCH_WRAP")
            .map(|w| w.split_whitespace().map(str::to_string).collect())
            .unwrap_or_default();
        let mut cmd = match wrap.split_first() {
            Some((tool, args)) => {
                let mut c = Command::new(tool);
                c.args(args).arg(binary());
                c
            }
            None => Command::new(binary()),
        };
        let child = cmd
            .args(["serve", "--config"])
            .arg(&file)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("daemon.log")).unwrap())
            .spawn()
            .unwrap();
        Daemon {
            child,
            http,
            modbus,
        }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    async fn scrape(&self, http: &reqwest::Client) -> String {
        let url = format!("http://127.0.0.1:{}/metrics", self.http);
        for _ in 0..50 {
            if let Ok(r) = http.get(&url).send().await
                && let Ok(text) = r.text().await
            {
                return text;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        panic!("the daemon's /metrics did not answer");
    }

    /// Until every drive of bus `bus` has been polled (and, with `opcua`,
    /// the OPC UA server serves: its first start makes its certificate,
    /// seconds of CPU that are no part of running).
    async fn ready(&self, http: &reqwest::Client, bus: &str, drives: u8, opcua: bool) {
        let start = Instant::now();
        loop {
            assert!(
                start.elapsed() < Duration::from_secs(120),
                "the daemon did not come up"
            );
            let url = format!("http://127.0.0.1:{}/metrics", self.http);
            if let Ok(r) = http.get(&url).send().await
                && let Ok(text) = r.text().await
            {
                let label = format!("bus=\"{bus}\"");
                if metric(&text, "drivegate_bus_polls_total", &[&label]) >= f64::from(drives)
                    && (!opcua || metric(&text, "drivegate_opcua_up", &[]) >= 1.0)
                {
                    return;
                }
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `perf record` on `pid` while it lives, if `DRIVEGATE_BENCH_PERF` names
/// a directory.
fn perf(pid: u32, name: &str) -> Option<Child> {
    let dir = std::env::var("DRIVEGATE_BENCH_PERF").ok()?;
    std::fs::create_dir_all(&dir).ok()?;
    Command::new("perf")
        .args([
            "record",
            "-e",
            "cpu-clock",
            "-F",
            "4999",
            "--call-graph",
            "dwarf,16384",
        ])
        .args(["-q", "-o"])
        .arg(Path::new(&dir).join(format!("{name}.perf.data")))
        .arg("-p")
        .arg(pid.to_string())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .ok()
}

fn stop_perf(perf: Option<Child>) {
    if let Some(mut p) = perf {
        let _ = Command::new("kill")
            .arg("-INT")
            .arg(p.id().to_string())
            .status();
        let _ = p.wait();
    }
}

/// The clients of `full`: each reads the status block of one drive back
/// to back until `deadline`. The latencies (sorted) and the errors.
async fn clients(addr: SocketAddr, deadline: Instant) -> (Vec<Duration>, usize) {
    let mut tasks = Vec::new();
    for client in 0..CLIENTS {
        let unit = (client % usize::from(DRIVES)) as u8 + 1;
        tasks.push(tokio::spawn(async move {
            let mut ctx = tcp::connect_slave(addr, Slave(unit)).await.unwrap();
            let mut latencies = Vec::new();
            let mut errors = 0;
            while Instant::now() < deadline {
                let sent = Instant::now();
                match ctx.read_holding_registers(0x00C0, 7).await {
                    Ok(Ok(regs)) if regs.len() == 7 => latencies.push(sent.elapsed()),
                    _ => errors += 1,
                }
            }
            (latencies, errors)
        }));
    }
    let mut latencies = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let (l, e) = t.await.unwrap();
        latencies.extend(l);
        errors += e;
    }
    latencies.sort();
    (latencies, errors)
}

/// What a thread spends being woken on this machine, in us of CPU a
/// wake-up: 2000 sleeps of 1.75 ms (a t3.5 at 115200 baud) to absolute
/// deadlines, in a thread that does nothing else, its own CPU clock read
/// before and after. On a virtual machine an idle core woken by a timer
/// costs far more than on bare metal, and a transaction's wake-ups cost at
/// least that many times this, whatever the daemon does when awake.
fn wake_cost_us() -> f64 {
    const SLEEPS: u32 = 2000;
    let thread = std::thread::spawn(|| {
        use nix::time::{ClockId, clock_gettime};
        let cpu = || {
            clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID)
                .map(|t| Duration::from(t).as_secs_f64())
                .unwrap_or(0.0)
        };
        let step = Duration::from_micros(1750);
        let before = cpu();
        let mut deadline = Instant::now();
        for _ in 0..SLEEPS {
            deadline += step;
            std::thread::sleep(deadline.saturating_duration_since(Instant::now()));
        }
        1e6 * (cpu() - before) / f64::from(SLEEPS)
    });
    thread.join().unwrap_or(0.0)
}

/// This machine's cost of a wake-up ([`wake_cost_us`]), once measured.
static WAKE_COST_US: std::sync::OnceLock<f64> = std::sync::OnceLock::new();

/// What one window measured.
#[derive(Default)]
struct Window {
    secs: f64,
    cpu_s: f64,
    run_s: f64,
    sleeps: Vec<(String, u64)>,
    rss_mib: [f64; 3],
    transactions: f64,
    answered: f64,
    idle_p50_ms: f64,
    idle_p99_ms: f64,
    latencies: Vec<Duration>,
    errors: usize,
    load_before: String,
    load_after: String,
}

impl Window {
    fn share(&self) -> f64 {
        100.0 * self.cpu_s / self.secs
    }

    fn wake_ups(&self) -> u64 {
        self.sleeps.iter().map(|(_, n)| n).sum()
    }

    fn print(&self, name: &str, sim: &str) {
        println!(
            "{name}: {:.1} s, load {} -> {}; CPU {:.2} s = {:.2} % of a core (run time {:.2} %), {:.0} wake-ups/s, RSS {:.1} MiB (anonymous {:.1}, file {:.1})",
            self.secs,
            self.load_before,
            self.load_after,
            self.cpu_s,
            self.share(),
            100.0 * self.run_s / self.secs,
            self.wake_ups() as f64 / self.secs,
            self.rss_mib[0],
            self.rss_mib[1],
            self.rss_mib[2],
        );
        if self.transactions > 0.0 {
            println!(
                "  {:.0} transactions ({:.1}/s, {:.1} % of the limit answered): {:.0} us of CPU each (run time {:.0} us), {:.1} wake-ups each; master idle p50 / p99 {:.3} / {:.3} ms",
                self.transactions,
                self.transactions / self.secs,
                100.0 * self.answered / self.secs / limit_per_s(),
                1e6 * self.cpu_s / self.transactions,
                1e6 * self.run_s / self.transactions,
                self.wake_ups() as f64 / self.transactions,
                self.idle_p50_ms,
                self.idle_p99_ms,
            );
        }
        if self.transactions > 0.0 {
            let threads: Vec<String> = self
                .sleeps
                .iter()
                .map(|(name, n)| format!("{name} {:.1}", *n as f64 / self.transactions))
                .collect();
            println!("  wake-ups per transaction: {}", threads.join(", "));
            if let Some(cost) = WAKE_COST_US.get() {
                println!(
                    "  those wake-ups at this machine's {cost:.0} us each: {:.0} us a transaction",
                    cost * self.wake_ups() as f64 / self.transactions
                );
            }
        }
        if !self.latencies.is_empty() || self.errors > 0 {
            println!(
                "  clients: {} reads, p50 / p99 / max {:.1} / {:.1} / {:.1} ms, {} errors",
                self.latencies.len(),
                percentile_ms(&self.latencies, 0.5),
                percentile_ms(&self.latencies, 0.99),
                percentile_ms(&self.latencies, 1.0),
                self.errors
            );
        }
        if !sim.is_empty() {
            println!("  simulator: {sim}");
        }
    }
}

/// Measures `daemon` over `secs`, with the clients of `full` if `clients`.
async fn window(
    daemon: &Daemon,
    http: &reqwest::Client,
    bus: &str,
    name: &str,
    secs: f64,
    clients_on: bool,
) -> Window {
    let label = format!("bus=\"{bus}\"");
    let perf = perf(daemon.pid(), name);
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    let before = daemon.scrape(http).await;
    let load_before = load();
    let (cpu0, run0, t0) = (
        cpu_s(daemon.pid()),
        run_time_s(daemon.pid()),
        Instant::now(),
    );
    let sleeps0 = sleeps(daemon.pid());
    let (latencies, errors) = if clients_on {
        clients(SocketAddr::from(([127, 0, 0, 1], daemon.modbus)), deadline).await
    } else {
        tokio::time::sleep_until(deadline.into()).await;
        (Vec::new(), 0)
    };
    let (cpu1, run1, t1) = (
        cpu_s(daemon.pid()),
        run_time_s(daemon.pid()),
        Instant::now(),
    );
    let sleeps1 = sleeps(daemon.pid());
    let after = daemon.scrape(http).await;
    stop_perf(perf);
    let count = |text: &str, outcome: Option<&str>| {
        let o = outcome.map(|o| format!("outcome=\"{o}\""));
        let mut labels = vec![label.as_str()];
        if let Some(o) = &o {
            labels.push(o);
        }
        metric(text, "drivegate_bus_transactions_total", &labels)
    };
    let idle = "drivegate_bus_interframe_idle_seconds";
    Window {
        secs: (t1 - t0).as_secs_f64(),
        cpu_s: cpu1 - cpu0,
        run_s: run1 - run0,
        sleeps: sleeps_since(&sleeps0, &sleeps1),
        rss_mib: rss_mib(daemon.pid()),
        transactions: count(&after, None) - count(&before, None),
        answered: count(&after, Some("ok")) - count(&before, Some("ok")),
        idle_p50_ms: histogram_ms(&before, &after, idle, &label, 0.5),
        idle_p99_ms: histogram_ms(&before, &after, idle, &label, 0.99),
        latencies,
        errors,
        load_before,
        load_after: load(),
    }
}

/// A configuration of the daemon on the external simulator at `link`.
fn link_config(dir: &Path, link: &Path, http: u16, modbus: u16, poll_interval_ms: u64) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:{http}\"\n\
         [modbus_tcp]\nlisten = \"127.0.0.1:{modbus}\"\nmax_connections_per_address = 64\n\
         [log]\nlevel = \"warn\"\n\
         [safety]\nstate_dir = \"{}\"\non_shutdown = \"none\"\n\
         [[bus]]\nname = \"bench\"\nport = \"{}\"\nbaud = {BAUD}\nresponse_timeout_ms = 50\n\
         retries = 1\npoll_interval_ms = {poll_interval_ms}\n",
        dir.join("state").display(),
        link.display()
    );
    for unit in 1..=DRIVES {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\ngear_ratio = 3.75\n"
        ));
    }
    toml
}

/// `full` or `polling`: the daemon on an external simulator.
async fn on_external_sim(name: &str, secs: f64, clients_on: bool) {
    let dir = tempfile::tempdir().unwrap();
    let (sim, link) = external_sim(dir.path());
    let (http_port, modbus_port) = (free_port(), free_port());
    let poll = if clients_on { 1000 } else { 0 };
    let toml = link_config(dir.path(), &link, http_port, modbus_port, poll);
    let daemon = Daemon::spawn(dir.path(), &toml, http_port, modbus_port);
    let http = reqwest::Client::new();
    daemon.ready(&http, "bench", DRIVES, false).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let w = window(&daemon, &http, "bench", name, secs, clients_on).await;
    drop(daemon);
    w.print(name, &stop_sim(sim));
}

/// `serve`: the built-in configuration, its listeners on free ports.
async fn serve(secs: f64) {
    let dir = tempfile::tempdir().unwrap();
    let (http_port, modbus_port, opcua_port) = (free_port(), free_port(), free_port());
    let default = include_str!("../config/default.toml")
        .replace("127.0.0.1:8080", &format!("127.0.0.1:{http_port}"))
        .replace("127.0.0.1:5020", &format!("127.0.0.1:{modbus_port}"))
        .replace("127.0.0.1:4840", &format!("127.0.0.1:{opcua_port}"));
    // The state directory `serve` alone would take from $HOME, and the
    // default log level.
    let toml = format!(
        "[safety]\nstate_dir = \"{}\"\n\n{default}",
        dir.path().join("state").display()
    );
    let daemon = Daemon::spawn(dir.path(), &toml, http_port, modbus_port);
    let http = reqwest::Client::new();
    daemon.ready(&http, "sim", 4, true).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let w = window(&daemon, &http, "sim", "serve", secs, false).await;
    w.print("serve", "");
}

/// mbusd on the external simulator with the clients of `full`.
async fn mbusd(path: &str, secs: f64) {
    let dir = tempfile::tempdir().unwrap();
    let (sim, link) = external_sim(dir.path());
    let port = free_port();
    let mut child = Command::new(path)
        .args(["-d", "-L", "-", "-v", "0", "-p"])
        .arg(&link)
        .args(["-s", "115200", "-A", "127.0.0.1", "-P"])
        .arg(port.to_string())
        .args(["-R", "2", "-W", "50", "-N", "1", "-C", "32", "-T", "0"])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    let up = Instant::now();
    while tokio::net::TcpStream::connect(addr).await.is_err() {
        assert!(
            up.elapsed() < Duration::from_secs(5),
            "mbusd did not listen"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let pid = child.id();
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    let load_before = load();
    let (cpu0, run0, t0) = (cpu_s(pid), run_time_s(pid), Instant::now());
    let sleeps0 = sleeps(pid);
    let (latencies, errors) = clients(addr, deadline).await;
    let (cpu1, run1, t1) = (cpu_s(pid), run_time_s(pid), Instant::now());
    let sleeps1 = sleeps(pid);
    let w = Window {
        secs: (t1 - t0).as_secs_f64(),
        cpu_s: cpu1 - cpu0,
        run_s: run1 - run0,
        sleeps: sleeps_since(&sleeps0, &sleeps1),
        rss_mib: rss_mib(pid),
        // mbusd does not poll: every transaction is a client's read.
        transactions: latencies.len() as f64,
        answered: latencies.len() as f64,
        idle_p50_ms: f64::NAN,
        idle_p99_ms: f64::NAN,
        latencies,
        errors,
        load_before,
        load_after: load(),
    };
    let _ = child.kill();
    let _ = child.wait();
    w.print("mbusd", &stop_sim(sim));
}

#[tokio::main]
async fn main() {
    let secs: f64 = std::env::var("DRIVEGATE_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20.0);
    let only: Option<Vec<String>> = std::env::var("DRIVEGATE_BENCH_ONLY")
        .ok()
        .map(|s| s.split(',').map(|t| t.trim().to_string()).collect());
    let wanted = |name: &str| only.as_ref().is_none_or(|o| o.iter().any(|t| t == name));
    println!(
        "footprint: {secs} s windows; the wire's limit {:.1} status reads/s ({DRIVES} drives, {BAUD} baud, turnaround {TURNAROUND_MS} ms)",
        limit_per_s()
    );
    let cost = WAKE_COST_US.get_or_init(wake_cost_us);
    println!(
        "this machine: a thread woken from a 1.75 ms sleep spends {cost:.0} us of CPU a wake-up (2000 sleeps, load {})",
        load()
    );
    if wanted("full") {
        on_external_sim("full", secs, true).await;
    }
    if wanted("full")
        && let Ok(path) = std::env::var("DRIVEGATE_BENCH_MBUSD")
    {
        mbusd(&path, secs).await;
    }
    if wanted("polling") {
        on_external_sim("polling", secs, false).await;
    }
    if wanted("serve") {
        serve(secs).await;
    }
}
