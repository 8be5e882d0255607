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
//!   refusals to exceptions,
//! - [`connection`] serves one client in order, [`server`] accepts them,
//!   [`access`] checks where they come from and gives them their role.
//!
//! `docs/modbus-tcp.md` says why the MBAP framing is the daemon's own
//! rather than tokio-modbus's server.

pub mod access;
pub mod connection;
pub mod gateway;
pub mod mbap;
pub mod outcome;
pub mod polled_copy;
pub mod request;
pub mod routing;
pub mod server;

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::control::Control;
use crate::metrics::Metrics;
use crate::plant::Plant;

use access::{Access, SharedAccess};
use connection::ConnectionSettings;
use gateway::Gateway;
use server::ServerSettings;

/// Binds the Modbus TCP listener and serves it until `shutdown` fires.
/// Returns the bound address and the task serving it.
pub async fn start(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    control: Control,
    shutdown: CancellationToken,
) -> Result<(SocketAddr, JoinHandle<()>), String> {
    let tcp = &config.modbus_tcp;
    let listener = tokio::net::TcpListener::bind(tcp.listen)
        .await
        .map_err(|e| {
            let hint =
                if tcp.listen.port() < 1024 && e.kind() == std::io::ErrorKind::PermissionDenied {
                    " (ports below 1024 need CAP_NET_BIND_SERVICE: see docs/modbus-tcp.md)"
                } else {
                    ""
                };
            format!("cannot listen for Modbus TCP on {}: {e}{hint}", tcp.listen)
        })?;
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    let gateway = Arc::new(Gateway::new(tcp, plant, control.clone(), metrics));
    let settings = ServerSettings {
        access: SharedAccess::new(Access::from_config(tcp), &control),
        max_connections: tcp.max_connections,
        connection: ConnectionSettings {
            idle_timeout: tcp.idle_timeout(),
            max_pipelined: tcp.max_pipelined,
        },
    };
    let task = tokio::spawn(server::run(listener, gateway, settings, shutdown));
    Ok((addr, task))
}

/// Binds the Modbus/TCP Security listener of `[modbus_tcp.tls]` (if any)
/// and serves it until `shutdown` fires; its certificate is reloaded on
/// SIGHUP.
pub async fn start_tls(
    config: &Config,
    plant: Arc<Plant>,
    metrics: Arc<Metrics>,
    control: Control,
    shutdown: CancellationToken,
) -> Result<Option<(SocketAddr, JoinHandle<()>)>, String> {
    let tcp = &config.modbus_tcp;
    let Some(section) = tcp.tls.clone() else {
        return Ok(None);
    };
    let reloadable =
        crate::tls::Reloadable::load(section.files(), crate::tls::ClientAuth::Required, &[])
            .map(Arc::new)
            .map_err(|e| format!("[modbus_tcp.tls]: {e}"))?;
    let listener = tokio::net::TcpListener::bind(section.listen)
        .await
        .map_err(|e| {
            let hint = if section.listen.port() < 1024
                && e.kind() == std::io::ErrorKind::PermissionDenied
            {
                " (ports below 1024 need CAP_NET_BIND_SERVICE: see docs/modbus-tcp.md)"
            } else {
                ""
            };
            format!(
                "cannot listen for Modbus/TCP Security on {}: {e}{hint}",
                section.listen
            )
        })?;
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
        access: SharedAccess::new(Access::from_config(tcp), &control),
        max_connections: tcp.max_connections,
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
    Ok(Some((addr, task)))
}
