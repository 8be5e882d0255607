//! A remote RS-485 line behind a serial device server (Moxa NPort,
//! USR-TCP232 and the like, in "TCP server" / raw socket mode): the bus's
//! `port` is `tcp://host:port` and the RTU frames travel as they are over
//! one TCP connection.
//!
//! The device server does the wire; the master still keeps one frame in
//! flight, its t3.5 silences, its timeouts and its guard, exactly as on a
//! local adapter. The connection is to the bus what the adapter is: when it
//! cannot be made or is lost, the bus is down and the scheduler reconnects
//! with the same backoff as for an unplugged adapter.
//!
//! Frames go out as soon as they are written (`TCP_NODELAY`), and a device
//! server that vanishes without closing the connection (powered off,
//! unplugged from the network) is noticed: keepalive probes on an idle
//! connection, and a limit on how long sent data may stay unacknowledged.

use std::io;
use std::time::Duration;

use socket2::{SockRef, TcpKeepalive};
use tokio::net::TcpStream;

/// The scheme of a serial device server's address in `port`.
pub const SCHEME: &str = "tcp://";

/// How long a connection attempt may take.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

/// Idle time before keepalive probes, and between them.
const KEEPALIVE: Duration = Duration::from_secs(5);
/// Longest time sent data may stay unacknowledged before the connection is
/// given up (TCP_USER_TIMEOUT).
const UNACKNOWLEDGED: Duration = Duration::from_secs(10);

/// Why a serial device server's connection could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The host name does not resolve, or to no address.
    #[error("cannot find the serial device server {address}: {source}")]
    Resolve {
        /// `host:port` as configured.
        address: String,
        /// What the resolver said.
        source: io::Error,
    },
    /// The connection was refused, timed out, or failed otherwise.
    #[error("cannot connect to the serial device server at {address}: {reason}")]
    Connect {
        /// `host:port` as configured.
        address: String,
        /// What happened, with a hint.
        reason: String,
    },
}

/// The `host:port` of a `tcp://host:port` port, checked; `None` for any
/// other port (a serial device, `sim`).
pub fn address(port: &str) -> Option<Result<&str, String>> {
    let rest = port.strip_prefix(SCHEME)?;
    Some(check_address(rest).map(|()| rest))
}

/// A `host:port` a serial device server can have, or why not.
fn check_address(address: &str) -> Result<(), String> {
    let hint = "write it as tcp://host:port, e.g. tcp://192.168.127.254:4001";
    let Some((host, port)) = address.rsplit_once(':') else {
        return Err(format!("tcp://{address} has no port number: {hint}"));
    };
    let host = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    if host.is_empty() || host.contains('/') || host.contains(char::is_whitespace) {
        return Err(format!("tcp://{address} has no valid host: {hint}"));
    }
    match port.parse::<u16>() {
        Ok(p) if p > 0 => Ok(()),
        _ => Err(format!(
            "tcp://{address}: port \"{port}\" is not a TCP port number (1 to 65535): {hint}"
        )),
    }
}

/// Connects to the device server at `address` (`host:port`), within
/// [`CONNECT_TIMEOUT`], and sets the connection up for RTU frames.
pub async fn connect(address: &str) -> Result<TcpStream, ConnectError> {
    let candidates: Vec<_> = tokio::net::lookup_host(address)
        .await
        .map_err(|source| ConnectError::Resolve {
            address: address.to_string(),
            source,
        })?
        .collect();
    if candidates.is_empty() {
        return Err(ConnectError::Resolve {
            address: address.to_string(),
            source: io::Error::new(io::ErrorKind::NotFound, "no address for that name"),
        });
    }
    let attempt = async {
        let mut last = None;
        for candidate in candidates {
            match TcpStream::connect(candidate).await {
                Ok(stream) => return Ok(stream),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| io::ErrorKind::NotFound.into()))
    };
    let failed = |reason: String| ConnectError::Connect {
        address: address.to_string(),
        reason,
    };
    let stream = match tokio::time::timeout(CONNECT_TIMEOUT, attempt).await {
        Ok(Ok(stream)) => stream,
        Ok(Err(e)) => return Err(failed(describe_connect_error(&e))),
        Err(_) => {
            return Err(failed(format!(
                "no answer within {} s (is it powered and reachable from here?)",
                CONNECT_TIMEOUT.as_secs()
            )));
        }
    };
    stream
        .set_nodelay(true)
        .map_err(|e| failed(e.to_string()))?;
    let socket = SockRef::from(&stream);
    let keepalive = TcpKeepalive::new()
        .with_time(KEEPALIVE)
        .with_interval(KEEPALIVE)
        .with_retries(3);
    // Best effort: without them a vanished server is only noticed by the
    // drives' timeouts.
    let _ = socket.set_tcp_keepalive(&keepalive);
    let _ = socket.set_tcp_user_timeout(Some(UNACKNOWLEDGED));
    Ok(stream)
}

/// A connection error in words that point at the likely cause.
fn describe_connect_error(e: &io::Error) -> String {
    match e.kind() {
        io::ErrorKind::ConnectionRefused => format!(
            "{e} (is the device server's port in TCP server mode, and not held by another client?)"
        ),
        io::ErrorKind::HostUnreachable | io::ErrorKind::NetworkUnreachable => {
            format!("{e} (check the address and the network route to it)")
        }
        _ => e.to_string(),
    }
}

/// The error for a connection the device server closed.
pub fn closed(address: &str) -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        format!("the serial device server at {address} closed the connection"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_are_checked_with_a_hint() {
        assert_eq!(address("/dev/ttyUSB0"), None);
        assert_eq!(address("sim"), None);
        assert_eq!(address("tcp://10.0.0.5:4001"), Some(Ok("10.0.0.5:4001")));
        assert_eq!(
            address("tcp://nport-3.plant:950"),
            Some(Ok("nport-3.plant:950"))
        );
        assert_eq!(address("tcp://[::1]:4001"), Some(Ok("[::1]:4001")));
        let no_port = address("tcp://10.0.0.5").unwrap().unwrap_err();
        assert!(no_port.contains("has no port number"), "{no_port}");
        assert!(no_port.contains("tcp://host:port"), "{no_port}");
        let bad_port = address("tcp://10.0.0.5:99999").unwrap().unwrap_err();
        assert!(bad_port.contains("1 to 65535"), "{bad_port}");
        assert!(address("tcp://:4001").unwrap().is_err());
        assert!(address("tcp://10.0.0.5:0").unwrap().is_err());
        assert!(address("tcp://a b:1").unwrap().is_err());
    }

    #[tokio::test]
    async fn a_refused_connection_says_what_to_check() {
        // A port nobody listens on: bind one, then free it.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap().to_string();
        drop(listener);
        let e = connect(&address).await.unwrap_err().to_string();
        assert!(
            e.starts_with(&format!(
                "cannot connect to the serial device server at {address}: "
            )),
            "{e}"
        );
        assert!(
            e.contains("refused") && e.contains("TCP server mode"),
            "{e}"
        );
    }

    #[tokio::test]
    async fn a_connection_is_set_up_for_frames() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let (stream, accepted) = tokio::join!(connect(&address), listener.accept());
        let stream = stream.unwrap();
        accepted.unwrap();
        assert!(stream.nodelay().unwrap());
        assert!(SockRef::from(&stream).keepalive().unwrap());
    }
}
