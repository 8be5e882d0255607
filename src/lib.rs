//! drivegate: puts a bus of RS-485 (Modbus RTU) servo drives on the network.
//!
//! See `docs/architecture.md` for the picture of the modules and the path of
//! a request through them.

pub mod api;
pub mod bench;
pub mod bus;
pub mod clock;
pub mod config;
pub mod console;
pub mod control;
pub mod daemon;
pub mod drive;
pub mod faces;
pub mod logging;
pub mod metrics;
pub mod modbus;
pub mod modbus_tcp;
pub mod monitor;
pub mod plant;
pub mod safety;
pub mod scope;
pub mod sim;
pub mod tls;
