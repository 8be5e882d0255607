//! The plainer console in a real browser: an offline drive's values
//! greyed with their age, raw registers only in a closed details view, the
//! token's name and role labelled as such, the brake's limits in words,
//! events with their date, and the speed setpoint field with its two
//! leases (held while the page is open, or for a number of seconds), each
//! confirmed by the drive and ended by the daemon.

use std::time::Instant;

use serde_json::json;

use super::browser::{LONG, assert_clean, open, picture, rest, text};
use super::harness::cdp::{Browser, Page};
use super::harness::{ADMIN, OPERATOR, Watcher, config, config_with_jog_lease, speed, until};
use crate::support::TestDaemon;

/// Whether the first element matching `selector` is rendered (not in a
/// closed `<details>`, not hidden).
async fn visible(page: &Page, selector: &str) -> bool {
    page.eval(&format!(
        "(() => {{ const el = document.querySelector({}); return !!el && el.checkVisibility(); }})()",
        serde_json::to_string(selector).unwrap()
    ))
    .await
        == json!(true)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_offline_drive_is_greyed_with_its_age_and_raw_values_wait_in_closed_details() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/feeder", Some(OPERATOR)).await;
    page.wait_for(
        "document.querySelector('[data-value=flags]').textContent.startsWith('0x')",
        LONG,
        "the feeder's status",
    )
    .await;

    // The token is named and its role labelled: "panel" is not a page.
    assert_eq!(text(&page, "#who .token-name").await, "panel");
    assert_eq!(text(&page, "#who .role").await, "operator");
    let who = text(&page, "#who").await;
    assert!(who.starts_with("token panel · role operator"), "{who}");

    // Raw registers are there, in a details view closed by default.
    assert_eq!(
        page.eval("document.querySelector('details[data-details=status]').open")
            .await,
        json!(false)
    );
    assert!(!visible(&page, "[data-value=flags]").await);
    let shown = text(&page, ".drive-head .values:not(.raw)").await;
    assert!(
        !shown.contains("0x") && !shown.contains("STATUS"),
        "raw values in view: {shown}"
    );
    page.click("details[data-details=status] > summary").await;
    assert!(visible(&page, "[data-value=flags]").await);
    let flags = text(&page, "[data-value=flags]").await;
    assert!(flags.len() == 6 && flags.starts_with("0x"), "{flags}");
    page.wait_for(
        "!!document.querySelector('details[data-details=settings]')",
        LONG,
        "the settings read from the drive",
    )
    .await;
    assert!(!visible(&page, "details[data-details=settings] td").await);
    let held = text(&page, ".held").await;
    let plain = held.split("Details").next().unwrap_or("");
    assert!(
        !plain.contains("alpha") && !plain.contains("counts"),
        "raw counts in view: {held}"
    );

    // The brake says what it is not.
    let note = text(&page, "[data-note=not-estop]").await;
    assert!(note.contains("not a safety-rated emergency stop"), "{note}");
    assert!(visible(&page, "[data-note=not-estop]").await);

    // The feeder goes silent: its values stay, greyed, with their age.
    daemon.sim().set_silent(4, true);
    page.wait_for(
        "document.querySelector('.drive-head').dataset.link === 'offline' \
         && document.querySelector('.drive-head .values').classList.contains('not-live')",
        LONG,
        "the drive page marking the feeder offline",
    )
    .await;
    let last_seen = text(&page, ".last-seen").await;
    assert!(
        last_seen.starts_with("Offline")
            && last_seen.contains("the last it sent")
            && last_seen.contains("not live"),
        "{last_seen}"
    );
    assert!(visible(&page, ".last-seen").await);
    // The values are the last ones, greyed, not dashes.
    let voltage = text(&page, "[data-value=voltage]").await;
    assert!(voltage.ends_with(" V") && voltage != "– V", "{voltage}");
    let grey = page
        .eval("getComputedStyle(document.querySelector('[data-value=voltage]')).fontStyle")
        .await;
    assert_eq!(grey, json!("italic"));
    // Its age grows as time passes: "last seen N s ago".
    page.wait_for(
        "/^last seen \\d+ s ago$/.test(document.querySelector('[data-value=age]').textContent)",
        LONG,
        "the age of the last status counting up",
    )
    .await;

    picture(&page, "console-drive-offline.png", false).await;

    // The overview says the same in the feeder's row.
    page.eval("location.hash = '#/'").await;
    let state = page
        .wait_for(
            "(() => { const r = document.querySelector('tr[data-drive=feeder]'); \
             return r && r.dataset.link === 'offline' ? r.querySelector('td:nth-of-type(2)').textContent : null; })()",
            LONG,
            "the feeder's row offline",
        )
        .await;
    assert!(
        state.as_str().unwrap().starts_with("offline, last seen "),
        "{state}"
    );
    let volts = page
        .eval("(() => { const c = document.querySelector('tr[data-drive=feeder] td:nth-of-type(7)'); return [c.textContent, getComputedStyle(c).fontStyle]; })()")
        .await;
    assert_ne!(volts[0], json!("–"), "{volts}");
    assert_eq!(volts[1], json!("italic"), "{volts}");

    // Events carry their date and time.
    page.eval("location.hash = '#/events'").await;
    let when = page
        .wait_for(
            "(() => { const r = [...document.querySelectorAll('table.log tbody tr')].find((tr) => tr.textContent.includes('offline')); \
             return r ? r.querySelector('time').textContent : null; })()",
            LONG,
            "the offline event",
        )
        .await;
    let when = when.as_str().unwrap();
    let today = page
        .eval("(() => { const d = new Date(); return `${d.getFullYear()}-${String(d.getMonth() + 1).padStart(2, '0')}-${String(d.getDate()).padStart(2, '0')}`; })()")
        .await;
    assert!(
        when.len() == 19 && when.starts_with(today.as_str().unwrap()),
        "{when} is not a date and time of today"
    );
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

async fn setpoint_state(page: &Page, state: &str, what: &str) -> String {
    page.wait_for(
        &format!(
            "(() => {{ const s = document.querySelector('[data-group=setpoint] .jog-state'); \
             return s.dataset.setpoint === '{state}' ? s.textContent : null; }})()"
        ),
        LONG,
        what,
    )
    .await
    .as_str()
    .unwrap()
    .to_string()
}

/// When `drive`'s lease ends, as the daemon says now (`expires_in_ms`).
async fn rest_lease_end(daemon: &TestDaemon, token: &str, drive: &str) -> Instant {
    let asked = Instant::now();
    let (_, view) = rest(
        daemon,
        Some(token),
        "GET",
        &format!("/api/v1/drives/{drive}"),
        None,
    )
    .await;
    let left = view["lease"]["expires_in_ms"]
        .as_u64()
        .unwrap_or_else(|| panic!("no lease on {drive}: {view}"));
    asked + std::time::Duration::from_millis(left)
}

/// The held setpoint's lease in [`the_setpoint_field_sets_a_speed_held_while_the_page_is_open_or_for_a_time`]:
/// the page renews it three times a lease, so it runs out only if the
/// page's renewals stop for over 2.6 s, which a machine loaded by many
/// tests and a browser does not do.
const HELD_LEASE_MS: u64 = 4000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_setpoint_field_sets_a_speed_held_while_the_page_is_open_or_for_a_time() {
    let daemon = TestDaemon::start(&config_with_jog_lease(true, "", HELD_LEASE_MS)).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    super::browser::in_speed_mode(&daemon, "conveyor").await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(OPERATOR)).await;
    page.wait_for(
        "drivegate.store.drives.get('conveyor').status.mode === 'speed'",
        LONG,
        "the page seeing speed mode",
    )
    .await;

    // Held while the page is open: the drive confirms, the motor turns,
    // the lease is the page's socket's and is renewed.
    page.fill("[data-field=setpoint-rpm]", "80").await;
    page.click("[data-action=set-speed]").await;
    let held = setpoint_state(&page, "held", "the speed held").await;
    assert!(
        held.starts_with("80 rpm, held while this page is open"),
        "{held}"
    );
    let note = text(&page, "[data-group=setpoint] .note").await;
    assert!(
        note.contains("confirmed by the drive: speed setpoint 80 rpm"),
        "{note}"
    );
    let turning = tokio::time::timeout(LONG, async {
        while speed(&daemon.plant, 1).is_none_or(|s| s <= 60) {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    if turning.is_err() {
        // What the daemon and the stream knew, to tell why.
        let (_, drive) = rest(
            &daemon,
            Some(OPERATOR),
            "GET",
            "/api/v1/drives/conveyor",
            None,
        )
        .await;
        let news: Vec<serde_json::Value> = watcher
            .all()
            .into_iter()
            .map(|(_, v)| v)
            .filter(|v| v["type"] != "status")
            .collect();
        panic!("the motor not at the set speed within {LONG:?}: {drive}\nstream: {news:?}");
    }
    let (_, drive) = rest(
        &daemon,
        Some(OPERATOR),
        "GET",
        "/api/v1/drives/conveyor",
        None,
    )
    .await;
    assert_eq!(drive["lease"]["owner"], "panel", "{drive}");
    assert_eq!(drive["lease"]["websocket"], true, "{drive}");
    assert_eq!(drive["lease"]["lease_ms"], HELD_LEASE_MS, "{drive}");
    // The page renews it: its end moves on, twice, and the motor turns on.
    let mut end = rest_lease_end(&daemon, OPERATOR, "conveyor").await;
    for renewal in 1..=2 {
        let t0 = Instant::now();
        loop {
            let now = rest_lease_end(&daemon, OPERATOR, "conveyor").await;
            // A renewal moves it by a third of a lease (1.3 s); the
            // request's own time is far less.
            if now > end + std::time::Duration::from_millis(500) {
                end = now;
                break;
            }
            assert!(
                t0.elapsed() < LONG,
                "renewal {renewal} not seen within {LONG:?}"
            );
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
    }
    assert!(speed(&daemon.plant, 1).unwrap() > 60);
    assert!(
        !watcher
            .all()
            .iter()
            .any(|(_, v)| v["type"] == "lease-expired"),
        "the held lease ran out while the page was open"
    );

    // Stop: zero speed confirmed, the lease given back without a stop.
    let stopped = Instant::now();
    page.click("[data-action=stop-speed]").await;
    let state = setpoint_state(&page, "stopped", "the stop").await;
    assert_eq!(state, "stopped");
    let note = text(&page, "[data-group=setpoint] .note").await;
    assert!(
        note.contains("confirmed by the drive: speed setpoint 0 rpm"),
        "{note}"
    );
    watcher
        .wait(stopped, LONG, "the lease's end", |v| {
            (v["type"] == "lease-ended" || v["type"] == "lease-expired") && v["drive"] == "conveyor"
        })
        .await;
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;

    // For 2 s: the REST lease nobody renews; drivegate stops the motor
    // when it runs out, and the field says so.
    page.click("[data-lease=timed]").await;
    page.fill("[data-field=lease-s]", "2").await;
    page.fill("[data-field=setpoint-rpm]", "-70").await;
    let sent = Instant::now();
    page.click("[data-action=set-speed]").await;
    let timed = setpoint_state(&page, "timed", "the timed speed").await;
    assert!(timed.starts_with("-70 rpm until "), "{timed}");
    page.eval("document.querySelector('[data-group=setpoint]').scrollIntoView({block: 'center'})")
        .await;
    picture(&page, "console-setpoint.png", false).await;
    until(LONG, "the motor turning backward", || {
        speed(&daemon.plant, 1).is_some_and(|s| s < -50)
    })
    .await;
    let (_, drive) = rest(
        &daemon,
        Some(OPERATOR),
        "GET",
        "/api/v1/drives/conveyor",
        None,
    )
    .await;
    assert_eq!(drive["lease"]["websocket"], false, "{drive}");
    assert_eq!(drive["lease"]["lease_ms"], 2000, "{drive}");
    let (ended, m) = watcher
        .wait(sent, LONG, "the timed lease's end", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    assert_eq!(m["reason"], "it was not renewed in time", "{m}");
    assert!(
        ended - sent >= std::time::Duration::from_millis(1900),
        "{:?}",
        ended - sent
    );
    until(LONG, "the motor stopped by the lease", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;
    let state = setpoint_state(&page, "ended", "the field saying the lease ended").await;
    assert!(state.contains("lease ended"), "{state}");
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}
