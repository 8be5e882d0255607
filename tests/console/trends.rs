//! The drive page's trends zoomed from the last 30 s (live, from the
//! stream) out to the hour, read from the daemon's history: the plots
//! start at the oldest point kept and end now, hold exactly the points the
//! history API answers for that range, and show the speed the drive ran
//! at; back at 30 s they are live again.

use serde_json::{Value, json};

use super::browser::{LONG, assert_clean, open, picture, rest, rest_ok};
use super::harness::cdp::Browser;
use super::harness::{ADMIN, OPERATOR, config, speed, until};
use crate::support::TestDaemon;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_drive_page_zooms_from_30_seconds_to_the_hour_from_the_history() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    let a = Some(ADMIN);
    super::browser::in_speed_mode(&daemon, "conveyor").await;
    rest_ok(
        &daemon,
        a,
        "PUT",
        "/api/v1/drives/conveyor/setpoint",
        Some(json!({"speed_rpm": 90})),
    )
    .await;
    until(LONG, "the conveyor at speed", || {
        speed(&daemon.plant, 1).is_some_and(|s| s > 80)
    })
    .await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(OPERATOR)).await;
    page.wait_for(
        "document.querySelector('.plots').dataset.source === 'live' \
         && Number(document.querySelector('.plots').dataset.points) > 5",
        LONG,
        "the live plots",
    )
    .await;
    assert_eq!(
        page.eval("document.querySelector('[data-zoom=\"30\"]').getAttribute('aria-pressed')")
            .await,
        json!("true")
    );
    // The drive page as an operator sees it, the conveyor running at 90
    // rpm: its plots live over five seconds, its controls.
    page.wait_for(
        "(() => { const h = drivegate.store.drives.get('conveyor').history; \
         return h && h.t.length && h.t[h.t.length - 1] - h.t[0] >= 5 && h.speed.slice(-5).every((v) => v > 80); })()",
        LONG,
        "five seconds of the speed plotted",
    )
    .await;
    picture(&page, "console-drive.png", true).await;

    page.click("[data-zoom=\"3600\"]").await;
    let read = page
        .wait_for(
            "(() => { const b = document.querySelector('.plots'); \
             return b.dataset.source === 'history' && b.dataset.points \
             ? [Number(b.dataset.from), Number(b.dataset.until), Number(b.dataset.points)] : null; })()",
            LONG,
            "the hour from the history",
        )
        .await;
    let (from, until_ms, points) = (
        read[0].as_i64().unwrap(),
        read[1].as_i64().unwrap(),
        read[2].as_u64().unwrap(),
    );
    assert_eq!(until_ms - from, 3_600_000);
    assert!(points > 0);
    let title = page
        .eval("document.getElementById('plots-h').textContent")
        .await;
    assert_eq!(title, json!("Last 1 h, from drivegate's history"));
    // drivegate has kept seconds of the hour: the x axis starts at the
    // oldest point kept (10 s before now at least) and ends now, so the
    // data fills the plot, and the note says how much there is.
    let x = page
        .eval("(() => { const p = document.querySelector('[data-plot=speed]').plot; return [p.scales.x.min, p.scales.x.max, p.data[0][0]]; })()")
        .await;
    let (x_min, x_max, oldest) = (
        x[0].as_f64().unwrap(),
        x[1].as_f64().unwrap(),
        x[2].as_f64().unwrap(),
    );
    assert_eq!((x_max * 1000.0).round() as i64, until_ms, "{x}");
    assert_eq!(x_min, oldest.min(x_max - 10.0), "{x}");
    assert!(x_max - x_min < 60.0, "{x}");
    let note = page
        .eval("document.querySelector('.plots').parentElement.querySelector('.note').textContent")
        .await;
    let note = note.as_str().unwrap_or_default();
    assert!(
        note.starts_with("drivegate has kept ")
            && note.ends_with("(it keeps 60 min): the plot starts there"),
        "{note}"
    );

    // The heading and the note below the page's fixed header.
    page.eval("document.getElementById('plots-h').scrollIntoView(); window.scrollBy(0, -70)")
        .await;
    picture(&page, "console-trends-hour.png", false).await;

    // The same range asked of the API: the same points, plotted as mean
    // with its minimum and maximum.
    let (status, history) = rest(
        &daemon,
        Some(OPERATOR),
        "GET",
        &format!(
            "/api/v1/drives/conveyor/history?fields=speed_rpm&since={from}&until={until_ms}&max_points=1500"
        ),
        None,
    )
    .await;
    assert_eq!(status, 200, "{history}");
    let plotted = page
        .eval("(() => { const p = document.querySelector('[data-plot=speed]').plot; return [p.data[0], p.data[1], p.data[2], p.data[3]]; })()")
        .await;
    let times: Vec<i64> = history["t_ms"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_i64().unwrap())
        .collect();
    let plotted_times: Vec<i64> = plotted[0]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| (t.as_f64().unwrap() * 1000.0).round() as i64)
        .collect();
    // A status polled just before the page asked may be kept just after
    // it was answered: the API's answer, asked later, may end with points
    // the page has not seen yet, never differ before them.
    let seen = times
        .iter()
        .take_while(|t| Some(*t) <= plotted_times.last())
        .count();
    assert!(times.len() - seen <= 3, "{times:?} {plotted_times:?}");
    assert_eq!(
        plotted_times,
        times[..seen],
        "the page plots the history's points"
    );
    let column = &history["fields"]["speed_rpm"];
    let numbers = |v: &Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .take(seen)
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    for (i, key) in [(1, "mean"), (2, "min"), (3, "max")] {
        assert_eq!(numbers(&plotted[i]), numbers(&column[key]), "{key}");
    }
    let top = column["max"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_f64)
        .fold(f64::MIN, f64::max);
    assert!(top > 80.0, "the speed in the hour's plot: {top}");

    // Back to 30 s: live again.
    page.click("[data-zoom=\"30\"]").await;
    page.wait_for(
        "document.querySelector('.plots').dataset.source === 'live' \
         && Number(document.querySelector('.plots').dataset.points) > 5",
        LONG,
        "the live plots again",
    )
    .await;
    rest_ok(
        &daemon,
        a,
        "POST",
        "/api/v1/drives/conveyor/commands/brake",
        None,
    )
    .await;
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}
