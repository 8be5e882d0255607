//! The console tells a dead line from a running one: the daemon runs on
//! an external simulator (`drivegate sim --link`, a process of its own);
//! killed, every value on the overview and the drive page is greyed, the
//! overview counts "0 of 2 online: bus line1 is down", each row says since
//! when and (on hover) why, the drive page says it in a sentence with the
//! port's error; the bus's card shows no utilisation nor error rate from
//! the moment it says the port is down ("— not live", greyed, never a
//! figure), and the header's badge, which says the page is connected,
//! says the bus is down beside it (never green over a dead line); plugged
//! back, all live again. A bus configured at the wrong baud rate shows its
//! drives as never answered, with the rate, the unit address and
//! `drivegate probe --try-bauds`, and the badge says they are not live.
//! The pictures for `docs/` (`DRIVEGATE_SCREENSHOTS=docs`) are taken once
//! each is checked.

use std::path::Path;

use serde_json::json;

use super::browser::{LONG, assert_clean, picture, rest_ok, text};
use super::harness::cdp::{Browser, Page};
use crate::support::config::ConfigBuilder;
use crate::support::sim_process::ExternalSim;
use crate::support::{TestDaemon, bounded};

/// The daemon on `link`, bus `line1` at `baud`, the conveyor (1) and the
/// belt (2); no tokens (loopback is admin).
fn config(link: &Path, baud: u32) -> String {
    ConfigBuilder::new()
        .bus("line1", |b| {
            b.port(&link.display().to_string())
                .keys(&format!("baud = {baud}"))
                .drive(1, "conveyor")
                .drive(2, "belt")
        })
        .toml()
}

/// Opens the console at `#hash` and waits until it lists both drives.
async fn open(browser: &Browser, base: &str, hash: &str) -> Page {
    let page = browser.new_page(1280, 900).await;
    page.goto(&format!("{base}/#{hash}")).await;
    page.wait_for(
        "window.drivegate && drivegate.stream.state === 'open' && drivegate.store.order.length === 2",
        LONG,
        "the console with both drives",
    )
    .await;
    page
}

/// The overview's summary line, once it reads `want`.
async fn summary(page: &Page, want: &str) {
    page.wait_for(
        &format!(
            "document.querySelector('.summary.drives') \
             && document.querySelector('.summary.drives').textContent === {}",
            serde_json::to_string(want).unwrap()
        ),
        LONG,
        &format!("the summary \"{want}\""),
    )
    .await;
}

/// Waits until the header's badge reads `text` with class `class`.
async fn badge_is(page: &Page, text: &str, class: &str) {
    page.wait_for(
        &format!(
            "document.getElementById('conn').textContent === {} && document.getElementById('conn').className === {}",
            serde_json::to_string(text).unwrap(),
            serde_json::to_string(class).unwrap()
        ),
        LONG,
        &format!("the badge \"{text}\""),
    )
    .await;
}

/// Bus line1's card's utilisation: `[text, font style, colour, the card
/// down]`, once it has a card.
const UTILISATION: &str = "(() => { const c = document.querySelector('.bus[data-bus=line1]'); if (!c) return null; \
    const dt = [...c.querySelectorAll('dt')].find((d) => d.textContent === 'Utilisation'); \
    const dd = dt.nextElementSibling; const s = getComputedStyle(dd); \
    return [dd.textContent, s.fontStyle, s.color, c.classList.contains('down')]; })()";

/// Records, from now on, every moment bus line1's card says its port is
/// down while a figure stands beside Utilisation or Errors.
const WATCH_RATES: &str = "(() => { window.ratesWhileDown = []; const check = () => { \
    const c = document.querySelector('.bus[data-bus=line1]'); if (!c || !c.classList.contains('down')) return; \
    for (const dt of c.querySelectorAll('dt')) { \
      if ((dt.textContent === 'Utilisation' || dt.textContent === 'Errors') && /\\d/.test(dt.nextElementSibling.textContent)) \
        window.ratesWhileDown.push(dt.nextElementSibling.textContent); } }; \
    new MutationObserver(check).observe(document.querySelector('.buses'), { childList: true, subtree: true, characterData: true }); \
    return true; })()";

/// `[text, font style, colour, title]` of cell `n` (1-based, after the
/// name: 2 the state, 4 the speed, 7 the voltage) of `drive`'s row.
async fn cell(page: &Page, drive: &str, n: usize) -> serde_json::Value {
    page.eval(&format!(
        "(() => {{ const c = document.querySelector('tr[data-drive={drive}] td:nth-of-type({n})'); \
         const s = getComputedStyle(c); return [c.textContent, s.fontStyle, s.color, c.title]; }})()"
    ))
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_that_went_down_greys_every_value_with_why_and_since_when() {
    bounded(std::time::Duration::from_secs(120), async {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-line1");
        let sim = ExternalSim::start(&link, "1-2", &[]).await;
        let daemon = TestDaemon::start(&config(&link, 115_200)).await;
        // The conveyor runs at 60 rpm, as on the line that looked alive.
        for (method, path, body) in [
            ("POST", "/api/v1/drives/conveyor/commands/activate", None),
            ("PUT", "/api/v1/drives/conveyor/mode", Some(json!({"mode": "speed"}))),
            ("PUT", "/api/v1/drives/conveyor/setpoint", Some(json!({"speed_rpm": 60}))),
        ] {
            rest_ok(&daemon, None, method, path, body).await;
        }
        let browser = Browser::start(&[]).await;
        let base = daemon.url("");
        let page = open(&browser, &base, "/").await;
        summary(&page, "2 of 2 online").await;
        page.wait_for(
            "document.querySelector('tr[data-drive=conveyor] td:nth-of-type(4)').textContent === '60'",
            LONG,
            "the conveyor at 60 rpm",
        )
        .await;
        // The page's link, and all live: green, one word.
        badge_is(&page, "connected", "conn open").await;
        let shown = page
            .wait_for(
                &format!("(() => {{ const u = {UTILISATION}; return u && u[0].endsWith(' %') ? u : null; }})()"),
                LONG,
                "the bus's utilisation",
            )
            .await;
        assert_eq!(shown[3], json!(false), "{shown}");
        assert_eq!(page.eval(WATCH_RATES).await, json!(true));

        sim.kill().await;
        summary(&page, "0 of 2 online: bus line1 is down").await;
        // The card: no figure from the moment it says the port is down.
        let utilisation = page
            .wait_for(
                &format!("(() => {{ const u = {UTILISATION}; return u && u[3] ? u : null; }})()"),
                LONG,
                "the card down",
            )
            .await;
        assert_eq!(
            utilisation,
            json!(["— not live: the port is down", "italic", "rgb(107, 114, 128)", true])
        );
        assert_eq!(
            page.eval("window.ratesWhileDown").await,
            json!([]),
            "a rate shown on a card whose port is down"
        );
        // The badge: still connected, and the bus down beside it.
        badge_is(&page, "connected · bus down", "conn open down").await;
        let title = page.eval("document.getElementById('conn').title").await;
        assert_eq!(
            title,
            json!("This page is connected to drivegate; 0 of 2 drives live; down: bus line1.")
        );
        for drive in ["conveyor", "belt"] {
            page.wait_for(
                &format!("document.querySelector('tr[data-drive={drive}]').dataset.freshness === 'bus-down'"),
                LONG,
                "the row marked bus down",
            )
            .await;
            // The state says since when; hovering it, why.
            let state = cell(&page, drive, 2).await;
            let (said, why) = (state[0].as_str().unwrap(), state[3].as_str().unwrap());
            assert!(said.starts_with("bus down since "), "{state}");
            assert!(
                why.starts_with("Bus line1 is down since ") && why.contains("bus line1 is down: "),
                "{state}"
            );
            // Its last values stay, greyed and in italics, not dashes.
            let voltage = cell(&page, drive, 7).await;
            assert_ne!(voltage[0], json!("–"), "{voltage}");
            assert_eq!(voltage[1], json!("italic"), "{voltage}");
            assert_eq!(voltage[2], json!("rgb(107, 114, 128)"), "{voltage}");
        }
        let speed = cell(&page, "conveyor", 4).await;
        assert_eq!((&speed[0], &speed[1]), (&json!("60"), &json!("italic")), "{speed}");
        // The last values' age keeps counting while the bus is down.
        page.wait_for(
            "/^[3-9]\\.\\d s$/.test(document.querySelector('tr[data-drive=conveyor] td:nth-of-type(9)').textContent)",
            LONG,
            "the conveyor's age counting past 3 s",
        )
        .await;
        // The bus's card says it too.
        let card = text(&page, ".bus[data-bus=line1]").await;
        assert!(card.contains("port down") && card.contains("0 of 2"), "{card}");
        // Why a full wire is no fault says nothing of a port that is down.
        assert!(!card.contains("Utilisation is the share"), "{card}");
        // The banner names the bus once, then the alarm and its words.
        let banner = page
            .wait_for(
                "(() => { const b = document.getElementById('alarm-banner'); \
                  return !b.hidden && b.textContent.includes('bus down') && b.textContent; })()",
                LONG,
                "the bus-down alarm's banner",
            )
            .await;
        let banner = banner.as_str().unwrap_or_default();
        assert!(
            banner.starts_with("1 alarm not acknowledged: ")
                && banner.contains(" bus line1: bus down, its port failed (")
                && banner.matches("bus line1").count() == 1,
            "{banner}"
        );
        picture(&page, "console-bus-down.png", false).await;

        // The drive page: greyed values, a sentence with since when, the
        // port's error beside it.
        page.eval("location.hash = '#/drive/conveyor'").await;
        page.wait_for(
            "document.querySelector('.drive-head') && document.querySelector('.drive-head').dataset.freshness === 'bus-down' \
             && document.querySelector('.drive-head .values').classList.contains('not-live')",
            LONG,
            "the drive page greyed",
        )
        .await;
        let banner = text(&page, ".last-seen").await;
        assert!(
            banner.starts_with("Bus line1 is down since ")
                && banner.contains("drivegate cannot reach this drive")
                && banner.contains("The values below are the last it sent")
                && banner.ends_with("they are not live."),
            "{banner}"
        );
        let why = text(&page, ".last-seen-why").await;
        assert!(why.starts_with("bus line1 is down: "), "{why}");
        assert!(why.contains("ttyUSB-line1") || why.contains("/dev/pts/"), "{why}");
        assert_eq!(text(&page, ".drive-head h1 .badge").await, "bus down");
        let speed = page
            .eval("(() => { const c = document.querySelector('[data-value=speed]'); return [c.textContent, getComputedStyle(c).fontStyle]; })()")
            .await;
        assert_eq!(speed, json!(["60 rpm", "italic"]));
        picture(&page, "console-drive-bus-down.png", false).await;

        // Plugged back: live again, nothing greyed.
        let _sim = ExternalSim::start(&link, "1-2", &[]).await;
        // The daemon first (the reopen waits for its backoff), then the
        // page: a failure says which of the two did not follow.
        super::harness::until(LONG, "the daemon's conveyor live again", || {
            daemon.plant.buses()[0]
                .handle
                .freshness(1)
                .is_some_and(|v| v.freshness.is_live())
        })
        .await;
        page.wait_for(
            "document.querySelector('.drive-head').dataset.freshness === 'live' \
             && !document.querySelector('.drive-head .values').classList.contains('not-live') \
             && document.querySelector('.last-seen').hidden",
            LONG,
            "the drive page live again",
        )
        .await;
        page.eval("location.hash = '#/'").await;
        summary(&page, "2 of 2 online").await;
        badge_is(&page, "connected", "conn open").await;
        page.wait_for(
            &format!("(() => {{ const u = {UTILISATION}; return u && !u[3] && u[0].endsWith(' %'); }})()"),
            LONG,
            "the utilisation again",
        )
        .await;
        assert_eq!(page.eval("window.ratesWhileDown").await, json!([]));
        let voltage = cell(&page, "belt", 7).await;
        assert_eq!(voltage[1], json!("normal"), "{voltage}");
        assert_clean(&page, &base);
        browser.stop().await;
        daemon.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_that_never_answered_at_the_wrong_baud_rate_says_to_check_the_rate() {
    bounded(std::time::Duration::from_secs(120), async {
        // The drives at 115200, the bus at 11520 (a digit lost): the
        // drives hear garbage and stay silent, as real ones do.
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyUSB-line1");
        let _sim = ExternalSim::start(&link, "1-2", &["--check-master-baud"]).await;
        let daemon = TestDaemon::start_no_wait(&config(&link, 11_520)).await;
        let browser = Browser::start(&[]).await;
        let base = daemon.url("");
        let page = open(&browser, &base, "/").await;
        summary(
            &page,
            "0 of 2 online: 2 never answered (check the bus's baud rate and the drives' unit addresses)",
        )
        .await;
        let state = cell(&page, "belt", 2).await;
        assert_eq!(state[0], json!("never answered"), "{state}");
        // The port is open, the page connected: the badge says the data is
        // not live all the same.
        badge_is(&page, "connected · 2 not live", "conn open not-live").await;
        page.wait_for(
            "(document.querySelector('tr[data-drive=belt] td:nth-of-type(2)').title || '').includes('11520 baud')",
            LONG,
            "the reason on the belt's row",
        )
        .await;
        let card = page
            .wait_for(
                "(() => { const c = document.querySelector('.bus[data-bus=line1]'); \
                 return c && c.textContent.includes('0 of 2') ? c.textContent : null; })()",
                LONG,
                "the bus's card",
            )
            .await;
        assert!(card.as_str().unwrap().contains("@ 11520"), "{card}");
        picture(&page, "console-never-overview.png", false).await;

        page.eval("location.hash = '#/drive/conveyor'").await;
        let banner = page
            .wait_for(
                "(() => { const p = document.querySelector('.last-seen'); \
                 return p && !p.hidden && p.textContent.includes('baud') ? p.textContent : null; })()",
                LONG,
                "the drive page's reason",
            )
            .await;
        let banner = banner.as_str().unwrap();
        for words in [
            "Never answered since bus line1 opened at ",
            " (the last poll: ",
            "check the baud rate (the bus runs at 11520 baud) and the unit address (1)",
            &format!("drivegate probe --port {} --try-bauds", link.display()),
        ] {
            assert!(banner.contains(words), "{words:?} not in {banner}");
        }
        assert_eq!(text(&page, ".drive-head h1 .badge").await, "never answered");
        assert_eq!(text(&page, "[data-value=speed]").await, "–");
        assert_eq!(text(&page, "[data-value=age]").await, "–");
        picture(&page, "console-drive-never.png", false).await;
        assert_clean(&page, &base);
        browser.stop().await;
        daemon.stop().await;
    })
    .await;
}
