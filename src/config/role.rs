//! The roles a caller can have (an API token's, a Modbus TCP client
//! network's): plain data here, read from the configuration; what each role
//! may do is the control core's to say (`crate::control::policy`).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The X.509 extension that carries a role in a client certificate, as an
/// ASN.1 UTF8String: Modbus/TCP Security's (its specification's), which
/// OPC UA user certificates carry too.
pub const ROLE_EXTENSION: &str = "1.3.6.1.4.1.50316.802.1";

/// A caller's role; each includes the rights of the ones before it.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize, Serialize, ToSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Reads and the stream.
    Viewer,
    /// Viewer, plus setpoints, modes, brake and resets.
    Operator,
    /// Operator, plus protection, ramps, inertia, saves, calibration,
    /// factory reset, RS-485 control, scans and address setting.
    Admin,
}

impl Role {
    /// The role named `name` (`viewer`, `operator`, `admin`).
    pub fn from_name(name: &str) -> Option<Role> {
        [Role::Viewer, Role::Operator, Role::Admin]
            .into_iter()
            .find(|r| r.name() == name)
    }

    /// Stable name for messages and logs.
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }

    /// True when this role includes `needed`.
    pub fn allows(self, needed: Role) -> bool {
        self >= needed
    }
}
