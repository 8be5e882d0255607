//! The MQTT face against Debian's mosquitto on a loopback port, with a
//! Sparkplug B host in the test (`support::sparkplug`, decoding with the
//! daemon's own types of the vendored `.proto`) and, once, the
//! third-party `pysparkplug`: births and bdSeq, rebirth, DDATA by
//! exception, commands through the control core and their refusals, the
//! motor-safety lease of MQTT's commands, the NDEATH of a killed daemon,
//! TLS with the broker's CA, and who may command: a password file and the
//! ACL of `docs/security.md` (`acl.rs`); and the adapter unplugged under a
//! daemon with every face on, each face timed showing it (`wire_gone`).

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod acl;
mod births;
mod commands;
mod convergence;
mod death;
mod json;
mod live;
mod oversized;
mod python;
mod reload;
mod safety;
mod store;
mod tls;
mod wire_gone;

use crate::support::config::ConfigBuilder;

/// The Sparkplug group and node of the tests' daemons.
pub const GROUP: &str = "plant";
/// The node id.
pub const NODE: &str = "gw1";

/// The plant of four simulated drives with `[mqtt]` on `broker` (group
/// [`GROUP`], node [`NODE`]) and `keys`.
pub fn config(broker: &str, keys: &str) -> String {
    ConfigBuilder::four_drives()
        .modbus_tcp_off()
        .section(
            "mqtt",
            &format!("broker = \"{broker}\"\ngroup_id = \"{GROUP}\"\nnode_id = \"{NODE}\"\n{keys}"),
        )
        .toml()
}
