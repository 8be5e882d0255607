//! Where each face listens: the address its section names (the API on
//! loopback without a token), the socket bound with an error a plant
//! engineer can act on, and whether two addresses can be held at once.

use std::net::SocketAddr;

use tokio::net::TcpListener;

use crate::config::Config;
use crate::config::diff::Face;

/// Where `face` is to listen with `config`, if at all. Without a token the
/// API listens on the loopback address of the same port, whatever `listen`
/// says (`api::listener::bind_address`).
pub(super) fn bind_address(face: Face, config: &Config) -> Option<SocketAddr> {
    match face {
        Face::Http => Some(crate::api::listener::bind_address(
            config.http.listen,
            !config.http.tokens.is_empty(),
        )),
        Face::ModbusTcp => config
            .modbus_tcp
            .enabled
            .then_some(config.modbus_tcp.listen),
        Face::ModbusTls => config.modbus_tcp.tls.as_ref().map(|t| t.listen),
        Face::OpcUa => config.opcua.as_ref().map(|o| o.listen),
        Face::Mqtt => None,
    }
}

/// Binds `address` for `face`; the error says where and why.
pub(super) async fn bind(face: Face, address: SocketAddr) -> Result<TcpListener, String> {
    TcpListener::bind(address).await.map_err(|e| {
        let hint = if address.port() < 1024 && e.kind() == std::io::ErrorKind::PermissionDenied {
            " (ports below 1024 need CAP_NET_BIND_SERVICE: see docs/modbus-tcp.md)"
        } else {
            ""
        };
        format!(
            "cannot listen for {} on {address}: {e}{hint}",
            protocol(face)
        )
    })
}

/// What `face` serves, in the log's words ("HTTP API listening").
pub(super) fn protocol(face: Face) -> &'static str {
    match face {
        Face::Http => "HTTP API",
        Face::ModbusTcp => "Modbus TCP",
        Face::ModbusTls => "Modbus/TCP Security",
        Face::OpcUa => "OPC UA",
        Face::Mqtt => "MQTT",
    }
}

/// True when a socket listening on `a` keeps another from listening on
/// `b` (the same port, and the same or a wildcard address).
pub(super) fn overlaps(a: SocketAddr, b: SocketAddr) -> bool {
    a.port() == b.port()
        && a.port() != 0
        && (a.ip() == b.ip() || a.ip().is_unspecified() || b.ip().is_unspecified())
}

#[cfg(test)]
mod tests {
    use super::overlaps;

    #[test]
    fn the_wildcard_overlaps_every_address_of_its_port() {
        let a = |s: &str| s.parse().unwrap_or_else(|e| panic!("{s}: {e}"));
        assert!(overlaps(a("0.0.0.0:502"), a("192.168.1.5:502")));
        assert!(overlaps(a("192.168.1.5:502"), a("[::]:502")));
        assert!(overlaps(a("127.0.0.1:502"), a("127.0.0.1:502")));
        assert!(!overlaps(a("127.0.0.1:502"), a("192.168.1.5:502")));
        assert!(!overlaps(a("0.0.0.0:502"), a("0.0.0.0:5020")));
        assert!(!overlaps(a("0.0.0.0:0"), a("127.0.0.1:0")));
    }
}
