//! Why a simulated bus cannot be built: the error of [`super::config`]'s
//! check and of the checks of the parts it is made of (delivery, faults),
//! at the bottom of the folder so that each part can give it.

use crate::drive::RangeError;

/// A simulated bus that cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// A drive at address 0.
    #[error("unit 0 is the broadcast address, not a drive: use 1 to 255")]
    BroadcastUnit,
    /// Two drives at one address.
    #[error("unit {0} is given twice: each simulated drive needs its own address")]
    DuplicateUnit(u8),
    /// Baud rate outside what serial lines use.
    #[error("baud rate {0} is out of range: valid 300 to 4000000")]
    Baud(u32),
    /// A number outside its range.
    #[error(transparent)]
    Range(#[from] RangeError),
}
