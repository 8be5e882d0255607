//! The end-to-end tests, in one binary: every test binary links the whole
//! daemon and its dependencies, so one link serves them all and
//! `support/` is compiled once.
//!
//! One module per area, each a directory whose `mod.rs` declares one
//! module per part; a new test goes into the module of its part, or a new
//! module of its area, never a new binary. `cargo test --test e2e api::`
//! runs one area, `cargo test --test e2e api::leases::` one part.
//! `scripts/run-tests.py` shows a test as `api/leases::name`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod support;

mod api;
mod bus;
mod console;
mod control;
mod deploy;
mod diagnostics;
mod faults;
mod input;
mod modbus_tcp;
mod mqtt;
mod protocol;
mod security;
mod soak;
