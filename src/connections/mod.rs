//! Connection budgets, shared by every listener (Modbus TCP, Modbus/TCP
//! Security, HTTP and WebSocket, OPC UA connections and sessions): one
//! rule for who gets a slot, one reserve of file descriptors, one way to
//! back off from failing accepts, one way to say a repeated warning.
//!
//! - [`budget`]: the rule, pure: share every free slot while there is
//!   room; near the limit, or near the process's file limit, the heaviest
//!   address gives way first; an optional hard cap per address;
//! - [`files`]: the process's file limit, its open files, the reserves;
//! - [`repeats`]: a repeated warning written once per cause and second at
//!   most, with a count, less often as it goes on (pure);
//! - [`record`]: what a listener turned away, per address, bounded, for
//!   the metrics and the console (pure);
//! - [`words`]: the listeners' names and keys;
//! - [`book`]: the process's connections, the tickets they hold, the
//!   verdicts applied (a quiet connection of the heaviest address closed
//!   to make room) and logged;
//! - [`guarded`]: a connection's stream, telling the book it is alive and
//!   failing its reads once it was chosen to make room;
//! - [`accept`]: accept errors backing off.
//!
//! A leaf below the faces: it knows none of them, each face wraps its
//! accepts in it (and the OPC UA stack through its connection gate,
//! `opcua/gate.rs`). `docs/security.md` says what each limit is for.

pub mod accept;
pub mod book;
pub mod budget;
pub mod files;
pub mod guarded;
pub mod record;
pub mod repeats;
pub mod words;

pub use book::{Book, Listener, Seat, Ticket, View};
pub use budget::{Limits, Refused, host_key};
pub use guarded::Guarded;
pub use words::Face;
