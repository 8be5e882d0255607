//! The scope and bus monitor pages in a real chromium: a capture armed
//! from the page with a level trigger fires on a speed step sent from the
//! API, fills, is plotted and downloads as the API's CSV; a second capture
//! is refused in the API's words. The monitor lists frames with who caused
//! them (an HTTP token, a Modbus TCP peer), its filters narrow the list,
//! pause holds it while frames keep being counted, and its PCAP download
//! opens in tshark. Every wait is for an event, never a fixed time.

use std::time::Duration;

use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::browser::{LONG, assert_clean, open, picture, rest, rest_ok, text};
use super::harness::cdp::{Browser, Page};
use super::harness::{ADMIN, OPERATOR, VIEWER, config};
use crate::support::TestDaemon;

/// Picks `value` in the select `selector`, as a user would (a change event).
async fn choose(page: &Page, selector: &str, value: &str) {
    let done = page
        .eval(&format!(
            "(() => {{ const el = document.querySelector({sel}); if (!el) return false; el.value = {v}; \
             el.dispatchEvent(new Event('change', {{bubbles: true}})); return el.value === {v}; }})()",
            sel = serde_json::to_string(selector).unwrap(),
            v = serde_json::to_string(value).unwrap()
        ))
        .await;
    assert_eq!(done, json!(true), "no option {value} in {selector}");
}

/// Waits for the monitor page's live feed to be open (again, after a
/// filter changed: the page reconnects with it).
async fn feed_open(page: &Page) {
    page.wait_for(
        "document.querySelector('[data-feed]').dataset.feed === 'open'",
        LONG,
        "the live feed open",
    )
    .await;
}

/// Sends one Modbus TCP request and reads its answer; returns the local
/// address the daemon sees as the peer.
async fn modbus_tcp_write(addr: std::net::SocketAddr, transaction: u16, unit: u8) -> String {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let peer = tcp.local_addr().unwrap().to_string();
    // Write single register 0x0002 = 0: the drive's "activate" command.
    let pdu = [0x06, 0x00, 0x02, 0x00, 0x00];
    let mut adu = transaction.to_be_bytes().to_vec();
    adu.extend_from_slice(&[0, 0, 0, pdu.len() as u8 + 1, unit]);
    adu.extend_from_slice(&pdu);
    tcp.write_all(&adu).await.unwrap();
    let mut head = [0u8; 7];
    tokio::time::timeout(LONG, tcp.read_exact(&mut head))
        .await
        .expect("a Modbus TCP answer")
        .unwrap();
    let mut rest = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]])) - 1];
    tcp.read_exact(&mut rest).await.unwrap();
    assert_eq!(rest, pdu, "the write's echo");
    peer
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_scope_page_arms_on_a_level_fills_plots_exports_and_shows_a_refusal() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let downloads = tempfile::tempdir().unwrap();
    let browser = Browser::start(&[]).await;
    browser.allow_downloads(downloads.path()).await;
    let base = daemon.url("");
    let page = open(&browser, &base, "/scope", Some(OPERATOR)).await;
    page.wait_for(
        "!!document.querySelector('[data-action=arm]')",
        LONG,
        "the arming form",
    )
    .await;

    // The conveyor's speed rising through 50 rpm; 20 samples before it,
    // 150 from it; speed and current (the form's default fields).
    choose(&page, "[data-field=trigger]", "rising").await;
    choose(&page, "[data-field=trigger-drive]", "conveyor").await;
    choose(&page, "[data-field=trigger-field]", "speed_rpm").await;
    page.fill("[data-field=level]", "50").await;
    page.fill("[data-field=pre]", "20").await;
    choose(&page, "[data-field=pre-unit]", "samples").await;
    page.fill("[data-field=length]", "150").await;
    choose(&page, "[data-field=length-unit]", "samples").await;
    page.click("[data-action=arm]").await;
    page.wait_for(
        "document.querySelector('.capture-state').dataset.state === 'armed'",
        LONG,
        "the capture armed",
    )
    .await;
    assert_eq!(
        page.eval("document.querySelector('.trigger-text').dataset.fired")
            .await,
        json!("false")
    );

    // A speed step from the API (another client) makes it trigger.
    let a = Some(ADMIN);
    super::browser::in_speed_mode(&daemon, "conveyor").await;
    rest_ok(
        &daemon,
        a,
        "PUT",
        "/api/v1/drives/conveyor/setpoint",
        Some(json!({"speed_rpm": 150})),
    )
    .await;
    page.wait_for(
        "document.querySelector('.capture-state').dataset.state === 'complete'",
        LONG,
        "the capture complete",
    )
    .await;
    // It filled under the page's eyes: the stream's scope messages (armed,
    // triggered, progress, the end) reached it.
    let messages = page
        .eval("drivegate.stream.counts.scope || 0")
        .await
        .as_u64()
        .unwrap();
    assert!(messages >= 3, "{messages} scope messages");
    assert_eq!(
        page.eval("document.querySelector('progress').value").await,
        json!(1)
    );
    let (_, state) = rest(&daemon, a, "GET", "/api/v1/buses/sim/scope", None).await;
    let capture = &state["capture"];
    assert_eq!(capture["state"], "complete", "{state:#}");
    assert_eq!(capture["post_trigger_samples"], 150, "{state:#}");
    let held = capture["pre_trigger_samples"].as_u64().unwrap()
        + capture["post_trigger_samples"].as_u64().unwrap();
    let fired = text(&page, ".trigger-text").await;
    assert!(
        fired.contains(capture["trigger"]["what"].as_str().unwrap()),
        "{fired} / {capture:#}"
    );

    // The plot: one per field, drawn with every sample.
    page.wait_for(
        &format!("drivegate.store.stats.scopeSamplesPlotted === {held}"),
        LONG,
        "the plot of every sample",
    )
    .await;
    assert_eq!(
        page.eval(
            "[...document.querySelectorAll('[data-scope-plot]')].map((f) => [f.dataset.scopePlot, !!f.querySelector('canvas'), f.querySelector('figcaption').textContent])"
        )
        .await,
        json!([["speed_rpm", true, "speed (rpm)"], ["current_a", true, "current (A)"]])
    );
    picture(&page, "console-scope.png", true).await;

    // The CSV download: the API's file, its columns named with their units.
    let seen = browser.downloads_done();
    page.click("[data-download=csv]").await;
    let name = browser.wait_download(seen, LONG).await;
    assert_eq!(name, format!("sim-capture-{}.csv", capture["id"]));
    let csv = std::fs::read_to_string(downloads.path().join(&name)).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("time,t_s,drive,unit,speed_rpm,current_a")
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len() as u64, held);
    let t: Vec<f64> = rows.iter().map(|r| r[1].parse().unwrap()).collect();
    assert!(t[0] < 0.0 && *t.last().unwrap() > 0.0, "{t:?}");
    let first_after = rows
        .iter()
        .find(|r| r[1].parse::<f64>().unwrap() >= 0.0)
        .unwrap();
    assert!(
        first_after[4].parse::<f64>().unwrap() >= 50.0,
        "{first_after:?}"
    );
    assert!(
        rows.iter()
            .filter(|r| r[1].parse::<f64>().unwrap() < 0.0)
            .all(|r| r[4].parse::<f64>().unwrap() < 50.0),
        "the pre-trigger holds what came before"
    );
    page.wait_for(
        "document.querySelector('[data-download=csv]').closest('.row').querySelector('.note.ok')",
        LONG,
        "the download's note",
    )
    .await;

    // A capture waiting for a manual trigger; a second arm is refused and
    // the API's words show beside the button.
    choose(&page, "[data-field=trigger]", "manual").await;
    page.click("[data-action=arm]").await;
    page.wait_for(
        "document.querySelector('.capture-state').dataset.state === 'armed'",
        LONG,
        "the second capture armed",
    )
    .await;
    page.click("[data-action=arm]").await;
    let refusal = page
        .wait_for(
            "(document.querySelector('.scope-form .note.fail') || {}).textContent",
            LONG,
            "the refusal",
        )
        .await;
    let (status, problem) = rest(
        &daemon,
        a,
        "POST",
        "/api/v1/buses/sim/scope",
        Some(json!({"drives": ["conveyor"], "trigger": {"type": "manual"}, "length": {"samples": 10}})),
    )
    .await;
    assert_eq!(status, 409, "{problem:#}");
    assert_eq!(problem["type"], "urn:drivegate:problem:scope-busy");
    let refusal = refusal.as_str().unwrap();
    assert!(
        refusal.contains(problem["detail"].as_str().unwrap()),
        "{refusal} / {problem:#}"
    );
    // Cancel from the page.
    page.click("[data-action=cancel]").await;
    page.wait_for(
        "document.querySelector('.capture-state').dataset.state === 'cancelled'",
        LONG,
        "the capture cancelled",
    )
    .await;
    assert_clean(&page, &base);
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_monitor_page_names_who_caused_each_frame_filters_pauses_and_downloads_a_pcap() {
    crate::support::tools::require("tshark");
    let daemon = TestDaemon::start(&config(true, "")).await;
    let downloads = tempfile::tempdir().unwrap();
    let browser = Browser::start(&[]).await;
    browser.allow_downloads(downloads.path()).await;
    let base = daemon.url("");
    let page = open(&browser, &base, "/monitor", Some(VIEWER)).await;
    page.wait_for(
        "document.querySelector('[data-feed]').dataset.feed === 'open' \
         && document.querySelectorAll('.frame-rows [data-seq]').length > 10",
        LONG,
        "the live list",
    )
    .await;

    // A setpoint from HTTP names its token ("commissioning"). The list is
    // filtered to what HTTP caused first (from the ring through the API's
    // filter): unfiltered, its 500 rows hold under 2 s of polls, and a
    // page kept from the CPU on a loaded machine can be shown the frame
    // and push it out again between two looks of the test.
    choose(&page, "[data-filter=source]", "http").await;
    feed_open(&page).await;
    let a = Some(ADMIN);
    rest_ok(
        &daemon,
        a,
        "POST",
        "/api/v1/drives/lift/commands/activate",
        None,
    )
    .await;
    rest_ok(
        &daemon,
        a,
        "PUT",
        "/api/v1/drives/lift/mode",
        Some(json!({"mode": "speed"})),
    )
    .await;
    rest_ok(
        &daemon,
        a,
        "PUT",
        "/api/v1/drives/lift/setpoint",
        Some(json!({"speed_rpm": 30})),
    )
    .await;
    let shown = page
        .wait_for(
            "(() => { const r = [...document.querySelectorAll('.frame[data-source=http][data-who=commissioning][data-unit=\"2\"]')] \
             .find((r) => r.textContent.includes('speed setpoint')); return r && r.textContent; })()",
            LONG,
            "the setpoint's frame, caused by the token",
        )
        .await;
    assert!(
        shown.as_str().unwrap().contains("HTTP commissioning"),
        "{shown}"
    );

    // A raw Modbus TCP request names its peer and transaction.
    choose(&page, "[data-filter=source]", "modbus-tcp").await;
    feed_open(&page).await;
    let peer = modbus_tcp_write(daemon.modbus_tcp.unwrap(), 0x77, 4).await;
    let shown = page
        .wait_for(
            &format!(
                "(() => {{ const r = document.querySelector('.frame[data-source=modbus-tcp][data-who=\"{peer}\"]'); return r && r.textContent; }})()"
            ),
            LONG,
            "the Modbus TCP frame, caused by its peer",
        )
        .await;
    assert!(
        shown
            .as_str()
            .unwrap()
            .contains(&format!("Modbus TCP {peer} (transaction 119)")),
        "{shown}"
    );

    // The filter narrowed the list to the Modbus TCP frames: the write and
    // its echo.
    page.wait_for(
        "(() => { const rows = [...document.querySelectorAll('.frame-rows [data-seq]')]; \
         return rows.length >= 2 && rows.every((r) => r.dataset.source === 'modbus-tcp'); })()",
        LONG,
        "only Modbus TCP frames",
    )
    .await;
    // Back to every source: the polls fill the list again.
    choose(&page, "[data-filter=source]", "").await;
    page.wait_for(
        "[...document.querySelectorAll('.frame-rows [data-seq]')].filter((r) => r.dataset.source === 'poller').length > 10",
        LONG,
        "the polls again",
    )
    .await;

    // Pause: the list stands still while the count of frames grows.
    page.click("[data-action=pause]").await;
    page.wait_for(
        "document.querySelector('[data-action=pause]').getAttribute('aria-pressed') === 'true'",
        LONG,
        "paused",
    )
    .await;
    let first = "document.querySelector('.frame-rows [data-seq]').dataset.seq";
    let held = page.eval(first).await;
    let received = page
        .eval("drivegate.store.stats.monitor.received")
        .await
        .as_u64()
        .unwrap();
    page.wait_for(
        &format!("drivegate.store.stats.monitor.received > {received} + 100"),
        LONG,
        "frames counted while paused",
    )
    .await;
    assert_eq!(page.eval(first).await, held, "the list moved while paused");
    picture(&page, "console-monitor.png", false).await;
    assert!(text(&page, ".monitor .count").await.contains("paused"));
    page.click("[data-action=pause]").await;
    page.wait_for(
        &format!("Number({first}) > Number({held})"),
        LONG,
        "the list moving again",
    )
    .await;
    let rows = page
        .eval("document.querySelectorAll('.frame-rows > .frame').length")
        .await
        .as_u64()
        .unwrap();
    assert!(rows <= 500, "{rows} rows: the list is bounded");

    // The PCAP download opens in tshark, with the command line the page shows.
    let hint = text(&page, "[data-hint=tshark]").await;
    assert_eq!(hint, "tshark -r sim-frames.pcap -o mbrtu.udp.port:502");
    let seen = browser.downloads_done();
    page.click("[data-download=pcap]").await;
    let name = browser.wait_download(seen, LONG).await;
    assert_eq!(name, "sim-frames.pcap");
    let out = tokio::time::timeout(
        Duration::from_secs(60),
        tokio::process::Command::new("tshark")
            .current_dir(downloads.path())
            .args(hint.split(' ').skip(1))
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("tshark in time")
    .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("tshark", &e)));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let decoded = String::from_utf8(out.stdout).unwrap();
    assert!(
        decoded.lines().count() > 100 && decoded.contains("Query") && decoded.contains("Response"),
        "{decoded}"
    );
    assert_clean(&page, &base);
    browser.stop().await;
    daemon.stop().await;
}
