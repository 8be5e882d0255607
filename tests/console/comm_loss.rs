//! The console's event log shows the end of a Modbus TCP client's
//! communication-loss lease in words: whose it was (the client's address),
//! why it ended, what the stop did, and the stop's own write; and a lease
//! a brake ended, with no stop.

use std::time::Duration;

use super::harness::cdp::Browser;
use super::harness::{ADMIN, config};
use crate::support::TestDaemon;
use crate::support::api::Api;
use crate::support::modbus_tcp::{Raw, write};

const LONG: Duration = Duration::from_secs(60);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_event_log_says_why_a_plcs_motor_was_stopped() {
    let daemon = TestDaemon::start(&config(
        true,
        "[[modbus_tcp.clients]]\nnetwork = \"127.0.0.1/32\"\nrole = \"operator\"\ncomm_loss_ms = 500\n",
    ))
    .await;
    let browser = Browser::start(&[]).await;
    let page = browser.new_page(1280, 900).await;
    page.goto(&format!("{}/#/events", daemon.url(""))).await;
    page.wait_for(
        "document.getElementById('login').open",
        LONG,
        "the token dialog",
    )
    .await;
    page.fill("#login input", ADMIN).await;
    page.click("#login button[type=submit]").await;
    page.wait_for(
        "window.drivegate && drivegate.stream.state === 'open' && drivegate.store.order.length === 4",
        LONG,
        "the console live",
    )
    .await;

    // A PLC sets the conveyor turning, then closes its connection.
    let mut plc = Raw::connect(daemon.modbus_tcp.unwrap()).await;
    let owner = format!("modbus-tcp {}", plc.stream.local_addr().unwrap());
    for (register, value) in [(0x0002, 0x0000), (0x0002, 0x000A), (0x0006, 300)] {
        let pdu = write(register, value);
        assert_eq!(plc.ask(1, &pdu).await, pdu);
    }
    drop(plc);

    let row = page
        .wait_for(
            "(() => { const r = document.querySelector('table.log tbody tr[data-kind=lease]'); return r && r.textContent; })()",
            LONG,
            "the lease's end in the log",
        )
        .await;
    let row = row.as_str().unwrap();
    assert!(
        row.contains("conveyor")
            && row.contains(&format!(
                "lease of {owner} ended (its Modbus TCP connection closed)"
            ))
            && row.contains("zero-speed: confirmed by the drive"),
        "{row}"
    );
    let stop = page
        .wait_for(
            &format!(
                "(() => {{ const r = [...document.querySelectorAll('table.log tbody tr[data-kind=write]')].find((r) => r.textContent.includes('lease-expiry ({owner})')); return r && r.textContent; }})()"
            ),
            LONG,
            "the stop's write in the log",
        )
        .await;
    assert!(
        stop.as_str().unwrap().contains("speed setpoint 0 rpm")
            && stop.as_str().unwrap().contains("confirmed by the drive"),
        "{stop}"
    );

    // Another PLC's lease ended by a brake from the panel: no stop, and
    // the log says so.
    let mut plc = Raw::connect(daemon.modbus_tcp.unwrap()).await;
    let owner = format!("modbus-tcp {}", plc.stream.local_addr().unwrap());
    let pdu = write(0x0006, 200);
    assert_eq!(plc.ask(1, &pdu).await, pdu);
    Api::new(daemon.http, Some(ADMIN))
        .command("conveyor", "brake")
        .await;
    let ended = page
        .wait_for(
            &format!(
                "(() => {{ const r = [...document.querySelectorAll('table.log tbody tr[data-kind=lease]')].find((r) => r.textContent.includes('{owner} ended without a stop')); return r && r.textContent; }})()"
            ),
            LONG,
            "the lease ended by the brake in the log",
        )
        .await;
    assert!(
        ended
            .as_str()
            .unwrap()
            .contains("(the brake from commissioning over HTTP was confirmed)"),
        "{ended}"
    );
    drop(plc);
    browser.stop().await;
    daemon.stop().await;
}
