//! What the areas of the end-to-end tests share, one module per concept
//! (`crate::support` in every area).

#![allow(dead_code)]

pub mod alone;
pub mod api;
pub mod bus;
pub mod cdp;
pub mod certs;
pub mod config;
pub mod csv;
pub mod daemon;
pub mod faults;
pub mod input;
pub mod logs;
pub mod metrics;
pub mod modbus_tcp;
pub mod mosquitto;
pub mod opcua;
pub mod ports;
pub mod proxy;
pub mod pty;
pub mod sim_process;
pub mod sparkplug;
pub mod tools;
pub mod vectors;
pub mod wait;

#[allow(unused_imports)]
pub use daemon::{FOUR_DRIVES, TestDaemon, WIRE_TIMING, replaced};
#[allow(unused_imports)]
pub use wait::{bounded, eventually};
