//! The roles a token carries, as the control core defines them (see
//! [`crate::control::policy`]): the API checks them early, so a caller
//! without the right is refused before its body is even read; the core
//! checks them again on every write.

pub use crate::control::policy::{Role, for_command};

/// The role a settings write needs: any write to flash is admin work, and so
/// are the settings themselves (they change how the motor reacts).
pub const SETTINGS: Role = Role::Admin;
