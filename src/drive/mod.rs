//! The drive's RS-485 protocol (maker's manual, sections 1.2 to 1.12) as pure
//! code: the register table, the config commands, status decoding and its
//! fields as the faces name them, value ranges and unit conversions, and
//! typed requests and replies. No I/O here.

pub(crate) mod command;
pub mod help;
pub(crate) mod message;
pub(crate) mod range;
pub(crate) mod registers;
pub mod settings;
pub(crate) mod status;
pub(crate) mod status_field;
pub mod units;
pub mod wanted;
pub(crate) mod writes;

pub use command::ConfigCommand;
pub use message::{DriveReply, DriveRequest, ReplyError};
pub use range::RangeError;
pub use registers::Register;
pub use status::{Fault, Mode, Status};
pub use status_field::{Reading, StatusField};
