//! Modbus exception codes, with texts a plant engineer can act on.

use std::fmt;

/// A Modbus exception code as carried in an exception reply (function | 0x80, code).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ExceptionCode(pub u8);

impl ExceptionCode {
    /// 0x01: the device does not implement this function code.
    pub const ILLEGAL_FUNCTION: Self = Self(0x01);
    /// 0x02: the register address is not in the device's table.
    pub const ILLEGAL_DATA_ADDRESS: Self = Self(0x02);
    /// 0x03: a value is outside what the device accepts.
    pub const ILLEGAL_DATA_VALUE: Self = Self(0x03);
    /// 0x04: the device failed while carrying out the request.
    pub const SERVER_DEVICE_FAILURE: Self = Self(0x04);
    /// 0x06: the device (or gateway queue) is busy; try again later.
    pub const SERVER_DEVICE_BUSY: Self = Self(0x06);
    /// 0x0A: the gateway has no path to that unit (unknown unit or bus down).
    pub const GATEWAY_PATH_UNAVAILABLE: Self = Self(0x0A);
    /// 0x0B: the gateway sent the request but the drive did not answer.
    pub const GATEWAY_TARGET_FAILED: Self = Self(0x0B);

    /// Short name of the code.
    pub fn name(self) -> &'static str {
        match self.0 {
            0x01 => "illegal function",
            0x02 => "illegal data address",
            0x03 => "illegal data value",
            0x04 => "server device failure",
            0x05 => "acknowledge",
            0x06 => "server device busy",
            0x08 => "memory parity error",
            0x0A => "gateway path unavailable",
            0x0B => "gateway target device failed to respond",
            _ => "unknown exception",
        }
    }
}

impl fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Modbus exception 0x{:02X} ({})", self.0, self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_codes() {
        assert_eq!(
            ExceptionCode::ILLEGAL_DATA_ADDRESS.to_string(),
            "Modbus exception 0x02 (illegal data address)"
        );
        assert_eq!(ExceptionCode(0x42).name(), "unknown exception");
    }
}
