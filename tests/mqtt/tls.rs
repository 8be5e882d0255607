//! The broker over TLS, trusted by its CA (certificates made by openssl),
//! in both formats.

use std::time::Duration;

use super::config;
use crate::support::certs::Pki;
use crate::support::mosquitto::{Mosquitto, Sub};
use crate::support::sparkplug::Host;
use crate::support::{TestDaemon, bounded, eventually};

const WAIT: Duration = Duration::from_secs(20);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn births_over_tls_with_the_brokers_ca() {
    bounded(Duration::from_secs(60), async {
        let pki = Pki::new();
        let broker = Mosquitto::start_tls(&pki);
        // The host on the plain listener, the daemon on the TLS one.
        let mut host = Host::connect(broker.port, "tls-host", None).await;
        let ca = pki.path("ca.pem");
        let d = TestDaemon::start(&config(
            &broker.tls_url(),
            &format!("ca = \"{}\"", ca.display()),
        ))
        .await;
        host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
        d.stop().await;
    })
    .await;
}

/// The JSON format's MQTT 5 connection over TLS: its retained state
/// `online` reaches a client of the plain listener.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_json_format_over_tls_with_the_brokers_ca() {
    bounded(Duration::from_secs(60), async {
        let pki = Pki::new();
        let broker = Mosquitto::start_tls(&pki);
        let state = format!("drivegate/{}/state", super::NODE);
        let mut sub = Sub::start(broker.port, &[&state]);
        let ca = pki.path("ca.pem");
        let d = TestDaemon::start(&config(
            &broker.tls_url(),
            &format!("format = \"json\"\nca = \"{}\"", ca.display()),
        ))
        .await;
        sub.next(WAIT, "the state online over TLS", |m| {
            m.topic == state && m.payload == "online"
        })
        .await;
        assert!(d.metrics.mqtt().link().connected);
        sub.stop().await;
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broker_signed_by_another_ca_is_refused() {
    bounded(Duration::from_secs(60), async {
        let pki = Pki::new();
        pki.ca("other");
        let broker = Mosquitto::start_tls(&pki);
        let other = pki.path("other.pem");
        let d = TestDaemon::start(&config(
            &broker.tls_url(),
            &format!("ca = \"{}\"", other.display()),
        ))
        .await;
        let why = eventually(WAIT, "a TLS error", || d.metrics.mqtt().link().last_error)
            .await
            .1;
        assert!(why.contains("TLS"), "{why}");
        assert!(!d.metrics.mqtt().link().connected);
        // /readyz says what is wrong, without making the daemon unready.
        let ready: serde_json::Value = reqwest::get(d.url("/readyz"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        assert_eq!(ready["mqtt"]["connected"], false, "{ready:#}");
        assert!(
            ready["mqtt"]["last_error"]
                .as_str()
                .unwrap()
                .contains("TLS"),
            "{ready:#}"
        );
        assert_eq!(ready["ready"], true, "{ready:#}");
        d.stop().await;
    })
    .await;
}
