//! Web console benchmark (`cargo bench --bench console`), not a test: the
//! daemon in-process on its simulator, Debian's chromium headless on
//! loopback (driven over DevTools, tests/support/cdp.rs).
//!
//! 1. First view: a new tab opens `/`; time to the page's load event, to
//!    the first status row drawn and to the first live value from the
//!    stream; bytes transferred (cold: empty cache; warm: revalidated with
//!    ETags, 304s).
//! 2. Keeping up: the overview open for `BENCH_SECONDS` while the bus polls
//!    every drive as fast as the wire allows: statuses received per second
//!    against row updates drawn and frames, the stream's bytes per second,
//!    and the browser's CPU (the renderer's main thread from DevTools, and
//!    every chromium process from /proc).
//!
//! Rows: 32 drives on one bus (the bus's full rate), and 128 drives on four
//! buses (four times that) for headroom. The same for the drive page with
//! its four plots.
//! 3. The bus monitor page on the first bus: every frame on the wire
//!    (requests and replies of a bus polled flat out) received, drawn as
//!    rows or dropped between two draws, lost by the feed, and the
//!    renderer's main thread.
//!
//! Environment: `BENCH_SECONDS` (default 10), `BENCH_LOADS` (10).

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub, dead_code)]

#[path = "../tests/support/cdp.rs"]
mod cdp;

use std::sync::Arc;
use std::time::{Duration, Instant};

use drivegate::config::Config;
use drivegate::metrics::Metrics;
use drivegate::plant::Plant;
use serde_json::Value;
use tokio_util::sync::CancellationToken;

use cdp::{Browser, Page};

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// `buses` simulated buses of `per_bus` drives each, polled flat out.
fn config(buses: u32, per_bus: u32) -> String {
    let mut c = String::from("[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n");
    for b in 0..buses {
        c += &format!(
            "[[bus]]\nname = \"line{}\"\nport = \"sim\"\nbaud = 115200\nresponse_timeout_ms = 50\nretries = 1\npoll_interval_ms = 0\n[bus.sim]\nturnaround_ms = 0.5\nseed = {}\n",
            b + 1,
            b + 1
        );
        for u in 1..=per_bus {
            c += &format!(
                "[[bus.drive]]\nunit = {u}\nname = \"d{}-{u:02}\"\ngear_ratio = 3.75\n",
                b + 1
            );
        }
    }
    c
}

/// CPU seconds (user + system) of `pid` and its descendants, from /proc.
fn cpu_seconds(root: u32) -> f64 {
    let tick = 100.0; // USER_HZ on Linux
    let mut total = 0.0;
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return 0.0;
    };
    let mut parents = std::collections::HashMap::new();
    let mut times = std::collections::HashMap::new();
    for entry in dir.flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        let Some(after) = stat.rfind(')').map(|i| &stat[i + 2..]) else {
            continue;
        };
        let f: Vec<&str> = after.split_whitespace().collect();
        let ppid: u32 = f[1].parse().unwrap_or(0);
        let t = f[11].parse::<f64>().unwrap_or(0.0) + f[12].parse::<f64>().unwrap_or(0.0);
        parents.insert(pid, ppid);
        times.insert(pid, t);
    }
    for (&pid, &t) in &times {
        let mut p = pid;
        loop {
            if p == root {
                total += t;
                break;
            }
            match parents.get(&p) {
                Some(&pp) if pp != 0 && pp != p => p = pp,
                _ => break,
            }
        }
    }
    total / tick
}

struct Daemon {
    base: String,
    plant: Arc<Plant>,
    shutdown: CancellationToken,
    faces: drivegate::daemon::supervisor::Faces,
}

async fn start(buses: u32, per_bus: u32) -> Daemon {
    let config = Config::parse(&config(buses, per_bus), "benchmark").unwrap();
    let plant = Arc::new(Plant::start(&config).unwrap());
    let metrics = Metrics::new(plant.clone());
    let shutdown = CancellationToken::new();
    let faces =
        drivegate::daemon::supervisor::start(&config, plant.clone(), metrics, shutdown.clone())
            .await
            .unwrap();
    let base = format!("http://{}", faces.http);
    let start = Instant::now();
    while plant
        .buses()
        .iter()
        .any(|b| b.handle.drives().iter().any(|d| d.status.is_none()))
    {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "drives did not come online"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    Daemon {
        base,
        plant,
        shutdown,
        faces,
    }
}

/// Bytes the page's requests took on the wire (headers and bodies).
fn bytes_loaded(page: &Page) -> f64 {
    page.events_of("Network.loadingFinished")
        .iter()
        .map(|e| e["params"]["encodedDataLength"].as_f64().unwrap_or(0.0))
        .sum()
}

fn ws_bytes(page: &Page) -> f64 {
    page.events_of("Network.webSocketFrameReceived")
        .iter()
        .map(|e| {
            e["params"]["response"]["payloadData"]
                .as_str()
                .map_or(0, str::len) as f64
        })
        .sum()
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

/// First views: `loads` new tabs, the first with an empty cache.
async fn first_view(browser: &Browser, base: &str, loads: u64) {
    let mut times = Vec::new();
    for i in 0..loads {
        let page = browser.new_page(1280, 900).await;
        page.goto(&format!("{base}/")).await;
        let v = page
            .wait_for(
                "window.drivegate && drivegate.store.stats.firstValueAt !== null && drivegate.store.stats.rowsDrawn > 0 \
                 && [performance.getEntriesByType('navigation')[0].loadEventEnd, drivegate.store.stats.firstRowsAt, drivegate.store.stats.firstValueAt]",
                Duration::from_secs(60),
                "the first live value",
            )
            .await;
        let a: Vec<f64> = v
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap_or(0.0))
            .collect();
        let bytes = bytes_loaded(&page);
        if i == 0 {
            println!(
                "  cold (empty cache): load event {:.0} ms, first rows drawn {:.0} ms, first live value {:.0} ms; {:.1} KB transferred in {} requests",
                a[0],
                a[1],
                a[2],
                bytes / 1024.0,
                page.events_of("Network.loadingFinished").len()
            );
        } else {
            times.push((a[0], a[1], a[2], bytes));
        }
        browser.close_page(&page).await;
    }
    if !times.is_empty() {
        let mut load: Vec<f64> = times.iter().map(|t| t.0).collect();
        let mut rows: Vec<f64> = times.iter().map(|t| t.1).collect();
        let mut live: Vec<f64> = times.iter().map(|t| t.2).collect();
        let mut bytes: Vec<f64> = times.iter().map(|t| t.3).collect();
        println!(
            "  warm (ETag revalidation), median of {}: load event {:.0} ms, first rows drawn {:.0} ms, first live value {:.0} ms; {:.1} KB transferred",
            times.len(),
            median(&mut load),
            median(&mut rows),
            median(&mut live),
            median(&mut bytes) / 1024.0
        );
    }
}

/// The page kept open at `hash` for `seconds`: what it received and drew.
async fn keep_up(browser: &Browser, base: &str, hash: &str, seconds: u64, label: &str) {
    let page = browser.new_page(1280, 900).await;
    page.goto(&format!("{base}/#{hash}")).await;
    page.wait_for("window.drivegate && drivegate.stream.state === 'open' && drivegate.store.stats.statusReceived > 0", Duration::from_secs(60), "live").await;
    // Settle, then measure.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stats = "[drivegate.store.stats.statusReceived, drivegate.store.stats.rowsDrawn || 0, drivegate.store.stats.frames || 0, drivegate.store.stats.plotsDrawn || 0]";
    let before: Vec<f64> = page
        .eval(stats)
        .await
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let m0 = page.metrics().await;
    let cpu0 = cpu_seconds(browser.pid);
    let ws0 = ws_bytes(&page);
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    let wall = t0.elapsed().as_secs_f64();
    let after: Vec<f64> = page
        .eval(stats)
        .await
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let m1 = page.metrics().await;
    let cpu1 = cpu_seconds(browser.pid);
    let ws1 = ws_bytes(&page);
    let rate = |i: usize| (after[i] - before[i]) / wall;
    let task = (m1["TaskDuration"] - m0["TaskDuration"]) / wall;
    let script = (m1["ScriptDuration"] - m0["ScriptDuration"]) / wall;
    let lagged: Value = page.eval("drivegate.stream.counts.lagged || 0").await;
    let drawn = if rate(3) > 0.0 {
        format!("redrew the 4 plots {:.0} times/s", rate(3) / 4.0)
    } else {
        format!(
            "drew {:.0} of them/s (two between draws count once) in {:.0} draws/s",
            rate(1),
            rate(2)
        )
    };
    println!(
        "  {label}: received {:.0} statuses/s, {drawn}; stream {:.1} KB/s; lagged notices {}; renderer main thread busy {:.1} % (script {:.1} %); all chromium processes {:.1} % of one core",
        rate(0),
        (ws1 - ws0) / wall / 1024.0,
        lagged,
        task * 100.0,
        script * 100.0,
        (cpu1 - cpu0) / wall * 100.0,
    );
    browser.close_page(&page).await;
}

/// The bus monitor page open on the first bus for `seconds`: the frames
/// the bus put on the wire against those the page received, drew and
/// dropped (more than one screen's worth between two draws), the frames
/// the feed lost for it, and the renderer's main thread.
async fn keep_up_monitor(browser: &Browser, daemon: &Daemon, seconds: u64) {
    let page = browser.new_page(1280, 900).await;
    page.goto(&format!("{}/#/monitor", daemon.base)).await;
    page.wait_for(
        "window.drivegate && drivegate.store.stats.monitor && drivegate.store.stats.monitor.received > 0",
        Duration::from_secs(60),
        "the live list",
    )
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stats = "(() => { const m = drivegate.store.stats.monitor; return [m.received, m.rendered, m.dropped, m.lost, m.draws, document.querySelectorAll('.frame-rows > .frame').length]; })()";
    let read = |v: Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let monitor = daemon.plant.buses()[0].monitor().clone();
    let before = read(page.eval(stats).await);
    let wire0 = monitor.frames();
    let m0 = page.metrics().await;
    let cpu0 = cpu_seconds(browser.pid);
    let ws0 = ws_bytes(&page);
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    let wall = t0.elapsed().as_secs_f64();
    let after = read(page.eval(stats).await);
    let wire = (monitor.frames() - wire0) as f64 / wall;
    let m1 = page.metrics().await;
    let cpu1 = cpu_seconds(browser.pid);
    let ws1 = ws_bytes(&page);
    let rate = |i: usize| (after[i] - before[i]) / wall;
    let task = (m1["TaskDuration"] - m0["TaskDuration"]) / wall;
    let script = (m1["ScriptDuration"] - m0["ScriptDuration"]) / wall;
    println!(
        "  monitor page (bus {}): the wire carried {wire:.0} frames/s; the page received {:.0}/s ({:.1} %), drew {:.0} rows/s in {:.0} draws/s, dropped {:.0} undrawn, the feed lost {:.0} for it; {} rows in the list; feed {:.1} KB/s; renderer main thread busy {:.1} % (script {:.1} %); all chromium processes {:.1} % of one core",
        daemon.plant.buses()[0].handle.name(),
        rate(0),
        rate(0) / wire * 100.0,
        rate(1),
        rate(4),
        after[2] - before[2],
        after[3] - before[3],
        after[5],
        (ws1 - ws0) / wall / 1024.0,
        task * 100.0,
        script * 100.0,
        (cpu1 - cpu0) / wall * 100.0,
    );
    // Paused: the frames still arrive and are counted, nothing is drawn.
    page.eval("document.querySelector('[data-action=pause]').click()")
        .await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let p0 = page.metrics().await;
    let received0 = read(page.eval(stats).await)[0];
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    let wall = t0.elapsed().as_secs_f64();
    let p1 = page.metrics().await;
    let received = read(page.eval(stats).await)[0] - received0;
    println!(
        "  the same page paused: received {:.0} frames/s, renderer main thread busy {:.1} % (script {:.1} %)",
        received / wall,
        (p1["TaskDuration"] - p0["TaskDuration"]) / wall * 100.0,
        (p1["ScriptDuration"] - p0["ScriptDuration"]) / wall * 100.0,
    );
    browser.close_page(&page).await;
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let seconds = env("BENCH_SECONDS", 10);
    let loads = env("BENCH_LOADS", 10);
    println!(
        "drivegate console benchmark: chromium headless on loopback, simulated drives at 115200 baud polled as fast as the bus allows"
    );
    for (buses, per_bus) in [(1, 32), (4, 32)] {
        let daemon = start(buses, per_bus).await;
        let browser = Browser::start(&[]).await;
        println!("{} drives on {} bus(es):", buses * per_bus, buses);
        first_view(&browser, &daemon.base, loads).await;
        let polls0: u64 = daemon
            .plant
            .buses()
            .iter()
            .map(|b| b.handle.stats().polls)
            .sum();
        let t = Instant::now();
        keep_up(&browser, &daemon.base, "/", seconds, "overview").await;
        let polls = daemon
            .plant
            .buses()
            .iter()
            .map(|b| b.handle.stats().polls)
            .sum::<u64>()
            - polls0;
        println!(
            "  the buses polled {:.0} statuses/s meanwhile",
            polls as f64 / t.elapsed().as_secs_f64()
        );
        keep_up(
            &browser,
            &daemon.base,
            "/drive/d1-01",
            seconds,
            "drive page (4 plots)",
        )
        .await;
        keep_up_monitor(&browser, &daemon, seconds).await;
        browser.stop().await;
        daemon.shutdown.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), daemon.faces.wait()).await;
        drivegate::control::shutdown(
            &daemon.plant,
            drivegate::control::stop_action::StopAction::None,
        )
        .await;
    }
}
