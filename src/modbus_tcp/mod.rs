//! The Modbus TCP passthrough face for SCADA and PLCs.
//!
//! A request's unit id picks a bus and a drive ([`routing`]); the PDU goes to
//! that bus's queue as a command from the connection's own source, and the
//! drive's reply PDU, exception replies included, goes back unchanged with
//! the client's transaction id. Register addresses are the drive's own.
//!
//! - [`mbap`] is the frame codec (pure),
//! - [`request`] the Modbus rules the gateway applies before the bus,
//! - [`routing`] the unit map, [`polled_copy`] status reads from the cache,
//! - [`gateway`] passes reads to the bus and hands writes to the control
//!   core ([`crate::control`]), which decides on them as for every face,
//! - [`outcome`] names outcomes and maps bus failures and the core's
//!   refusals to exceptions, [`pending`] turns what the bus and the core
//!   did into the reply,
//! - [`connection`] serves one client in order, [`server`] accepts them,
//!   [`access`] checks where they come from and gives them their role,
//!   [`refusals`] says when a stranger's refusal is logged; how many
//!   connections each address may hold is the budget's
//!   ([`crate::connections`]), as on every listener.
//!
//! `docs/modbus-tcp.md` says why the MBAP framing is the daemon's own
//! rather than tokio-modbus's server.

pub mod access;
pub mod arrivals;
pub mod connection;
pub mod gateway;
pub mod mbap;
pub mod outcome;
pub mod pending;
pub mod polled_copy;
pub mod refusals;
pub mod request;
pub mod routing;
pub mod server;

use crate::faces_shared::start::FaceStart;
use std::net::SocketAddr;
use std::sync::Arc;

use tokio::task::JoinHandle;

use access::SharedAccess;
use connection::ConnectionSettings;
use gateway::Gateway;
use server::ServerSettings;

/// Serves Modbus TCP on `listener` (bound by the caller at `[modbus_tcp]
/// listen`) until `shutdown` fires. Returns the bound address and the task
/// serving it.
pub(crate) fn start(
    start: FaceStart,
    listener: tokio::net::TcpListener,
) -> Result<(SocketAddr, JoinHandle<()>), String> {
    let FaceStart {
        config,
        plant,
        control,
        metrics,
        stop: shutdown,
        ..
    } = start;
    let running = config.clone();
    let config = &*config;
    let tcp = &config.modbus_tcp;
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    // Said at every start: a plain admin network, a listener on the plant
    // network that admits loopback only since allowed_networks is unset.
    for (warning, text) in tcp.notices(addr) {
        if warning {
            tracing::warn!("{text}");
        } else {
            tracing::info!("{text}");
        }
    }
    let gateway = Arc::new(Gateway::new(tcp, plant, control.clone(), metrics));
    let settings = ServerSettings {
        access: SharedAccess::new(running, &control),
        max_connections: tcp.max_connections.map(|n| n.0),
        max_connections_per_address: tcp.per_address_limit(),
        connection: ConnectionSettings {
            idle_timeout: tcp.idle_timeout(),
            max_pipelined: tcp.max_pipelined,
        },
    };
    let task = tokio::spawn(server::run(listener, gateway, settings, shutdown));
    Ok((addr, task))
}

/// Serves Modbus/TCP Security on `listener` (bound by the caller at
/// `[modbus_tcp.tls] listen`) until `shutdown` fires; its certificate is
/// reloaded on SIGHUP. Refused without a `[modbus_tcp.tls]` section.
pub(crate) fn start_tls(
    start: FaceStart,
    listener: tokio::net::TcpListener,
) -> Result<(SocketAddr, JoinHandle<()>), String> {
    let FaceStart {
        config,
        plant,
        control,
        metrics,
        stop: shutdown,
        ..
    } = start;
    let running = config.clone();
    let config = &*config;
    let tcp = &config.modbus_tcp;
    let Some(section) = tcp.tls.clone() else {
        return Err("no [modbus_tcp.tls] section".to_string());
    };
    let reloadable =
        crate::tls::Reloadable::load(section.files(), crate::tls::ClientAuth::Required, &[])
            .map(Arc::new)
            .map_err(|e| format!("[modbus_tcp.tls]: {e}"))?;
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    let counter = metrics.clone();
    crate::tls::reload_on_hangup(
        reloadable.clone(),
        "modbus_tcp",
        move |ok| counter.security().tls_reload("modbus_tcp", ok),
        shutdown.clone(),
    )
    .map_err(|e| format!("cannot watch for SIGHUP (certificate reloads): {e}"))?;
    let gateway = Arc::new(Gateway::new(tcp, plant, control.clone(), metrics));
    let settings = ServerSettings {
        access: SharedAccess::new(running, &control),
        max_connections: tcp.max_connections.map(|n| n.0),
        max_connections_per_address: tcp.per_address_limit(),
        connection: ConnectionSettings {
            idle_timeout: tcp.idle_timeout(),
            max_pipelined: tcp.max_pipelined,
        },
    };
    let tls = server::TlsSettings {
        config: reloadable,
        section,
        read_only: tcp.read_only,
    };
    let task = tokio::spawn(server::run_tls(listener, gateway, settings, tls, shutdown));
    Ok((addr, task))
}
