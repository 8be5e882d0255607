//! The bus engine: one task owns each serial port and serialises every
//! transaction on it; everything else talks to it through a [`BusHandle`].
//!
//! - [`port`] opens the adapter (and sets RS-485 direction control),
//! - [`tcp_port`] connects to a serial device server (`tcp://host:port`),
//! - [`transport`] is either, as the master sees it,
//! - [`master`] is the RTU master: one frame in flight, t3.5 silences, reply
//!   framing and checks, retries, guard time and input flush after faults,
//! - [`queue`] holds waiting jobs by priority, fair between submitters,
//! - [`reply_timeout`] learns how long each drive takes to answer,
//! - [`interframe`] keeps the silence before each drive's requests (the
//!   spec's, a fixed one, or each drive's own, learned),
//! - [`poller`] decides which drive's status is due next,
//! - [`scheduler`] is the task's loop tying them together, run with the
//!   [`settings`] the configuration builds,
//! - [`cache`] keeps each drive's latest status and publishes changes,
//! - [`freshness`] says how fresh a drive's data is (live, stale, offline,
//!   never, bus-down), the one answer every face shows,
//! - [`stats`] counts what happened on the wire, for health and metrics,
//! - [`handle`] is what the faces (HTTP, Modbus TCP, metrics) hold,
//! - [`origin`] says who caused each job (for the monitor and the scope),
//! - [`observers`] is what the bus shows and asks of those who watch it
//!   (the bus monitor, the scope), through the master's [`tap`]; the bus
//!   never names them,
//! - [`fault`] and [`priority`] are leaves shared by the master, the
//!   queue and the errors; [`link`] (a port's state, whether a drive
//!   answers) is the leaf the cache, freshness, the handle and the
//!   scheduler share.

pub mod cache;
pub mod error;
pub mod fault;
pub mod feed;
pub mod freshness;
pub mod handle;
pub mod interframe;
pub mod job;
pub mod link;
pub mod master;
pub mod observers;
pub mod origin;
pub mod poller;
pub mod port;
pub mod priority;
pub mod queue;
pub mod reply_timeout;
pub mod rs485;
pub mod scheduler;
pub mod settings;
pub mod stats;
pub mod tap;
pub mod tcp_port;
pub mod transport;

pub use cache::{BusEvent, DriveSnapshot};
pub use error::BusError;
pub use feed::BusFollower;
pub use handle::BusHandle;
pub use job::{Exchange, Priority, SourceId};
pub use observers::Observers;
pub use origin::Origin;
