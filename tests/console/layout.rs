//! The console's layout, measured in the real browser: the header in one
//! row at 1280 px (BRAKE ALL beside the pages, not under them) over a
//! plant's overview, and pages that fit a tablet's width; the trends' time
//! labels apart from each other at every zoom and width; the bus's
//! utilisation explained where it is shown. The overview's and the
//! tablet's pictures for docs/ are taken here.

use serde_json::{Value, json};

use super::browser::{LONG, assert_clean, open, picture, rest_ok};
use super::harness::cdp::Browser;
use super::harness::{ADMIN, OPERATOR, config};
use crate::support::TestDaemon;

/// The header's items as boxes: every item's top and bottom, and the
/// header's own height (the alarm banner, a row of its own by design,
/// left out).
const HEADER: &str = "(() => { \
    const items = [document.querySelector('.brand'), ...document.querySelectorAll('#nav a'), \
      document.getElementById('conn'), document.getElementById('who'), \
      document.getElementById('brake-all')] \
      .filter((e) => e && !e.hidden && e.getClientRects().length); \
    const boxes = items.map((e) => { const r = e.getBoundingClientRect(); \
      return { id: e.id || e.textContent.trim().slice(0, 20), top: r.top, bottom: r.bottom, right: r.right }; }); \
    const header = document.querySelector('header.top').getBoundingClientRect(); \
    return { boxes, height: header.height, width: document.documentElement.clientWidth, \
      brake: !document.getElementById('brake-all').hidden }; })()";

/// Checks that the header's items share one row: each one's box spans the
/// vertical middle of the others, and none passes the window's edge.
fn one_row(header: &Value) {
    let boxes = header["boxes"].as_array().unwrap();
    assert!(boxes.len() >= 10, "{header:#}");
    let top = boxes
        .iter()
        .map(|b| b["top"].as_f64().unwrap())
        .fold(f64::MIN, f64::max);
    let bottom = boxes
        .iter()
        .map(|b| b["bottom"].as_f64().unwrap())
        .fold(f64::MAX, f64::min);
    assert!(
        top < bottom,
        "the header wraps onto a second row: {header:#}"
    );
    let width = header["width"].as_f64().unwrap();
    for b in boxes {
        assert!(
            b["right"].as_f64().unwrap() <= width,
            "{b} past the edge: {header:#}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_of_a_plant_fits_one_header_row_at_1280_px_and_a_tablet() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    // A plant: the conveyor running, the turntable in fault, the feeder
    // gone silent.
    super::browser::in_speed_mode(&daemon, "conveyor").await;
    rest_ok(
        &daemon,
        Some(ADMIN),
        "PUT",
        "/api/v1/drives/conveyor/setpoint",
        Some(json!({"speed_rpm": 120})),
    )
    .await;
    daemon
        .sim()
        .inject_fault(3, drivegate::drive::Fault::OverTemperature)
        .unwrap();
    daemon.sim().set_silent(4, true);
    let browser = Browser::start(&[]).await;
    // The admin sees every page in the navigation, and BRAKE ALL.
    let page = open(&browser, &daemon.url(""), "/", Some(ADMIN)).await;
    page.wait_for(
        "!document.getElementById('brake-all').hidden && document.querySelectorAll('#nav a').length === 9 \
         && document.querySelectorAll('tr.fault').length === 1 && document.querySelectorAll('tr.offline').length === 1",
        LONG,
        "the admin's header over the plant's overview",
    )
    .await;
    page.wait_for(UTILISATION, LONG, "the utilisation").await;
    let header = page.eval(HEADER).await;
    assert_eq!(header["width"], json!(1280), "{header:#}");
    assert_eq!(header["brake"], json!(true));
    one_row(&header);
    // One row of buttons with the padding around it, not two rows.
    let height = header["height"].as_f64().unwrap();
    assert!(
        height < 70.0
            || page
                .eval("!document.getElementById('alarm-banner').hidden")
                .await
                == json!(true),
        "header {height} px high: {header:#}"
    );
    let below_banner = page
        .eval("(() => { const b = document.getElementById('alarm-banner'); const brake = document.getElementById('brake-all'); \
               return b.hidden || b.getBoundingClientRect().top >= brake.getBoundingClientRect().bottom; })()")
        .await;
    assert_eq!(
        below_banner,
        json!(true),
        "the alarm banner is a row of its own"
    );
    picture(&page, "console-overview.png", false).await;
    assert_clean(&page, &daemon.url(""));

    tablet_pages(&browser, &daemon).await;
    browser.stop().await;
    daemon.stop().await;
}

/// At a tablet's width (an operator's) the header wraps, by design, and
/// the overview and the drive page fit without scrolling sideways; their
/// pictures are taken.
async fn tablet_pages(browser: &Browser, daemon: &TestDaemon) {
    let tablet = browser.new_page(820, 1180).await;
    tablet.goto(&format!("{}/#/", daemon.url(""))).await;
    tablet
        .wait_for(
            "document.getElementById('login').open",
            LONG,
            "the token dialog",
        )
        .await;
    tablet.fill("#login input", OPERATOR).await;
    tablet.click("#login button[type=submit]").await;
    tablet
        .wait_for(
            "window.drivegate && drivegate.stream.state === 'open' \
             && document.querySelectorAll('table.drives tbody tr').length === 4 \
             && document.querySelectorAll('tr.offline').length === 1",
            LONG,
            "the overview at tablet width",
        )
        .await;
    tablet
        .wait_for(UTILISATION, LONG, "the utilisation at tablet width")
        .await;
    let widths = tablet
        .eval("[document.documentElement.scrollWidth, document.documentElement.clientWidth]")
        .await;
    assert_eq!(
        widths[0], widths[1],
        "the overview scrolls sideways: {widths}"
    );
    picture(&tablet, "console-overview-tablet.png", false).await;
    tablet.eval("location.hash = '#/drive/conveyor'").await;
    tablet
        .wait_for(
            "!!document.querySelector('.controls') && !document.getElementById('brake-all').hidden \
             && Number(document.querySelector('.plots').dataset.points) > 5",
            LONG,
            "the drive page at tablet width",
        )
        .await;
    let widths = tablet
        .eval("[document.documentElement.scrollWidth, document.documentElement.clientWidth]")
        .await;
    assert_eq!(
        widths[0], widths[1],
        "the drive page scrolls sideways: {widths}"
    );
    picture(&tablet, "console-drive-tablet.png", false).await;
    assert_clean(&tablet, &daemon.url(""));
}

/// The time labels of the plot `u` (a JavaScript expression) as boxes in
/// CSS pixels of its canvas: `[left, right, text]`, in order.
const LABELS: &str = "((u) => { \
    const ax = u.axes[0]; const dpr = window.devicePixelRatio || 1; \
    const ctx = document.createElement('canvas').getContext('2d'); ctx.font = ax.font[0]; \
    const out = []; \
    (ax._splits || []).forEach((s, i) => { const v = ax._values[i]; if (v == null || v === '') return; \
      const x = u.bbox.left / dpr + u.valToPos(s, 'x'); const w = ctx.measureText(String(v)).width / dpr; \
      out.push([x - w / 2, x + w / 2, String(v)]); }); \
    return { width: u.width, labels: out }; })";

/// Checks that `plot`'s labels are apart (4 px at least between two), on
/// the canvas, and at least two on a plot 400 px wide or more (one on the
/// narrowest).
fn apart(plot: &Value, what: &str) {
    let labels = plot["labels"].as_array().unwrap();
    let width = plot["width"].as_f64().unwrap();
    let least = if width >= 400.0 { 2 } else { 1 };
    assert!(labels.len() >= least, "{what}: too few labels: {plot}");
    // Each label says another time: ticks closer than the labels' unit
    // would repeat one.
    let texts: std::collections::BTreeSet<&str> =
        labels.iter().map(|l| l[2].as_str().unwrap()).collect();
    assert_eq!(
        texts.len(),
        labels.len(),
        "{what}: a time said twice: {plot}"
    );
    for pair in labels.windows(2) {
        let (right, next_left) = (pair[0][1].as_f64().unwrap(), pair[1][0].as_f64().unwrap());
        assert!(right + 4.0 <= next_left, "{what}: labels overlap: {plot}");
    }
    for l in labels {
        let (left, right) = (l[0].as_f64().unwrap(), l[1].as_f64().unwrap());
        assert!(
            left >= 0.0 && right <= width,
            "{what}: label {l} cut off: {plot}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_trends_time_labels_never_overlap_at_any_zoom_or_width() {
    let daemon = TestDaemon::start(&config(true, "")).await;
    super::browser::in_speed_mode(&daemon, "conveyor").await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/drive/conveyor", Some(ADMIN)).await;
    page.wait_for(
        "Number(document.querySelector('.plots').dataset.points) > 5",
        LONG,
        "the live plots",
    )
    .await;
    // Just opened: the live view has seen a second or less.
    for plot in ["speed", "temperature"] {
        let measured = page
            .eval(&format!(
                "{LABELS}(document.querySelector('[data-plot={plot}]').plot)"
            ))
            .await;
        apart(&measured, &format!("{plot} just opened"));
    }
    // The drive page's own plots at each zoom, on a wide screen and at
    // tablet width.
    for (width, height) in [(1280, 900), (820, 1180)] {
        page.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        )
        .await;
        for zoom in ["300", "900", "3600", "30"] {
            page.click(&format!("[data-zoom=\"{zoom}\"]")).await;
            page.wait_for(
                &format!(
                    "(() => {{ const b = document.querySelector('.plots'); return b.dataset.window === '{zoom}' \
                     && Number(b.dataset.points) > 1 && b.clientWidth <= {width}; }})()"
                ),
                LONG,
                "the zoomed plots",
            )
            .await;
            for plot in ["speed", "temperature"] {
                let measured = page
                    .eval(&format!(
                        "{LABELS}(document.querySelector('[data-plot={plot}]').plot)"
                    ))
                    .await;
                apart(&measured, &format!("{plot} at {zoom} s, {width} px"));
            }
        }
    }
    // The axis the plots use, over every span from seconds to hours and
    // widths from a phone's to a wide screen's: a drive page open an hour
    // shows the whole hour, which the test's young daemon cannot.
    let sweep = page
        .eval(&format!(
            "import('/console/trends.js').then(async ({{ timeAxis, timePadding }}) => {{ \
               const made = []; const end = Math.floor(Date.now() / 1000) + 17.3; \
               for (const width of [240, 400, 600, 820, 1200]) \
                 for (const span of [10, 30, 37, 90, 300, 600, 900, 1800, 3600, 7200]) {{ \
                   const box = document.createElement('div'); document.body.append(box); \
                   const u = new uPlot({{ width, height: 160, padding: timePadding(), legend: {{ show: false }}, \
                     scales: {{ x: {{ time: true, range: () => [end - span, end] }} }}, \
                     axes: [timeAxis(), {{ size: 56 }}], series: [{{}}, {{}}] }}, \
                     [[end - span, end], [0, 1]], box); \
                   made.push({{ width, span, u, box }}); }} \
               await new Promise((r) => requestAnimationFrame(() => setTimeout(r, 0))); \
               return made.map(({{ width, span, u, box }}) => {{ \
                 const plot = {LABELS}(u); u.destroy(); box.remove(); return {{ width, span, plot }}; }}); }})"
        ))
        .await;
    let sweep = sweep.as_array().unwrap();
    assert_eq!(sweep.len(), 50);
    for case in sweep {
        apart(
            &case["plot"],
            &format!("{} s at {} px", case["span"], case["width"]),
        );
    }
    // The hour reads in hours and minutes.
    let hour = sweep
        .iter()
        .find(|c| c["span"] == 3600 && c["width"] == 1200)
        .unwrap();
    let first = hour["plot"]["labels"][0][2].as_str().unwrap();
    assert_eq!(first.len(), 5, "{hour}");
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;
}

/// The overview's utilisation of bus `sim` and the note beside it.
const UTILISATION: &str = "(() => { const card = document.querySelector('.bus[data-bus=sim]'); \
    if (!card) return null; const dts = [...card.querySelectorAll('dt')]; \
    const dt = dts.find((d) => d.textContent === 'Utilisation'); \
    const note = card.querySelector('[data-field=utilisation-note]'); \
    return dt && dt.nextElementSibling.textContent !== '–' && note \
      ? [dt.nextElementSibling.textContent, note.textContent] : null; })()";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn utilisation_is_explained_where_it_is_shown() {
    // Polled flat out (poll_interval_ms = 0, the default): the wire is
    // full, by design, and the card says so beside the figure.
    let daemon = TestDaemon::start(&config(false, "")).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/", None).await;
    let shown = page.wait_for(UTILISATION, LONG, "the utilisation").await;
    let (figure, note) = (shown[0].as_str().unwrap(), shown[1].as_str().unwrap());
    assert!(figure.ends_with(" %"), "{shown}");
    assert!(
        note.starts_with("Utilisation is the share of the wire's time in use.")
            && note.contains("polled as fast as the line allows (poll_interval_ms = 0)")
            && note.contains("near 100 % by design"),
        "{note}"
    );
    assert_clean(&page, &daemon.url(""));
    browser.stop().await;
    daemon.stop().await;

    // Paced: no word of "by design".
    let paced = crate::support::config::ConfigBuilder::four_drives()
        .with_bus("sim", |b| b.keys("poll_interval_ms = 200"))
        .toml();
    let daemon = TestDaemon::start(&paced).await;
    let browser = Browser::start(&[]).await;
    let page = open(&browser, &daemon.url(""), "/", None).await;
    let shown = page.wait_for(UTILISATION, LONG, "the utilisation").await;
    let note = shown[1].as_str().unwrap();
    assert!(
        note.starts_with("Utilisation is the share of the wire's time in use")
            && !note.contains("by design"),
        "{note}"
    );
    browser.stop().await;
    daemon.stop().await;
}
