//! The listeners as the log, the metrics and the console name them: each
//! with its section and the keys that change its limits.

/// A listener's names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Face {
    /// The `face` label of the metrics.
    pub label: &'static str,
    /// Its name in the log.
    pub name: &'static str,
    /// The configuration section of its keys.
    pub section: &'static str,
    /// The key of its limit.
    pub max_key: &'static str,
    /// The key of its hard cap per address.
    pub per_address_key: &'static str,
    /// What it counts: "connection", or "session".
    pub unit: &'static str,
}

/// Modbus TCP.
pub const MODBUS_TCP: Face = Face {
    label: "modbus_tcp",
    name: "Modbus TCP",
    section: "[modbus_tcp]",
    max_key: "max_connections",
    per_address_key: "max_connections_per_address",
    unit: "connection",
};

/// Modbus/TCP Security: the plain listener's keys, counted on its own.
pub const MODBUS_TLS: Face = Face {
    label: "modbus_tls",
    name: "Modbus/TCP Security",
    section: "[modbus_tcp]",
    max_key: "max_connections",
    per_address_key: "max_connections_per_address",
    unit: "connection",
};

/// HTTP (REST, WebSocket, the console, metrics).
pub const HTTP: Face = Face {
    label: "http",
    name: "HTTP",
    section: "[http]",
    max_key: "max_connections",
    per_address_key: "max_connections_per_address",
    unit: "connection",
};

/// OPC UA connections (each carries one secure channel).
pub const OPCUA: Face = Face {
    label: "opcua",
    name: "OPC UA",
    section: "[opcua]",
    max_key: "max_connections",
    per_address_key: "max_connections_per_address",
    unit: "connection",
};

/// OPC UA sessions.
pub const OPCUA_SESSIONS: Face = Face {
    label: "opcua_sessions",
    name: "OPC UA",
    section: "[opcua]",
    max_key: "max_sessions",
    per_address_key: "max_sessions_per_address",
    unit: "session",
};

/// Every listener, in the order the metrics list them.
pub const ALL: [Face; 5] = [MODBUS_TCP, MODBUS_TLS, HTTP, OPCUA, OPCUA_SESSIONS];

/// What happened to connections turned away, in the words of the
/// console's overview ("12 connections from 10.0.0.5 refused: the listener
/// was full").
pub fn turned_words(face: Face, turned: super::record::Turned) -> String {
    use super::budget::Refused;
    use super::record::Turned;
    let unit = face.unit;
    match turned {
        Turned::Refused(Refused::Limit) => "refused: the listener was full".to_string(),
        Turned::Refused(Refused::Heaviest) => {
            format!("refused: the listener was nearly full and this address held the most {unit}s")
        }
        Turned::Refused(Refused::PerAddress) => format!(
            "refused: the address held {} {} {unit}s",
            face.section, face.per_address_key
        ),
        Turned::Refused(Refused::Files) => format!(
            "refused: drivegate was near its limit of open files and this address held the most {unit}s"
        ),
        Turned::Closed => format!("closed to make room for other addresses' {unit}s"),
    }
}
