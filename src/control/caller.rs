//! Who asks: the face a request came through, who is behind it (for the
//! audit log and lease owners), with which role, whose turn on the bus it
//! takes, and the session (if any) whose closing ends its leases.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use super::policy::Role;
use crate::bus::{Origin, SourceId};

/// The way a request came in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Face {
    /// The REST API.
    Http,
    /// A command on the WebSocket stream.
    WebSocket,
    /// A Modbus TCP client.
    ModbusTcp,
    /// A command from the MQTT broker (a Sparkplug DCMD).
    Mqtt,
    /// A write or method call of an OPC UA session.
    OpcUa,
    /// drivegate itself (safe stops, a brake applied again).
    Internal,
}

impl Face {
    /// Stable name for the audit log and events.
    pub fn name(self) -> &'static str {
        match self {
            Face::Http => "http",
            Face::WebSocket => "websocket",
            Face::ModbusTcp => "modbus-tcp",
            Face::Mqtt => "mqtt",
            Face::OpcUa => "opcua",
            Face::Internal => "internal",
        }
    }

    /// In words, for messages ("over Modbus TCP").
    pub fn words(self) -> &'static str {
        match self {
            Face::Http => "over HTTP",
            Face::WebSocket => "over the WebSocket stream",
            Face::ModbusTcp => "over Modbus TCP",
            Face::Mqtt => "over MQTT",
            Face::OpcUa => "over OPC UA",
            Face::Internal => "by drivegate",
        }
    }
}

/// A connection that can hold leases: they end when it closes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SessionId(pub u64);

static NEXT_SESSION: AtomicU64 = AtomicU64::new(1);

impl SessionId {
    /// A new, never used session id.
    pub fn new_unique() -> SessionId {
        SessionId(NEXT_SESSION.fetch_add(1, Ordering::Relaxed))
    }
}

/// The bus monitor's cause of a caller's frames on `face`. A Modbus TCP
/// client's is set per request by its face (peer and transaction id).
fn origin_of(face: Face, who: &Arc<str>, session: Option<SessionId>) -> Origin {
    match (face, session) {
        (Face::Http, _) => Origin::Http { who: who.clone() },
        (Face::WebSocket, Some(session)) => Origin::WebSocket {
            session: session.0,
            who: who.clone(),
        },
        (Face::WebSocket, None) => Origin::Http { who: who.clone() },
        (Face::Mqtt, _) => Origin::Mqtt { who: who.clone() },
        (Face::OpcUa, _) => Origin::OpcUa { who: who.clone() },
        (Face::ModbusTcp | Face::Internal, _) => Origin::Internal,
    }
}

/// Who is asking, with what rights.
#[derive(Debug, Clone)]
pub struct Caller {
    /// The face it came through.
    pub face: Face,
    /// Token name or client address: written to the audit log with every
    /// write, and shown as a lease's owner.
    pub who: Arc<str>,
    /// What it may do.
    pub role: Role,
    /// Its share of the bus queues, so one busy client cannot starve the
    /// others.
    pub source: SourceId,
    /// The session its leases are tied to, if any.
    pub session: Option<SessionId>,
    /// What the bus monitor shows as the cause of this caller's frames:
    /// derived from the face and who, refined by a face that knows more
    /// (a Modbus TCP request's transaction id).
    pub origin: Origin,
}

impl Caller {
    /// A caller on `face` without a session.
    pub fn new(face: Face, who: impl Into<Arc<str>>, role: Role, source: SourceId) -> Self {
        let who = who.into();
        Caller {
            origin: origin_of(face, &who, None),
            face,
            who,
            role,
            source,
            session: None,
        }
    }

    /// The same caller within `session`, on `face`.
    pub fn in_session(&self, face: Face, session: SessionId) -> Self {
        Caller {
            face,
            session: Some(session),
            origin: origin_of(face, &self.who, Some(session)),
            ..self.clone()
        }
    }

    /// The same caller, its frames shown as caused by `origin`.
    pub fn with_origin(&self, origin: Origin) -> Self {
        Caller {
            origin,
            ..self.clone()
        }
    }

    /// drivegate itself.
    pub fn internal(who: &str) -> Self {
        Caller::new(Face::Internal, who, Role::Admin, SourceId::INTERNAL)
    }

    /// Who holds a lease this caller takes, as lease views and the stream
    /// show it: a token's name, or for a Modbus TCP client its face and
    /// address ("modbus-tcp 10.1.2.3:50412"), since an address alone does
    /// not say what it is (and for MQTT, "mqtt" and the host: "mqtt scada";
    /// for OPC UA the user and the client's address: "opcua alice
    /// (10.0.0.5:50412)").
    pub fn owner(&self) -> Arc<str> {
        match self.face {
            Face::ModbusTcp | Face::Mqtt | Face::OpcUa => {
                format!("{} {}", self.face.name(), self.who).into()
            }
            Face::Http | Face::WebSocket | Face::Internal => self.who.clone(),
        }
    }

    /// "scada (Modbus TCP)": who, and how, for messages.
    pub fn describe(&self) -> String {
        format!("{} {}", self.who, self.face.words())
    }
}
