//! The Modbus TCP face against the daemon on the simulator: third-party
//! clients (pymodbus, mbpoll), raw MBAP byte by byte, connections under
//! stress, several buses behind one listener, the audit log.
//!
//! A new Modbus TCP test goes into the module of its part here; attacks
//! and access control go to `tests/input/` and `tests/security/`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod audit;
mod buses;
mod clients;
mod comm_loss;
mod connections;
mod fair_shares;
mod functions;
mod late;
mod networks;
