//! The bus engine and the simulator through real ptys: the RTU master
//! against scripted peers, the scheduler against scripted peers and
//! against the simulator, the simulator's wire and timing, `drivegate sim`.
//!
//! A new test of the bus (master, scheduler, queue, poller) or of the
//! simulator goes into the module of its part here. Helpers shared with
//! other areas live in `tests/support/`.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod dead_drive;
mod interframe;
mod long_replies;
mod master_pty;
mod master_timing;
mod probe;
mod pty;
mod reply_timeout;
mod sim;
mod sim_cli;
mod sim_listen;
mod sim_wire;
mod tcp_port;
