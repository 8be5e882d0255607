//! Access control and limits: every route against every role (from the
//! OpenAPI document), the HTTP API's size and connection limits, the
//! Modbus TCP listener's networks and read-only mode, and state files that
//! cannot stall a start (`state_files.rs`: the real binary with 200 MB
//! files, its time to serve, its memory, SIGTERM during the start).
//!
//! A new access-control or limit test goes into the module of its face
//! here.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod https;
mod limits;
mod modbus_tcp;
mod modbus_tls;
mod opcua_budget;
mod opcua_input;
mod origin;
mod routes;
mod state_files;
mod tokens;
