//! The motor-safety rules of the control core, through every face: a brake
//! or a deactivation ends a lease whichever face sent it, still-checks and
//! their overrides, roles by token and by network, and one audit wording.
//!
//! One module per rule; a new test of a rule goes into its module, and a
//! row into `every_face`'s table, which runs every rule through every face.
//! Helpers shared with other areas live in `tests/support/`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod audit;
mod brake;
mod every_face;
mod opcua;
mod opcua_attacks;
mod opcua_browse;
mod opcua_certificates;
mod opcua_late;
mod opcua_operate;
mod opcua_wire;
mod roles;
mod rules;
