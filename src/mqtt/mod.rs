//! The MQTT face: the plant's drives on a broker as an Eclipse Sparkplug B
//! 3.0 edge node, for SCADA hosts that discover them without configuration.
//!
//! - [`topic`] names the topics and tells incoming ones apart (pure),
//! - [`metric`] is a drive as a Sparkplug device: its metrics, units and
//!   protobuf form (pure), over the types of [`sparkplug_b`] (generated
//!   from the vendored `proto/sparkplug_b.proto`, checked in),
//! - [`exception`] decides what of a new status is published (deadbands,
//!   pure), [`host`] follows the primary host's `STATE` (pure),
//! - [`commands`] turns DCMD metrics into requests for the control core,
//! - `arrival` tells a live command from a retained or queued one, for
//!   both formats (pure; the core refuses what is not live),
//! - `node` is the edge node's task: births and deaths, data, commands and
//!   the session's motor-safety lease, over a `connection` (rumqttc) with
//!   its `bd_seq` (kept across restarts in `[safety] state_dir`),
//! - `relay` carries the Sparkplug connection's bytes to the broker and
//!   `too_large` cuts the messages above `[mqtt] max_message_bytes` from
//!   what comes back (pure), so a large message costs itself, not the
//!   connection,
//! - [`store`] keeps on disk what cannot be published (store and forward:
//!   the node's [`Outbox`] when there is a state directory); [`replay`]
//!   holds what comes back out until its drive's DBIRTH is out (pure).
//!
//! With `format = "json"`, [`json`] publishes plain JSON instead (the
//! API's status, the stream's command messages, replies and events).
//!
//! Like every face it decides nothing about the motors: commands go to
//! [`crate::control`] as face `mqtt` with the role of `[mqtt] commands`, in
//! a session whose communication-loss function holds their leases, named
//! by what is known of their sender ([`identity`]: the broker's login, the
//! primary host claimed). See `docs/mqtt.md` and `docs/security.md`.

mod arrival;
mod bd_seq;
mod connection;
pub mod exception;
pub mod host;
pub mod identity;
pub mod json;
pub mod metric;
pub mod metric_commands;
mod node;
mod outbox;
mod relay;
pub mod replay;
pub mod store;
#[rustfmt::skip]
pub mod sparkplug_b;
mod too_large;
pub mod topic;

use crate::faces_shared::start::FaceStart;
use std::sync::Arc;

use tokio::task::JoinHandle;

use crate::config::MqttConfig;
use crate::config::mqtt::Format;
pub use outbox::{Discard, Outbox};

/// The node id of `config`: its `node_id`, else the host's name (with any
/// character a topic level cannot hold replaced by `-`).
pub fn node_id(config: &MqttConfig) -> String {
    if let Some(id) = &config.node_id {
        return id.clone();
    }
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_default();
    let id: String = host
        .chars()
        .map(|c| {
            if matches!(c, '/' | '+' | '#') || c.is_control() {
                '-'
            } else {
                c
            }
        })
        .collect();
    if id.is_empty() {
        "drivegate".to_string()
    } else {
        id
    }
}

/// Starts the MQTT face of `config` (if it has an `[mqtt]` section): it
/// connects, and reconnects, on its own, and stops when `shutdown` fires
/// (after its NDEATH). `outbox` keeps what cannot be published meanwhile.
pub(crate) fn start(
    start: FaceStart,
    outbox: Box<dyn Outbox>,
) -> Result<Option<JoinHandle<()>>, String> {
    let FaceStart {
        config,
        control,
        metrics,
        stop: shutdown,
        ..
    } = start;
    let config = &*config;
    let Some(section) = config.mqtt.clone() else {
        return Ok(None);
    };
    let node_id = node_id(&section);
    // Who commands come from, as far as known, and their role: the core's.
    let login = identity::login(&section);
    let primary_host = match section.format {
        Format::Json => None,
        _ => section.primary_host_id.as_deref(),
    };
    let identity = crate::control::identity::identify(
        config,
        crate::control::Face::Mqtt,
        crate::control::identity::Credential::Broker {
            login: &login,
            primary_host,
        },
    )?;
    if section.format == Format::Json {
        if section.primary_host_id.is_some() {
            tracing::warn!(
                "[mqtt] primary_host_id is Sparkplug's: the JSON format does not follow a primary host"
            );
        }
        return Ok(Some(json::node::spawn(
            Arc::new(section),
            identity,
            node_id,
            control,
            metrics,
            shutdown,
        )));
    }
    Ok(Some(node::spawn(
        Arc::new(section),
        identity,
        node_id,
        control,
        metrics,
        outbox,
        config.safety.state_dir(),
        shutdown,
    )))
}
