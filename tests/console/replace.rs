//! The replace-a-drive page walked through end to end on the simulator:
//! the lift's settings saved to a file from its drive page, the lift
//! "replaced" (its simulated drive reset to factory settings and moved to
//! a spare address, the other drives unplugged), then every step of the
//! page: the file chosen, the new drive alone, the scan over 1 to 255, the
//! old address by the guarded broadcast, the settings' difference (a dry
//! run that writes nothing), the writes saved to flash, a calibration, the
//! verification (read back, difference empty), and the procedure's start
//! and end in the audit log. The time it took is printed.

use std::time::Duration;

use serde_json::{Value, json};

use super::browser::{LONG, assert_clean, open, picture, rest_ok, text};
use super::harness::cdp::{Browser, Page};
use super::harness::{ADMIN, config};
use crate::support::TestDaemon;
use drivegate::bus::cache::Link;

/// A scan of 255 units, each silent one costing a response timeout
/// (60 ms in this test) and a guard, on a loaded machine.
const SCAN: Duration = Duration::from_secs(300);

/// The lift's settings before it fails: none is the factory's.
const LIFT: [(&str, &str); 4] = [
    ("/protection", r#"{"limit_a": 6.0, "stall_ms": 1500}"#),
    ("/ramps/speed", r#"{"alpha": 1200}"#),
    ("/ramps/position", r#"{"alpha": 300}"#),
    ("/inertia", r#"{"ratio": 7}"#),
];

/// Waits until step `id` of the page is in `state` (or failed), and
/// returns its result in words.
async fn step(page: &Page, id: &str, state: &str, limit: Duration) -> String {
    let v = page
        .wait_for(
            &format!(
                "(() => {{ const s = document.querySelector('[data-step={id}]'); \
                 return s.dataset.state === '{state}' || s.dataset.state === 'failed' \
                 ? [s.dataset.state, s.querySelector('.result').textContent] : null; }})()"
            ),
            limit,
            &format!("step {id} {state}"),
        )
        .await;
    assert_eq!(v[0], json!(state), "step {id}: {}", v[1]);
    v[1].as_str().unwrap().to_string()
}

/// Clicks the button at `selector` until the page has taken the click (the
/// button is disabled or gone): on a loaded machine the page may redraw
/// between the press and the release, which a person would click again.
async fn click_until_taken(page: &Page, selector: &str) {
    let taken = format!(
        "(() => {{ const b = document.querySelector({sel}); return !b || b.disabled; }})()",
        sel = serde_json::to_string(selector).unwrap()
    );
    let start = std::time::Instant::now();
    loop {
        page.click(selector).await;
        let waited = std::time::Instant::now();
        while waited.elapsed() < Duration::from_secs(2) {
            if page.eval(&taken).await == json!(true) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert!(
            start.elapsed() < LONG,
            "{selector}: no click taken within {LONG:?}"
        );
    }
}

async fn step_ms(page: &Page, id: &str) -> u64 {
    page.eval(&format!(
        "Number(document.querySelector('[data-step={id}]').dataset.ms || 0)"
    ))
    .await
    .as_u64()
    .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_is_replaced_step_by_step_from_a_saved_file() {
    crate::support::logs::capture_logs();
    // A scan waits a whole response timeout and a guard at each silent
    // unit: 60 ms and 10 ms here (the simulator answers within a
    // millisecond) keep the 254 silent ones to a fifth of the default's.
    let plant = config(true, "");
    let short = plant
        .replace("response_timeout_ms = 250", "response_timeout_ms = 60")
        .replace("guard_ms = 50", "guard_ms = 10");
    assert_ne!(
        plant, short,
        "the tests' bus timing moved: update this test"
    );
    let daemon = TestDaemon::start(&short).await;
    let a = Some(ADMIN);
    for (path, body) in LIFT {
        let body: Value = serde_json::from_str(body).unwrap();
        rest_ok(
            &daemon,
            a,
            "PUT",
            &format!("/api/v1/drives/lift{path}"),
            Some(body),
        )
        .await;
    }
    let downloads = tempfile::tempdir().unwrap();
    let browser = Browser::start(&[]).await;
    browser.allow_downloads(downloads.path()).await;
    let page = open(&browser, &daemon.url(""), "/drive/lift", Some(ADMIN)).await;

    // Its settings to a file, from the drive page.
    page.wait_for(
        "!!document.querySelector('details[data-details=settings]')",
        LONG,
        "the settings read from the lift",
    )
    .await;
    let seen = browser.downloads_done();
    page.click("[data-read=file]").await;
    let name = browser.wait_download(seen, LONG).await;
    assert_eq!(name, "lift-settings.json");
    // Under a name only this test uses, to find its lines in the log.
    let unique = format!(
        "lift-settings-{}.json",
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos()
    );
    let file = downloads.path().join(&unique);
    std::fs::rename(downloads.path().join(&name), &file).unwrap();
    let saved: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    assert_eq!(saved["drive"], "lift", "{saved:#}");
    assert_eq!(saved["inertia_ratio"], 7, "{saved:#}");
    assert_eq!(saved["speed_ramp"]["alpha"], 1200, "{saved:#}");

    // The lift fails and a new drive takes its place: factory settings, a
    // spare address (9), and for now the only drive on the bus.
    rest_ok(
        &daemon,
        a,
        "POST",
        "/api/v1/drives/lift/commands/factory-reset",
        None,
    )
    .await;
    for unit in [1, 3, 4] {
        daemon.sim().set_silent(unit, true);
    }
    let moved = rest_ok(
        &daemon,
        a,
        "POST",
        "/api/v1/buses/sim/address",
        Some(json!({"address": 9, "only_drive_on_bus": true})),
    )
    .await;
    assert_eq!(moved["verified"], true, "{moved}");
    let new = daemon.sim().drive(9).expect("the new drive at unit 9");
    assert_eq!(new.settings.inertia_ratio, 1, "a factory-fresh drive");
    assert!(daemon.sim().drive(2).is_none());

    // The page, step by step.
    page.eval("location.hash = '#/replace/lift'").await;
    page.wait_for(
        "document.querySelector('[data-step=choose]').dataset.state === 'active' \
         && document.querySelector('[data-field=replace-drive]').value === 'lift'",
        LONG,
        "the first step",
    )
    .await;
    page.set_files("[data-field=settings-file]", &[file.as_path()])
        .await;
    page.click("[data-field=calibrate]").await;
    assert_eq!(
        page.eval("document.querySelector('[data-source=file]').checked")
            .await,
        json!(true)
    );
    page.click("[data-action=start]").await;
    let chosen = step(&page, "choose", "done", LONG).await;
    assert!(
        chosen.contains("Replacing lift (bus sim, unit 2)")
            && chosen.contains(&format!("the file {unique}, saved from lift"))
            && chosen.contains("calibration asked"),
        "{chosen}"
    );

    page.click("[data-action=scan]").await;
    let refused = text(&page, "[data-step=connect] .note").await;
    assert!(refused.contains("tick the box"), "{refused}");
    page.click("[data-field=alone]").await;
    page.click("[data-action=scan]").await;
    step(&page, "connect", "done", LONG).await;
    let scanned = step(&page, "scan", "done", SCAN).await;
    assert!(
        scanned.starts_with("Exactly one drive answers, at unit 9"),
        "{scanned}"
    );

    let _ = step(&page, "address", "active", LONG).await;
    page.click("[data-action=set-address]").await;
    let addressed = step(&page, "address", "done", LONG).await;
    assert!(
        addressed.contains("took address 2") && addressed.contains("polls it as lift"),
        "{addressed}"
    );

    // The difference first: shown, and nothing written.
    page.wait_for(
        "!document.querySelector('[data-action=write-settings]').hidden",
        LONG,
        "the dry run's difference",
    )
    .await;
    let differ = text(&page, "[data-step=settings] .result").await;
    assert!(differ.contains("settings differ"), "{differ}");
    let inertia = text(&page, "[data-diff=dry-run] [data-setting=inertia_ratio]").await;
    assert!(inertia.contains('1') && inertia.contains('7'), "{inertia}");
    let after_dry_run = daemon.sim().drive(2).expect("the new drive at unit 2");
    assert_eq!(after_dry_run.settings.inertia_ratio, 1, "the dry run wrote");
    click_until_taken(&page, "[data-action=write-settings]").await;
    let restored = step(&page, "settings", "done", LONG).await;
    assert!(
        restored.contains("confirmed by the drive, saved to its flash"),
        "{restored}"
    );

    page.click("[data-action=calibrate]").await;
    let calibrated = step(&page, "calibrate", "done", LONG).await;
    assert!(calibrated.starts_with("Calibrated in"), "{calibrated}");
    let verified = step(&page, "verify", "done", LONG).await;
    assert!(verified.contains("the difference is empty"), "{verified}");
    let done = step(&page, "done", "done", LONG).await;
    assert!(done.starts_with("lift replaced in"), "{done}");
    page.eval("scrollTo(0, 0)").await;
    picture(&page, "console-replace.png", true).await;
    let took = page
        .eval("Number(document.querySelector('[data-step=done]').dataset.elapsedMs)")
        .await
        .as_u64()
        .unwrap();
    let scan_ms = step_ms(&page, "scan").await;
    println!(
        "replace-a-drive on the simulator: {:.1} s from Start to Done, of which the scan {:.1} s \
         (255 units, response timeout 60 ms, guard 10 ms) and the calibration {:.1} s",
        took as f64 / 1000.0,
        scan_ms as f64 / 1000.0,
        step_ms(&page, "calibrate").await as f64 / 1000.0
    );

    // The new drive holds the old one's settings, in flash too.
    let lift = daemon.sim().drive(2).expect("the new drive at unit 2");
    for settings in [lift.settings, lift.flash.settings] {
        assert_eq!(settings.inertia_ratio, 7);
        assert_eq!(settings.speed_alpha, 1200);
        assert_eq!(settings.position_alpha, 300);
        assert_eq!(settings.stall_duration_ms, 1500);
        assert_eq!(settings.stall_current, 768, "6.0 A");
    }
    // The procedure in the audit log, around its writes.
    let logs = crate::support::logs::log_text();
    let lines: Vec<&str> = logs.lines().collect();
    let line = |what: &str| {
        lines
            .iter()
            .position(|l| {
                l.contains(what) && l.contains(&unique) && l.contains("who=\"commissioning\"")
            })
            .unwrap_or_else(|| panic!("no audit line {what:?}"))
    };
    let start = line("drive replacement started");
    let end = line("drive replacement finished");
    assert!(
        lines[start..end]
            .iter()
            .any(|l| l.contains("drive address set and verified") && l.contains("address=2")),
        "no address line between the start and the end"
    );

    // The others are plugged in again: all four online.
    for unit in [1, 3, 4] {
        daemon.sim().set_silent(unit, false);
    }
    super::harness::until(Duration::from_secs(90), "all four drives online", || {
        (1..=4).all(|u| {
            daemon.plant.buses()[0]
                .handle
                .drive(u)
                .is_some_and(|d| d.link == Link::Online)
        })
    })
    .await;
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}
