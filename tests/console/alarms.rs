//! Alarms in the console, on the daemon's alarms API and stream: a drive
//! gone silent raises an alarm whose banner stays on every page until an
//! operator acknowledges it (a viewer sees it, with no button); the alarm
//! list shows its date, what to do (the API's help, not the page's) and
//! who acknowledged it when; a fault on the drive page says what to do in
//! the words of its alarm.

use serde_json::{Value, json};

use super::browser::{LONG, assert_clean, open, picture, rest, text};
use super::harness::cdp::Browser;
use super::harness::{OPERATOR, VIEWER, config};
use crate::support::TestDaemon;

/// The alarms of `drive` of `kind`, as the API lists them.
async fn alarms_of(d: &TestDaemon, drive: &str, kind: &str) -> Vec<Value> {
    let (status, list) = rest(
        d,
        Some(VIEWER),
        "GET",
        &format!("/api/v1/alarms?drive={drive}"),
        None,
    )
    .await;
    assert_eq!(status, 200, "{list}");
    list["alarms"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["kind"] == kind)
        .cloned()
        .collect()
}

/// Acknowledges every alarm not acknowledged yet (as the admin).
async fn acknowledge_all(d: &TestDaemon) {
    let (_, list) = rest(
        d,
        Some(VIEWER),
        "GET",
        "/api/v1/alarms?unacknowledged=true",
        None,
    )
    .await;
    for a in list["alarms"].as_array().unwrap() {
        let (status, body) = rest(
            d,
            Some(super::harness::ADMIN),
            "POST",
            &format!("/api/v1/alarms/{}/ack", a["id"]),
            None,
        )
        .await;
        assert_eq!(status, 200, "{body}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_shows_a_banner_until_an_operator_acknowledges_it() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/", Some(OPERATOR)).await;
    let viewer = open(&browser, &daemon.url(""), "/events", Some(VIEWER)).await;
    // The operator's tab in front (a background tab draws nothing); the
    // viewer's banner is not drawn by frames, so it works behind.
    page.call("Page.bringToFront", json!({})).await;
    // A loaded machine can make a drive miss its polls for a moment, which
    // is an alarm too: whatever is there before the test's own is
    // acknowledged first, and the checks below are about the feeder's.
    acknowledge_all(&daemon).await;
    page.wait_for(
        "document.getElementById('alarm-banner').hidden",
        LONG,
        "no banner once every alarm is acknowledged",
    )
    .await;

    daemon.sim().set_silent(4, true);
    let banner = page
        .wait_for(
            "(() => { const b = document.getElementById('alarm-banner'); return !b.hidden && b.textContent.includes('feeder: offline') && b.textContent; })()",
            LONG,
            "the alarm banner",
        )
        .await;
    let banner = banner.as_str().unwrap();
    assert!(
        banner.contains(" not acknowledged: ") && banner.contains("feeder: offline"),
        "{banner}"
    );
    picture(&page, "console-alarm-banner.png", false).await;
    // On every page, and for a viewer too, without the button.
    for hash in ["/drive/lift", "/settings/lift", "/events"] {
        page.eval(&format!("location.hash = '#{hash}'")).await;
        page.wait_for(
            &format!(
                "document.getElementById('main').dataset.page === '{}'",
                hash.split('/').nth(1).unwrap()
            ),
            LONG,
            hash,
        )
        .await;
        assert_eq!(
            page.eval("document.getElementById('alarm-banner').hidden")
                .await,
            json!(false),
            "no banner on {hash}"
        );
    }
    viewer
        .wait_for(
            "!document.getElementById('alarm-banner').hidden",
            LONG,
            "the viewer's banner",
        )
        .await;
    assert_eq!(
        viewer
            .eval("!!document.querySelector('#alarm-banner button')")
            .await,
        json!(false)
    );

    // The list: date and time, what to do in the API's words.
    let alarm = alarms_of(&daemon, "feeder", "offline").await;
    assert_eq!(alarm.len(), 1, "{alarm:?}");
    let alarm = &alarm[0];
    let id = alarm["id"].as_u64().unwrap();
    page.eval("location.hash = '#/alarms'").await;
    let row = format!("tr[data-alarm='{id}']");
    page.wait_for(
        &format!("!!document.querySelector(\"{row}\")"),
        LONG,
        "the alarm in the list",
    )
    .await;
    let help = text(&page, &format!("{row} td.help")).await;
    assert_eq!(help, alarm["help"].as_str().unwrap());
    assert!(!help.is_empty());
    let raised = text(&page, &format!("{row} td:first-child time")).await;
    assert_eq!(raised.len(), 19, "{raised}");

    // Acknowledged from the banner: it goes, the list says who and when.
    page.click("#alarm-banner button[data-ack]").await;
    let gone = "(() => { const b = document.getElementById('alarm-banner'); return b.hidden || !b.textContent.includes('feeder: offline'); })()";
    page.wait_for(gone, LONG, "the banner gone").await;
    viewer
        .wait_for(gone, LONG, "the viewer's banner gone")
        .await;
    let acked = alarms_of(&daemon, "feeder", "offline").await;
    assert_eq!(acked[0]["acknowledged_by"], "panel", "{acked:?}");
    let by = page
        .wait_for(
            &format!("(() => {{ const c = document.querySelector(\"{row} td:last-child\"); return c && c.textContent.startsWith('by ') ? c.textContent : null; }})()"),
            LONG,
            "who acknowledged it",
        )
        .await;
    assert!(by.as_str().unwrap().starts_with("by panel"), "{by}");
    picture(&page, "console-alarms.png", false).await;
    // Still active: the drive is still silent.
    assert_eq!(acked[0]["active"], true);
    assert!(text(&page, &row).await.contains("active"));

    // A fault: the drive page says what to do, in its alarm's words.
    daemon
        .sim()
        .inject_fault(3, drivegate::drive::Fault::OverTemperature)
        .unwrap();
    page.eval("location.hash = '#/drive/turntable'").await;
    let shown = page
        .wait_for(
            "(() => { const f = document.querySelector('.fault-help'); const h = f && f.querySelector('[data-help]'); return !f.hidden && h ? f.textContent : null; })()",
            LONG,
            "the fault's help on the drive page",
        )
        .await;
    let fault = alarms_of(&daemon, "turntable", "fault").await;
    let fault_help = fault[0]["help"].as_str().unwrap();
    let shown = shown.as_str().unwrap();
    assert!(
        shown.starts_with("Fault: over temperature. What to do: ") && shown.ends_with(fault_help),
        "{shown} / {fault_help}"
    );
    picture(&page, "console-fault-help.png", false).await;
    // The banner is back for the new alarm (the newest, unless the
    // machine's load raised another since).
    assert_eq!(fault[0]["acknowledged"], false);
    page.wait_for(
        "!document.getElementById('alarm-banner').hidden",
        LONG,
        "the fault's banner",
    )
    .await;
    assert_clean(&page, &daemon.url(""));
    assert_clean(&viewer, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}
