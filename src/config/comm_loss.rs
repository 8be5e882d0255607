//! A communication-loss function as configured, for a Modbus TCP client
//! network and for the Modbus/TCP Security listener alike: below both
//! sections.

use std::time::Duration;

use super::safety::StopAction;

/// A client network's communication-loss function, as configured: its
/// setpoints and mode commands each take a lease that any request of the
/// connection renews and `after` of silence ends with `action`. The control
/// core's lease book runs it (`crate::control::CommLoss`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommLossConfig {
    /// Silence that ends its leases.
    pub after: Duration,
    /// What their end sends.
    pub action: StopAction,
}
