//! Access control and limits: every route against every role (from the
//! OpenAPI document), the HTTP API's size and connection limits, the
//! Modbus TCP listener's networks and read-only mode.
//!
//! A new access-control or limit test goes into the module of its face
//! here.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

#[path = "../support/mod.rs"]
mod support;

mod https;
mod limits;
mod modbus_tcp;
mod modbus_tls;
mod origin;
mod routes;
mod tokens;
