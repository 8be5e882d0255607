//! drivegate: puts a bus of RS-485 (Modbus RTU) servo drives on the network.
//!
//! See `docs/architecture.md` for the picture of the modules and the path of
//! a request through them.

pub mod clock;
pub mod drive;
pub mod modbus;
pub mod sim;
