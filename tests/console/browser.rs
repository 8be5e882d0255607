//! The web console in a real browser: Debian's chromium, headless, driven
//! over the DevTools protocol (tests/console_support/cdp.rs) against the
//! daemon on its simulator. Each test waits for what it expects to see (a
//! page element, a stream message, the drive's polled state), never for a
//! fixed time, so a loaded machine only makes it slower.
//!
//! The pictures in docs/ are taken by the tests that check what they show
//! (`picture`), when `DRIVEGATE_SCREENSHOTS` is set: `DRIVEGATE_SCREENSHOTS=docs
//! cargo test --test e2e console::` retakes them all.

use std::time::{Duration, Instant};

use serde_json::{Value, json};

use super::harness::cdp::{Browser, Page};
use super::harness::{ADMIN, OPERATOR, Proxy, VIEWER, Watcher, config, speed, until};
use crate::support::TestDaemon;
use crate::support::opcua::{Held, server_pki};

/// The jog's lease in the page (web/console/jog.js).
const LEASE: Duration = Duration::from_millis(super::harness::JOG_LEASE_MS);
/// Room for a loaded machine's scheduling beside the lease itself.
const SLACK: Duration = Duration::from_millis(1500);
pub(crate) const LONG: Duration = Duration::from_secs(60);

/// Opens the console at `base` + `#hash`, enters `token` in the token
/// dialog if asked, and waits until the page is live with every drive.
pub(crate) async fn open(browser: &Browser, base: &str, hash: &str, token: Option<&str>) -> Page {
    let page = browser.new_page(1280, 900).await;
    page.goto(&format!("{base}/#{hash}")).await;
    if let Some(t) = token {
        page.wait_for(
            "document.getElementById('login').open",
            LONG,
            "the token dialog",
        )
        .await;
        page.fill("#login input", t).await;
        page.click("#login button[type=submit]").await;
    }
    page.wait_for(
        "window.drivegate && drivegate.stream.state === 'open' && drivegate.store.order.length === 4 \
         && drivegate.store.stats.statusReceived > 0",
        LONG,
        "the console live with four drives",
    )
    .await;
    page
}

/// No errors, and every request to the daemon's own address.
pub(crate) fn assert_clean(page: &Page, base: &str) {
    assert_no_errors(page, false);
    assert_loopback(page, base);
}

/// No exception, no console.error, no failed load; with `answers_too`, not
/// even an error status from the API (chromium logs every 4xx and 5xx
/// answer, which the page shows in words beside its control).
pub(crate) fn assert_no_errors(page: &Page, answers_too: bool) {
    let errors: Vec<String> = page
        .errors()
        .into_iter()
        .filter(|e| answers_too || !e.contains("the server responded with a status of"))
        .collect();
    assert!(errors.is_empty(), "the page reported errors: {errors:#?}");
}

/// Every request the page made went to `base` (the daemon, or the proxy).
pub(crate) fn assert_loopback(page: &Page, base: &str) {
    let ws = base.replacen("http://", "ws://", 1);
    let requests = page.requests();
    assert!(!requests.is_empty());
    for url in requests {
        assert!(
            url.starts_with(&format!("{base}/"))
                || url.starts_with(&format!("{ws}/"))
                || url.starts_with(&format!("blob:{base}/"))
                || url == "about:blank",
            "a request left the daemon: {url}"
        );
    }
}

pub(crate) async fn text(page: &Page, selector: &str) -> String {
    page.eval(&format!(
        "(document.querySelector({}) || {{}}).textContent || ''",
        serde_json::to_string(selector).unwrap()
    ))
    .await
    .as_str()
    .unwrap_or("")
    .to_string()
}

/// A REST call that must succeed; a drive that did not answer in time (a
/// loaded machine's simulator) is asked again, twice at most.
pub(crate) async fn rest_ok(
    daemon: &TestDaemon,
    token: Option<&str>,
    method: &str,
    path: &str,
    body: Option<Value>,
) -> Value {
    let mut last = (0, Value::Null);
    for _ in 0..3 {
        last = rest(daemon, token, method, path, body.clone()).await;
        if last.0 == 200 {
            return last.1;
        }
        if last.0 < 500 {
            break;
        }
    }
    panic!("{method} {path}: {} {:#}", last.0, last.1);
}

/// Activates `drive` and puts it in speed mode over REST, as an admin.
pub(crate) async fn in_speed_mode(daemon: &TestDaemon, drive: &str) {
    let a = Some(ADMIN);
    let activate = format!("/api/v1/drives/{drive}/commands/activate");
    rest_ok(daemon, a, "POST", &activate, None).await;
    let mode = Some(json!({"mode": "speed"}));
    rest_ok(
        daemon,
        a,
        "PUT",
        &format!("/api/v1/drives/{drive}/mode"),
        mode,
    )
    .await;
}

pub(crate) async fn rest(
    daemon: &TestDaemon,
    token: Option<&str>,
    method: &str,
    path: &str,
    body: Option<Value>,
) -> (u16, Value) {
    let client = reqwest::Client::new();
    let mut r = client.request(method.parse().unwrap(), daemon.url(path));
    if let Some(t) = token {
        r = r.bearer_auth(t);
    }
    if let Some(b) = body {
        r = r.json(&b);
    }
    let res = r.send().await.unwrap();
    let status = res.status().as_u16();
    (status, res.json().await.unwrap_or(Value::Null))
}

/// Clicks `button` until `done` holds, as an operator would try again
/// when the page says the drive did not answer (a loaded machine's
/// simulator can miss a response timeout).
async fn click_until(page: &Page, button: &str, done: &str, what: &str) {
    for _ in 0..3 {
        page.click(button).await;
        let settled = page
            .wait_for(
                &format!(
                    "(({done}) && 'done') || (document.querySelector({b}).closest('.group').querySelector('.note.fail') && 'failed')",
                    b = serde_json::to_string(button).unwrap()
                ),
                LONG,
                what,
            )
            .await;
        if settled == "done" {
            return;
        }
    }
    panic!("{what}: failed three times");
}

/// Activates the drive and puts it in speed mode from the page's buttons.
async fn activate_in_speed_mode(page: &Page) {
    click_until(
        page,
        "[data-command=activate]",
        "drivegate.store.drives.get('conveyor').status.active",
        "the drive active",
    )
    .await;
    click_until(
        page,
        "[data-mode=speed]",
        "drivegate.store.drives.get('conveyor').status.mode === 'speed'",
        "the drive in speed mode",
    )
    .await;
}

/// A position as the console writes it: "12.25 turns".
fn is_position(text: &serde_json::Value) -> bool {
    text.as_str()
        .and_then(|t| t.strip_suffix(" turns"))
        .is_some_and(|n| {
            n.parse::<f64>().is_ok() && n.split_once('.').is_some_and(|(_, d)| d.len() == 2)
        })
}

/// Every page, live values, and the overview's line of the OPC UA face:
/// where it serves, and its sessions as a client (asyncua) comes and goes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_page_loads_clean_from_loopback_and_values_update_live() {
    let dir = tempfile::tempdir().unwrap();
    let opcua = format!(
        "[opcua]\nlisten = \"127.0.0.1:0\"\npki_dir = \"{}\"\nsecurity = [\"none\"]",
        server_pki(dir.path()).display()
    );
    let daemon = TestDaemon::start(&config(false, &opcua)).await;
    let base = daemon.url("");
    let browser = Browser::start(&[]).await;
    let opcua = daemon
        .faces_addresses()
        .await
        .opcua
        .expect("OPC UA listens");
    // The client starts meanwhile (a Python process takes a while).
    let client = tokio::spawn(Held::open(format!("opc.tcp://{opcua}/"), LONG));
    let page = open(&browser, &base, "/", None).await;
    page.wait_for(
        "document.querySelectorAll('table.drives tbody tr').length === 4",
        LONG,
        "four rows",
    )
    .await;

    // Live: a speed set from outside the page shows in its row.
    rest_ok(
        &daemon,
        None,
        "POST",
        "/api/v1/drives/lift/commands/activate",
        None,
    )
    .await;
    rest_ok(
        &daemon,
        None,
        "PUT",
        "/api/v1/drives/lift/mode",
        Some(json!({"mode": "speed"})),
    )
    .await;
    rest_ok(
        &daemon,
        None,
        "PUT",
        "/api/v1/drives/lift/setpoint",
        Some(json!({"speed_rpm": 40})),
    )
    .await;
    let shown = page
        .wait_for(
            "(() => { const c = document.querySelector('tr[data-drive=lift] td:nth-of-type(4)'); \
             return c && Number(c.textContent) > 30 ? c.textContent : null; })()",
            LONG,
            "the lift's speed in its row",
        )
        .await;
    assert!(shown.as_str().unwrap().parse::<i32>().unwrap() > 30);
    // A position is written one way on every page: output turns, to a
    // hundredth (the overview's cell here, the drive page's below).
    let position = page
        .eval("document.querySelector('tr[data-drive=lift] td:nth-of-type(5)').textContent")
        .await;
    assert!(
        is_position(&position),
        "the overview's position: {position}"
    );
    let before = page
        .eval("drivegate.store.stats.statusReceived")
        .await
        .as_u64()
        .unwrap();
    page.wait_for(
        &format!("drivegate.store.stats.statusReceived > {before} + 20"),
        LONG,
        "statuses keep coming",
    )
    .await;

    // The drive page writes the position as the overview does, and its
    // buttons show the states the drive is in: Activate pressed for the
    // active lift, nothing pressed for the inactive conveyor (Deactivate
    // is an action, not a state).
    page.eval("location.hash = '#/drive/lift'").await;
    page.wait_for(
        "(document.querySelector('[data-command=activate]') || {}).getAttribute && document.querySelector('[data-command=activate]').getAttribute('aria-pressed') === 'true'",
        LONG,
        "Activate pressed for the active lift",
    )
    .await;
    let position = page
        .eval("document.querySelector('[data-value=position]').textContent")
        .await;
    assert!(
        is_position(&position),
        "the drive page's position: {position}"
    );
    assert_eq!(
        page.eval(
            "document.querySelector('[data-command=deactivate]').getAttribute('aria-pressed')"
        )
        .await,
        "false"
    );
    page.eval("location.hash = '#/drive/conveyor'").await;
    page.wait_for(
        "(() => { const b = document.querySelectorAll('[data-command]'); return drivegate.store.drives.get('conveyor').status && b.length === 3 && [...b].every((x) => x.getAttribute('aria-pressed') === 'false'); })()",
        LONG,
        "no activation button pressed for the inactive conveyor",
    )
    .await;

    // The OPC UA session is open before the tour, which ends on the
    // overview: its line is read again as the overview opens.
    let held = client.await.expect("the OPC UA client");
    assert!(held.address.starts_with("127.0.0.1:"), "{}", held.address);

    // Every page of the console, each without an error.
    for (hash, marker) in [
        ("/drive/lift", "[data-plot=speed] canvas"),
        ("/settings/lift", "[data-field=limit_a]"),
        ("/commissioning", "[data-action=scan]"),
        ("/events", "table.log"),
        ("/alarms", "table.alarms"),
        ("/replace", "[data-action=start]"),
        ("/scope", "[data-action=arm]"),
        ("/monitor", ".frame-rows [data-seq]"),
        ("/", "table.drives"),
    ] {
        page.eval(&format!("location.hash = '#{hash}'")).await;
        page.wait_for(
            &format!(
                "!!document.querySelector({})",
                serde_json::to_string(marker).unwrap()
            ),
            LONG,
            hash,
        )
        .await;
    }
    // The overview lists the OPC UA face: where it serves, with the
    // client's session; closed, the count goes back down.
    let opcua_line = |sessions: &str| {
        format!(
            "(document.querySelector('.summary.opcua.good:not([hidden])') || {{}}).textContent === {}",
            serde_json::to_string(&format!(
                "OPC UA: serving on opc.tcp://{opcua}/ ({sessions})"
            ))
            .unwrap()
        )
    };
    page.wait_for(
        &opcua_line("1 session"),
        LONG,
        "the OPC UA line with one session",
    )
    .await;
    held.close(LONG).await;
    page.wait_for(
        &opcua_line("0 sessions"),
        LONG,
        "the OPC UA line with no session",
    )
    .await;

    // The plot drew the speed it received.
    page.eval("location.hash = '#/drive/lift'").await;
    page.wait_for(
        "(() => { const h = drivegate.store.drives.get('lift').history; return h && h.speed.some((v) => v > 30); })()",
        LONG,
        "the speed history of the plot",
    )
    .await;
    rest_ok(
        &daemon,
        None,
        "POST",
        "/api/v1/drives/lift/commands/brake",
        None,
    )
    .await;
    assert_clean(&page, &base);
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hold_to_jog_moves_and_the_lease_stops_the_motor_after_release() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(OPERATOR)).await;
    activate_in_speed_mode(&page).await;

    page.mouse_down("[data-jog=forward]").await;
    until(
        LONG,
        "the motor turning forward while the button is held",
        || speed(&daemon.plant, 1).is_some_and(|s| s > 20),
    )
    .await;
    // Held for longer than several leases: the page renews it.
    let (_, lease) = rest(
        &daemon,
        Some(OPERATOR),
        "GET",
        "/api/v1/drives/conveyor",
        None,
    )
    .await;
    assert_eq!(lease["lease"]["websocket"], true, "{lease}");
    let renewals_from = Instant::now();
    until(LONG, "still turning after 3 leases", || {
        renewals_from.elapsed() > 3 * LEASE
    })
    .await;
    assert!(speed(&daemon.plant, 1).unwrap() > 20);
    assert!(
        !watcher
            .all()
            .iter()
            .any(|(_, v)| v["type"] == "lease-expired"),
        "the lease ended while the button was held"
    );

    let released = Instant::now();
    page.mouse_up("[data-jog=forward]").await;
    let (ended, message) = watcher
        .wait(released, LONG, "the lease's end", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    assert_eq!(message["reason"], "it was not renewed in time", "{message}");
    assert_eq!(message["ok"], true, "{message}");
    let after = ended - released;
    assert!(
        after <= LEASE + SLACK,
        "the lease ended {after:?} after the release"
    );
    // The stop was the lease's: the page sent no setpoint of its own.
    let page_writes: Vec<Value> = watcher
        .all()
        .into_iter()
        .filter(|(at, v)| *at >= released && v["type"] == "write" && v["who"] == "panel")
        .map(|(_, v)| v)
        .collect();
    assert!(
        page_writes.is_empty(),
        "the page wrote after the release: {page_writes:?}"
    );
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;
    page.wait_for(
        "document.querySelector('[data-jog]').closest('.group').querySelector('.jog-state').dataset.jog === 'released'",
        LONG,
        "the page saying the jog was released",
    )
    .await;
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_the_tab_mid_jog_stops_the_motor() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(OPERATOR)).await;
    activate_in_speed_mode(&page).await;
    page.mouse_down("[data-jog=forward]").await;
    until(LONG, "the motor turning", || {
        speed(&daemon.plant, 1).is_some_and(|s| s > 20)
    })
    .await;

    let closed = Instant::now();
    browser.close_page(&page).await;
    let (ended, message) = watcher
        .wait(closed, LONG, "the lease's end", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    // Whichever came first, the socket's close or the lease's time, both
    // are the daemon's doing.
    assert!(ended - closed <= LEASE + SLACK, "{:?}", ended - closed);
    assert_eq!(message["ok"], true, "{message}");
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_network_stops_the_motor_while_the_button_is_still_held() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    let proxy = Proxy::start(daemon.http).await;
    let base = format!("http://{}", proxy.addr);
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &base, "/drive/conveyor", Some(OPERATOR)).await;
    activate_in_speed_mode(&page).await;
    page.mouse_down("[data-jog=forward]").await;
    until(LONG, "the motor turning", || {
        speed(&daemon.plant, 1).is_some_and(|s| s > 20)
    })
    .await;

    // The cable is cut: no byte either way, no connection closed. The page
    // still holds the button and keeps trying to renew.
    let cut = Instant::now();
    proxy.freeze();
    let (ended, message) = watcher
        .wait(cut, LONG, "the lease's end", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    assert_eq!(message["reason"], "it was not renewed in time", "{message}");
    assert!(ended - cut <= LEASE + SLACK, "{:?}", ended - cut);
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;
    // The page still thinks it jogs: the stop was the daemon's alone.
    assert_eq!(
        page.eval("document.querySelector('.jog-state').dataset.jog")
            .await,
        json!("running")
    );
    // Back on the wire, the page's late renewals find no lease: it says so
    // and stops, and the motor stays still.
    proxy.unfreeze();
    page.wait_for(
        "document.querySelector('.jog-state').dataset.jog !== 'running'",
        LONG,
        "the page giving up the jog",
    )
    .await;
    page.mouse_up("[data-jog=forward]").await;
    assert_eq!(speed(&daemon.plant, 1), Some(0));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_token_sees_no_control() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/", Some(VIEWER)).await;
    assert_eq!(text(&page, "#who .role").await, "viewer");
    for hash in [
        "/",
        "/drive/conveyor",
        "/alarms",
        "/events",
        "/commissioning",
        "/replace",
        "/settings/conveyor",
        "/scope",
        "/monitor",
    ] {
        page.eval(&format!("location.hash = '#{hash}'")).await;
        page.wait_for(
            &format!(
                "document.getElementById('main').dataset.page === '{}'",
                hash.split('/')
                    .nth(1)
                    .filter(|s| !s.is_empty())
                    .unwrap_or("overview")
            ),
            LONG,
            hash,
        )
        .await;
        let controls = page
            .eval(
                "[...document.querySelectorAll('button, input, select')].filter((el) => el.offsetParent !== null \
                 && !el.closest('header, dialog, .filters, .zoom') && !el.dataset.read).map((el) => el.outerHTML.slice(0, 80))",
            )
            .await;
        assert_eq!(controls, json!([]), "controls shown to a viewer on {hash}");
        assert_eq!(
            page.eval("document.getElementById('brake-all').hidden")
                .await,
            json!(true)
        );
    }
    let nav = text(&page, "#nav").await;
    assert!(
        !nav.contains("Commissioning") && !nav.contains("Settings") && !nav.contains("Gateway"),
        "{nav}"
    );
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_emergency_brake_works_from_every_page() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/", Some(ADMIN)).await;
    for drive in ["conveyor", "lift", "turntable", "feeder"] {
        rest_ok(
            &daemon,
            Some(ADMIN),
            "POST",
            &format!("/api/v1/drives/{drive}/commands/activate"),
            None,
        )
        .await;
        rest_ok(
            &daemon,
            Some(ADMIN),
            "PUT",
            &format!("/api/v1/drives/{drive}/mode"),
            Some(json!({"mode": "speed"})),
        )
        .await;
    }
    let pages = [
        "/",
        "/drive/turntable",
        "/settings/lift",
        "/commissioning",
        "/events",
    ];
    for (i, hash) in pages.iter().enumerate() {
        rest_ok(
            &daemon,
            Some(ADMIN),
            "PUT",
            "/api/v1/drives/feeder/setpoint",
            Some(json!({"speed_rpm": 50})),
        )
        .await;
        until(LONG, "the feeder turning", || {
            speed(&daemon.plant, 4).is_some_and(|s| s > 20)
        })
        .await;
        page.eval(&format!("location.hash = '#{hash}'")).await;
        page.wait_for(
            "!document.getElementById('brake-all').hidden",
            LONG,
            "the brake in view",
        )
        .await;
        let visible = page
            .eval("(() => { const r = document.getElementById('brake-all').getBoundingClientRect(); return r.top >= 0 && r.bottom <= innerHeight && r.width > 0; })()")
            .await;
        assert_eq!(visible, json!(true), "the brake is not in view on {hash}");
        let pressed = Instant::now();
        if i % 2 == 0 {
            page.click("#brake-all").await;
        } else {
            // Shift+B, the keyboard's way to the same brake.
            page.key("keyDown", "B", "KeyB", 66, 8).await;
            page.key("keyUp", "B", "KeyB", 66, 8).await;
        }
        for drive in ["conveyor", "lift", "turntable", "feeder"] {
            watcher
                .wait(
                    pressed,
                    LONG,
                    &format!("the brake of {drive} from {hash}"),
                    |v| {
                        v["type"] == "write"
                            && v["drive"] == drive
                            && v["who"] == "commissioning"
                            && v["what"].as_str().unwrap_or("").contains("brake")
                            && v["ok"] == true
                    },
                )
                .await;
        }
        until(LONG, "the feeder braked to a stop", || {
            speed(&daemon.plant, 4) == Some(0)
        })
        .await;
        page.wait_for(
            "document.getElementById('brake-note').textContent.includes('confirmed by all 4')",
            LONG,
            "the page saying every drive confirmed the brake",
        )
        .await;
        rest_ok(
            &daemon,
            Some(ADMIN),
            "POST",
            "/api/v1/drives/feeder/commands/activate",
            None,
        )
        .await;
        rest_ok(
            &daemon,
            Some(ADMIN),
            "PUT",
            "/api/v1/drives/feeder/mode",
            Some(json!({"mode": "speed"})),
        )
        .await;
    }
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_value_shows_the_apis_message_beside_its_control() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/turntable", Some(ADMIN)).await;
    // What the API itself says about 400 degrees.
    let (status, problem) = rest(
        &daemon,
        Some(ADMIN),
        "PUT",
        "/api/v1/drives/turntable/setpoint",
        Some(json!({"position_deg": 400})),
    )
    .await;
    assert_eq!(status, 422);
    let detail = problem["detail"].as_str().unwrap().to_string();

    page.fill("[data-field=position]", "400").await;
    page.click("[data-action=goto]").await;
    let shown = page
        .wait_for(
            "(() => { const n = document.querySelector('[data-action=goto]').closest('.group').querySelector('.note.fail'); return n && n.textContent; })()",
            LONG,
            "the refusal beside the control",
        )
        .await;
    assert!(
        shown.as_str().unwrap().contains(&detail),
        "{shown} lacks {detail}"
    );

    // The same on the settings page: a limit above 15.99 A.
    page.eval("location.hash = '#/settings/turntable'").await;
    page.wait_for(
        "!!document.querySelector('[data-field=limit_a]')",
        LONG,
        "the settings forms",
    )
    .await;
    page.fill("[data-field=limit_a]", "40").await;
    page.click("[data-field=limit_a]").await;
    page.eval("document.querySelector('[data-field=limit_a]').closest('form').querySelector('[data-action=write]').click()")
        .await;
    let shown = page
        .wait_for(
            "(() => { const n = document.querySelector('[data-field=limit_a]').closest('form').querySelector('.note.fail'); return n && n.textContent; })()",
            LONG,
            "the settings refusal",
        )
        .await;
    assert!(shown.as_str().unwrap().contains("out of range"), "{shown}");
    assert!(shown.as_str().unwrap().contains("15.99"), "{shown}");
    // A 422 is the page working: chromium logs the answer, nothing else.
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_event_log_shows_every_write_live_and_the_ramp_time_follows_the_manual() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/events", Some(ADMIN)).await;
    // A write by another client shows, newest first, with who and the answer.
    rest_ok(
        &daemon,
        Some(OPERATOR),
        "POST",
        "/api/v1/drives/lift/commands/activate",
        None,
    )
    .await;
    let row = page
        .wait_for(
            "(() => { const r = document.querySelector('table.log tbody tr[data-kind=write]'); return r && r.textContent; })()",
            LONG,
            "the write in the log",
        )
        .await;
    let row = row.as_str().unwrap();
    assert!(
        row.contains("panel") && row.contains("activate") && row.contains("confirmed by the drive"),
        "{row}"
    );
    // Two more, in the order they were made, newest first.
    rest_ok(
        &daemon,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/lift/mode",
        Some(json!({"mode": "speed"})),
    )
    .await;
    rest_ok(
        &daemon,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/lift/setpoint",
        Some(json!({"speed_rpm": 30})),
    )
    .await;
    let newest = page
        .wait_for(
            "(() => { const r = document.querySelectorAll('table.log tbody tr[data-kind=write]'); return r.length >= 3 && r[0].textContent; })()",
            LONG,
            "three writes in the log",
        )
        .await;
    assert!(newest.as_str().unwrap().contains("30 rpm"), "{newest}");
    picture(&page, "console-events.png", false).await;
    rest_ok(
        &daemon,
        Some(OPERATOR),
        "POST",
        "/api/v1/drives/lift/commands/brake",
        None,
    )
    .await;
    // Filtered to faults, it is gone.
    page.eval("(() => { const k = document.querySelector('[data-filter=kind]'); k.value = 'fault'; k.dispatchEvent(new Event('change')); })()")
        .await;
    page.wait_for(
        "document.querySelectorAll('table.log tbody tr').length === 0",
        LONG,
        "the filter",
    )
    .await;

    // The manual's worked examples of formulas (2) and (3).
    let t = page
        .eval("import('/console/ramps.js').then((r) => [r.speedRampTime(5000, 133, 3.75), r.positionRampTime(200, 180), r.speedRampTime(10, 133, 3.75), r.positionRampTime(10, 180)])")
        .await;
    let t: Vec<f64> = t
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    // The manual rounds its constants: within 0.2 %.
    for (got, manual) in t.iter().zip([0.2047, 0.2507, 4.5765, 1.121]) {
        assert!(
            (got - manual).abs() / manual < 0.002,
            "{got} vs the manual's {manual}"
        );
    }
    // The settings form shows the time as the user types alpha.
    page.eval("location.hash = '#/settings/conveyor'").await;
    page.wait_for(
        "!!document.querySelector('[data-field=step_rpm-alpha]')",
        LONG,
        "the ramp form",
    )
    .await;
    page.eval("(() => { const f = document.querySelector('[data-field=step_rpm-alpha]').closest('form'); f.querySelector('input[value=alpha]').click(); })()")
        .await;
    page.fill("[data-field=step_rpm]", "133").await;
    page.fill("[data-field=step_rpm-alpha]", "5000").await;
    let preview = text(&page, "[data-preview=step_rpm]").await;
    assert!(preview.starts_with("0.2044 s"), "{preview}");
    picture(&page, "console-settings.png", true).await;

    // The drive page's read-back says so when another client writes after
    // it, and a new read clears that.
    page.eval("location.hash = '#/drive/lift'").await;
    let held_read = "document.querySelector('.held').dataset.stale === 'false'";
    page.wait_for(held_read, LONG, "the settings read back")
        .await;
    rest_ok(
        &daemon,
        Some(OPERATOR),
        "PUT",
        "/api/v1/drives/lift/mode",
        Some(json!({"mode": "position"})),
    )
    .await;
    page.wait_for(
        "document.querySelector('.held').dataset.stale === 'true'",
        LONG,
        "the read-back marked stale",
    )
    .await;
    let note = text(&page, ".held + .row .note").await;
    assert!(
        note.contains("written since") && note.contains("read again"),
        "{note}"
    );
    page.click("[data-read=settings]").await;
    page.wait_for(held_read, LONG, "the settings read again")
        .await;
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

/// With `DRIVEGATE_SCREENSHOTS` set (a directory, relative to the
/// repository or absolute: `docs`), saves a PNG of `page` there as
/// `name`: each picture of the docs is taken by the test that checks what
/// it shows, at that moment (`assets::every_picture_of_the_docs_is_taken_by_a_test`
/// holds every one to it). Without it, nothing.
pub(crate) async fn picture(page: &Page, name: &str, full: bool) {
    let Some(dir) = std::env::var_os("DRIVEGATE_SCREENSHOTS") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    let dir = if dir.is_absolute() {
        dir
    } else {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(dir)
    };
    page.screenshot(&dir.join(name), full).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commissioning_scans_with_progress_guards_the_address_and_follows_a_calibration() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/commissioning", Some(ADMIN)).await;
    // Before any scan the broadcast is not offered.
    page.wait_for(
        "!!document.querySelector('[data-action=set-address]')",
        LONG,
        "the page",
    )
    .await;
    assert_eq!(
        page.eval("document.querySelector('[data-action=set-address]').disabled")
            .await,
        json!(true)
    );

    page.fill("[data-field=scan-to]", "12").await;
    page.click("[data-action=scan]").await;
    page.wait_for(
        "(() => { const n = document.querySelector('#scan-h').parentElement.querySelector('.note'); return n.classList.contains('ok') || n.classList.contains('fail'); })()",
        LONG,
        "the scan's end",
    )
    .await;
    let note = text(&page, "#scan-h ~ output.note").await;
    assert!(note.starts_with("scanned: 4 answered"), "{note}");
    assert_eq!(
        page.eval(
            "(() => { const p = document.querySelector('progress'); return [p.value, p.max]; })()"
        )
        .await,
        json!([12, 12])
    );
    // Four drives answer, and the scan did not cover 1 to 255: still refused, saying why.
    assert_eq!(
        page.eval("document.querySelector('[data-action=set-address]').disabled")
            .await,
        json!(true)
    );
    let why = text(&page, ".check").await;
    assert!(why.contains("did not cover units 1 to 255"), "{why}");
    picture(&page, "console-commissioning.png", true).await;

    // Calibration of the lift, confirmed in the dialog, followed to its end.
    page.eval("(() => { const s = document.getElementById('proc-drive'); s.value = 'lift'; })()")
        .await;
    page.eval("[...document.querySelectorAll('button')].find((b) => b.textContent === 'Calibrate…').click()").await;
    page.wait_for(
        "document.getElementById('dialog').open",
        LONG,
        "the confirmation",
    )
    .await;
    let body = text(&page, "#dialog").await;
    assert!(body.contains("about 4 s"), "{body}");
    page.click("#dialog button[value=ok]").await;
    let done = page
        .wait_for(
            "(() => { const n = document.getElementById('proc-h').parentElement.querySelector('output.note'); return (n.classList.contains('ok') && n.textContent.includes('done')) || n.classList.contains('fail') ? n.textContent : null; })()",
            LONG,
            "the calibration's end",
        )
        .await;
    assert!(
        done.as_str().unwrap().contains("Calibration done")
            && done.as_str().unwrap().contains("reports calibrated"),
        "{done}"
    );
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_keyboard_jogs_and_a_lost_focus_releases() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let watcher = Watcher::start(daemon.http, Some(ADMIN)).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(OPERATOR)).await;
    activate_in_speed_mode(&page).await;
    page.eval("document.activeElement.blur()").await;

    // Held arrow key: backward while held, stopped by the lease on key-up.
    page.key("keyDown", "ArrowLeft", "ArrowLeft", 37, 0).await;
    until(LONG, "the motor turning backward", || {
        speed(&daemon.plant, 1).is_some_and(|s| s < -20)
    })
    .await;
    let released = Instant::now();
    page.key("keyUp", "ArrowLeft", "ArrowLeft", 37, 0).await;
    let (_, m) = watcher
        .wait(released, LONG, "the lease's end after key-up", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    assert_eq!(m["reason"], "it was not renewed in time", "{m}");
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;

    // Held, then the window loses focus (no key-up ever comes): released.
    page.key("keyDown", "ArrowRight", "ArrowRight", 39, 0).await;
    until(LONG, "the motor turning forward", || {
        speed(&daemon.plant, 1).is_some_and(|s| s > 20)
    })
    .await;
    let blurred = Instant::now();
    page.eval("window.dispatchEvent(new Event('blur'))").await;
    let (_, m) = watcher
        .wait(blurred, LONG, "the lease's end after the lost focus", |v| {
            v["type"] == "lease-expired" && v["drive"] == "conveyor"
        })
        .await;
    assert_eq!(m["reason"], "it was not renewed in time", "{m}");
    until(LONG, "the motor standing still", || {
        speed(&daemon.plant, 1) == Some(0)
    })
    .await;
    let state = text(&page, ".jog-state").await;
    assert!(state.contains("the window lost focus"), "{state}");
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

/// The package's configuration as shipped has no bus: the overview says
/// what to do first, in the words of /readyz, and nothing fails.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_bus_the_overview_says_to_run_probe() {
    let daemon = TestDaemon::start_no_wait(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nlisten = \"127.0.0.1:0\"\n",
    )
    .await;
    let browser = Browser::start(&[]).await;
    let page = browser.new_page(1280, 900).await;
    let base = daemon.url("");
    page.goto(&format!("{base}/#/")).await;
    page.wait_for(
        "document.querySelector('.buses .no-bus') !== null",
        LONG,
        "the overview's no-bus message",
    )
    .await;
    let text = page
        .eval("document.querySelector('.buses .no-bus').textContent")
        .await;
    assert_eq!(
        text,
        json!(
            "No bus configured: run drivegate probe --port /dev/serial/by-id/... (your adapter's \
             stable name: ls -l /dev/serial/by-id/) to find the drives and their baud rate, then add a [[bus]] with its drives \
             to the configuration and reload it (systemctl reload drivegate)."
        )
    );
    assert_clean(&page, &base);
    browser.stop().await;
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scan_offers_the_drives_it_found_and_an_admin_adds_them_to_the_configuration() {
    // An external simulator with six drives on a pty; the file knows four.
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyLINE");
    let mut sim = tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
        .args(["sim", "--units", "1-6", "--link"])
        .arg(&link)
        .stdout(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut stdout =
        tokio::io::AsyncBufReadExt::lines(tokio::io::BufReader::new(sim.stdout.take().unwrap()));
    tokio::time::timeout(LONG, stdout.next_line())
        .await
        .expect("the simulator printed its pty")
        .unwrap();
    let toml = format!(
        "# The line, by hand: keep this comment.\n{}",
        crate::support::config::ConfigBuilder::four_drives()
            .with_bus("sim", |b| b.port(link.to_str().unwrap()))
            .http_token("commissioning", "admin", ADMIN)
            .toml()
    );
    let daemon = TestDaemon::reloadable(&toml).await;
    let browser = Browser::start(&[]).await;
    let base = daemon.url("");
    let page = open(&browser, &base, "/commissioning", Some(ADMIN)).await;
    page.wait_for(
        "!!document.querySelector('[data-action=scan]')",
        LONG,
        "the page",
    )
    .await;
    page.fill("[data-field=scan-to]", "8").await;
    page.click("[data-action=scan]").await;
    let button = "document.querySelector('[data-action=add-to-config]')";
    page.wait_for(
        &format!("{button} && !{button}.disabled"),
        LONG,
        "the offer to add the drives found",
    )
    .await;
    assert_eq!(
        page.eval("document.querySelector('[data-field=new-drives]').textContent")
            .await,
        json!(
            "[[bus.drive]]\nunit = 5\nname = \"sim-5\"\n\n[[bus.drive]]\nunit = 6\nname = \"sim-6\"\n"
        )
    );
    page.click("[data-action=add-to-config]").await;
    page.wait_for(
        "drivegate.store.order.length === 6",
        LONG,
        "the two drives added to the page",
    )
    .await;
    let note = page
        .eval("document.querySelector('.scan-add output.note').textContent")
        .await;
    assert_eq!(
        note,
        json!(
            "written and reloaded: drives added: sim-5, sim-6; bus sim changed in place (drives), its port kept open"
        )
    );
    let written = std::fs::read_to_string(daemon.config_path()).unwrap();
    assert!(written.starts_with("# The line, by hand: keep this comment.\n"));
    assert!(
        written.contains("[[bus.drive]]\nunit = 6\nname = \"sim-6\"\n"),
        "{written}"
    );
    assert_eq!(daemon.plant.now().drive_count(), 6);
    assert_clean(&page, &base);
    browser.stop().await;
    daemon.stop().await;
}
