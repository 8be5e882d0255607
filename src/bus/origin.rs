//! Who caused a bus job: carried with every job to the wire, so the bus
//! monitor can say for each frame which client (or which part of the daemon)
//! put it there, and the scope can trigger on a write from any face.
//!
//! The faces set it when they submit; the poller, the scope and the safe
//! stops set their own. It is a label, not a permission: it never changes
//! how a job is queued or run.

use std::fmt;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use crate::listed::listed_enum;

/// The cause of one bus job.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Origin {
    /// The daemon itself, for work no client asked for (tests, tools).
    #[default]
    Internal,
    /// The background status poll.
    Poller,
    /// A status poll the scope asked for (a captured drive, at full rate).
    Scope,
    /// A REST request: the token's name (or the client's address when no
    /// tokens are configured).
    Http {
        /// Token name or client address.
        who: Arc<str>,
    },
    /// A command sent on a WebSocket stream.
    WebSocket {
        /// The stream session's number.
        session: u64,
        /// Token name or client address.
        who: Arc<str>,
    },
    /// A Modbus TCP request (the client's address is kept as address and
    /// port, which keeps every job small).
    ModbusTcp {
        /// The client's IP address.
        ip: IpAddr,
        /// The client's port.
        port: u16,
        /// The request's MBAP transaction id.
        transaction: u16,
        /// The client's name, when it has one: the CN of its certificate
        /// (Modbus/TCP Security). A thin pointer, so jobs stay small.
        name: Option<Arc<String>>,
    },
    /// A command from the MQTT face (a Sparkplug DCMD, a JSON command):
    /// what is known of its sender.
    Mqtt {
        /// How the broker knows drivegate's connection and the primary
        /// host claimed (`broker user gw1; primary host "scada" claimed`).
        who: Arc<str>,
    },
    /// A write or method call of an OPC UA session: its user and the
    /// client's address (`alice (10.0.0.5:50412)`).
    OpcUa {
        /// Who: the session's user and its client's address.
        who: Arc<str>,
    },
    /// The stop sent when a motor-safety lease ended.
    LeaseExpiry {
        /// Who held the lease.
        owner: Arc<str>,
    },
    /// The safe stop at shutdown.
    Shutdown,
}

listed_enum! {
    /// What kind of cause an [`Origin`] is, without its details.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum OriginKind {
        /// [`Origin::Internal`].
        Internal,
        /// [`Origin::Poller`].
        Poller,
        /// [`Origin::Scope`].
        Scope,
        /// [`Origin::Http`].
        Http,
        /// [`Origin::WebSocket`].
        WebSocket,
        /// [`Origin::ModbusTcp`].
        ModbusTcp,
        /// [`Origin::Mqtt`].
        Mqtt,
        /// [`Origin::OpcUa`].
        OpcUa,
        /// [`Origin::LeaseExpiry`].
        LeaseExpiry,
        /// [`Origin::Shutdown`].
        Shutdown,
    }
}

impl OriginKind {
    /// Stable name, for filters, metrics and documentation.
    pub const fn name(self) -> &'static str {
        match self {
            OriginKind::Internal => "internal",
            OriginKind::Poller => "poller",
            OriginKind::Scope => "scope",
            OriginKind::Http => "http",
            OriginKind::WebSocket => "websocket",
            OriginKind::ModbusTcp => "modbus-tcp",
            OriginKind::Mqtt => "mqtt",
            OriginKind::OpcUa => "opcua",
            OriginKind::LeaseExpiry => "lease-expiry",
            OriginKind::Shutdown => "shutdown",
        }
    }
}

/// Every origin kind's name, for filters, metrics and documentation: made
/// from [`OriginKind::ALL`], so none can be missing.
pub const KINDS: [&str; OriginKind::ALL.len()] = {
    let mut names = [""; OriginKind::ALL.len()];
    let mut i = 0;
    while i < names.len() {
        names[i] = OriginKind::ALL[i].name();
        i += 1;
    }
    names
};

impl Origin {
    /// A Modbus TCP request from `peer` with MBAP transaction id `transaction`.
    pub fn modbus_tcp(peer: SocketAddr, transaction: u16) -> Self {
        Origin::ModbusTcp {
            ip: peer.ip(),
            port: peer.port(),
            transaction,
            name: None,
        }
    }

    /// A Modbus TCP request from the client `name` (its certificate's CN)
    /// at `peer`.
    pub fn modbus_tcp_named(peer: SocketAddr, name: Option<Arc<String>>, transaction: u16) -> Self {
        Origin::ModbusTcp {
            ip: peer.ip(),
            port: peer.port(),
            transaction,
            name,
        }
    }

    /// Stable kind name (`poller`, `http`, `modbus-tcp`, ...), one of [`KINDS`].
    pub fn kind(&self) -> &'static str {
        self.origin_kind().name()
    }

    /// Its kind, without the details.
    pub fn origin_kind(&self) -> OriginKind {
        match self {
            Origin::Internal => OriginKind::Internal,
            Origin::Poller => OriginKind::Poller,
            Origin::Scope => OriginKind::Scope,
            Origin::Http { .. } => OriginKind::Http,
            Origin::WebSocket { .. } => OriginKind::WebSocket,
            Origin::ModbusTcp { .. } => OriginKind::ModbusTcp,
            Origin::Mqtt { .. } => OriginKind::Mqtt,
            Origin::OpcUa { .. } => OriginKind::OpcUa,
            Origin::LeaseExpiry { .. } => OriginKind::LeaseExpiry,
            Origin::Shutdown => OriginKind::Shutdown,
        }
    }

    /// The client behind it, if any: a token name, a client address, a
    /// Modbus TCP peer, a lease's owner.
    pub fn who(&self) -> Option<String> {
        match self {
            Origin::Http { who }
            | Origin::WebSocket { who, .. }
            | Origin::Mqtt { who }
            | Origin::OpcUa { who } => Some(who.to_string()),
            Origin::ModbusTcp {
                ip,
                port,
                name: None,
                ..
            } => Some(SocketAddr::new(*ip, *port).to_string()),
            Origin::ModbusTcp {
                ip,
                port,
                name: Some(name),
                ..
            } => Some(format!("{name} ({})", SocketAddr::new(*ip, *port))),
            Origin::LeaseExpiry { owner } => Some(owner.to_string()),
            _ => None,
        }
    }

    /// The WebSocket session or Modbus TCP transaction id, if any.
    pub fn reference(&self) -> Option<u64> {
        match self {
            Origin::WebSocket { session, .. } => Some(*session),
            Origin::ModbusTcp { transaction, .. } => Some(u64::from(*transaction)),
            _ => None,
        }
    }

    /// True for work the daemon does on its own schedule (polls), as
    /// opposed to something a client or a safety rule asked for.
    pub fn is_background(&self) -> bool {
        matches!(self, Origin::Poller | Origin::Scope)
    }
}

impl fmt::Display for Origin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Origin::Internal => f.write_str("drivegate"),
            Origin::Poller => f.write_str("poller"),
            Origin::Scope => f.write_str("scope"),
            Origin::Http { who } => write!(f, "HTTP {who}"),
            Origin::WebSocket { session, who } => write!(f, "WebSocket {who} (session {session})"),
            Origin::ModbusTcp {
                ip,
                port,
                transaction,
                name,
            } => match name {
                None => write!(
                    f,
                    "Modbus TCP {} (transaction {transaction})",
                    SocketAddr::new(*ip, *port)
                ),
                Some(name) => write!(
                    f,
                    "Modbus TCP {name} ({}) (transaction {transaction})",
                    SocketAddr::new(*ip, *port)
                ),
            },
            Origin::Mqtt { who } => write!(f, "MQTT {who}"),
            Origin::OpcUa { who } => write!(f, "OPC UA {who}"),
            Origin::LeaseExpiry { owner } => write!(f, "lease expiry ({owner}'s lease)"),
            Origin::Shutdown => f.write_str("shutdown"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_and_texts() {
        let tcp = Origin::modbus_tcp("127.0.0.1:50211".parse().unwrap(), 17);
        assert_eq!(tcp.kind(), "modbus-tcp");
        assert_eq!(tcp.who().as_deref(), Some("127.0.0.1:50211"));
        assert_eq!(tcp.reference(), Some(17));
        assert_eq!(
            tcp.to_string(),
            "Modbus TCP 127.0.0.1:50211 (transaction 17)"
        );
        let http = Origin::Http {
            who: "scada".into(),
        };
        assert_eq!(http.to_string(), "HTTP scada");
        assert!(Origin::Poller.is_background() && !http.is_background());
        for o in [
            Origin::Internal,
            Origin::Poller,
            Origin::Scope,
            http,
            Origin::WebSocket {
                session: 3,
                who: "a".into(),
            },
            tcp,
            Origin::Mqtt {
                who: "scada".into(),
            },
            Origin::LeaseExpiry { owner: "a".into() },
            Origin::Shutdown,
        ] {
            assert!(KINDS.contains(&o.kind()), "{o:?}");
        }
        assert_eq!(KINDS[0], "internal");
        assert_eq!(KINDS[KINDS.len() - 1], "shutdown");
    }
}
