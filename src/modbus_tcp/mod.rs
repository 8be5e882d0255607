//! The Modbus TCP passthrough face for SCADA and PLCs.

pub mod config;
