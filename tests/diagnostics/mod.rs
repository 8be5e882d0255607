//! The bus monitor and the scope against the daemon on the simulator, over
//! real sockets: who caused each frame, filters, CSV and PCAP (read by
//! tshark), the live feed, the per-attempt wire counters; captures with
//! their triggers, pre-trigger, limits and roles, and the floor rate of the
//! drives not captured.
//!
//! One module per part; helpers shared with other areas live in
//! `tests/support/`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod monitor;
mod scope;
