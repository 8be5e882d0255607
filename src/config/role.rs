//! The roles a caller can have (an API token's, a Modbus TCP client
//! network's): plain data here, read from the configuration; what each role
//! may do is the control core's to say (`crate::control::policy`).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

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
