//! drivegate: puts a bus of RS-485 (Modbus RTU) servo drives on the network.
//!
//! See `docs/architecture.md` for the picture of the modules and the path of
//! a request through them.
//!
//! # What the library exposes, and to whom
//!
//! The library's users are the `drivegate` binary (`src/main.rs`), the
//! benchmarks (`benches/`), the fuzz targets (`fuzz/targets.rs`) and the
//! end-to-end tests (`tests/`). Each module below is public because one of
//! them needs it, for the parts named here. In [`drive`], [`modbus`] and
//! [`sim`] every other part is `pub(crate)`: their surface is what they
//! re-export plus those parts.
//!
//! - Protocol, pure code: [`drive`] (requests, replies, status; `units` for
//!   the conversions the fuzz targets check), [`modbus`] (`crc`,
//!   `rtu_frame`, `reply`, `timing`: the framing and line timing the
//!   tests and benchmarks put on a wire).
//! - The simulator, [`sim`]: its configuration and handle, `bus` (fuzzed
//!   with requests), `cli` (`drivegate sim`), `model` (a drive's settings
//!   and procedures, which tests read back) and `pty`.
//! - The bus and its observers: [`bus`] (the handle every face uses, and the
//!   RTU master and port the pty tests drive directly), [`monitor`],
//!   [`scope`], [`history`] (the trends), [`clock`].
//! - The control core, [`control`] (with its stop actions, `stop_action`).
//! - The faces: [`api`] (the request bodies and stream messages fuzzed, the
//!   OpenAPI document checked for drift), [`modbus_tcp`] (MBAP, fuzzed),
//!   [`mqtt`] (Sparkplug B; its payload types for the tests' host),
//!   [`opcua`] (the OPC UA server; its address space's names for the
//!   tests),
//!   [`console`] (its assets), [`metrics`].
//! - Putting it together: [`config`], [`plant`], [`daemon`] (`serve`, its
//!   `supervisor` of the faces and its `reloader`, which the tests start
//!   as the daemon does), [`logging`], [`bench`] (`drivegate bench`),
//!   [`probe`] (`drivegate probe`).
//!
//! Private to the crate, because none of them needs it: `faces_shared`
//! (what the faces share: problem documents, a drive's status JSON, the
//! command messages), `port_holders` (who holds a serial port),
//! `suggest` ("did you mean"), `timestamp` (the one time format of every
//! face and observer), and the daemon's `systemd` notifications.

pub mod api;
pub mod bench;
pub mod bus;
pub mod certificate;
pub mod clock;
pub mod config;
pub mod connections;
pub mod console;
pub mod control;
pub mod daemon;
pub mod drive;
pub(crate) mod faces_shared;
pub mod history;
pub mod listed;
pub mod logging;
pub mod metrics;
pub mod modbus;
pub mod modbus_tcp;
pub mod monitor;
pub mod mqtt;
pub mod opcua;
pub mod plant;
pub(crate) mod port_holders;
pub mod probe;
pub mod scope;
pub mod sim;
pub(crate) mod suggest;
pub(crate) mod timestamp;
pub mod tls;
