//! Faults through the real pty with eight simulated drives: wire faults at
//! a known rate, a drive gone silent or powered off, the adapter unplugged
//! and plugged back. Every job is answered and the accounting adds up.
//!
//! A new fault test goes into the module of its kind of fault here; the
//! soak, which measures the whole process, runs alone in a process of
//! its own (`tests/soak/`).

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod adapter;
mod drives;
mod held_port;
mod stall;
mod wire;
