//! The HTTP API and its WebSocket stream, over real sockets against the
//! daemon on the simulator: reads, commands, errors, leases, access
//! control, the OpenAPI document.
//!
//! One module per part of the API; a new test of the API goes into the
//! module of its part (or a new module declared here). Helpers shared with
//! other areas live in `tests/support/`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod alarms;
mod auth;
mod buses;
mod commands;
mod config_file;
mod drives;
mod errors;
mod freshness;
mod history;
mod leases;
mod openapi;
mod settings;
mod stream;
