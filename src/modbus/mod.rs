//! Generic Modbus pieces shared by the RTU master, the simulator and the TCP face:
//! CRC, function and exception codes, RTU framing and RTU line timing. Pure code, no I/O.

pub mod crc;
pub(crate) mod exception;
pub(crate) mod function;
pub mod reply;
pub mod rtu_frame;
pub mod timing;

pub use exception::ExceptionCode;
