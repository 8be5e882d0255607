//! The web console: its files as built into the binary and served (CSP,
//! ETags, no foreign host), the public API additions it uses, and the page
//! itself in a real Debian chromium, headless, driven over the DevTools
//! protocol (`support::cdp`).
//!
//! One module per part; `harness` holds what only these tests need (tokens,
//! a stream watcher, a proxy that can freeze a connection).

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub, dead_code)]

mod alarms;
mod api;
mod assets;
mod browser;
mod comm_loss;
mod diagnostics;
mod freshness;
mod gateway;
mod harness;
mod https;
mod layout;
mod listeners;
mod plain;
mod replace;
mod trends;
