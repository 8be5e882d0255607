//! Modbus function codes used by the drives, and helpers to read PDUs.

/// 0x03 Read Holding Registers.
pub(crate) const READ_HOLDING_REGISTERS: u8 = 0x03;
/// 0x06 Write Single Register.
pub(crate) const WRITE_SINGLE_REGISTER: u8 = 0x06;
/// 0x10 Write Multiple Registers.
pub(crate) const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;

/// Bit set in the function code of an exception reply.
pub(crate) const EXCEPTION_BIT: u8 = 0x80;

/// Reads a big-endian u16 at `offset`, if the slice is long enough.
pub(crate) fn be_u16(bytes: &[u8], offset: usize) -> Option<u16> {
    let hi = *bytes.get(offset)?;
    let lo = *bytes.get(offset + 1)?;
    Some(u16::from_be_bytes([hi, lo]))
}

/// A short human label for a function code, used in logs and metric labels.
pub(crate) fn label(function: u8) -> &'static str {
    match function {
        0x01 => "read_coils",
        0x02 => "read_discrete_inputs",
        0x03 => "read_holding_registers",
        0x04 => "read_input_registers",
        0x05 => "write_single_coil",
        0x06 => "write_single_register",
        0x07 => "read_exception_status",
        0x08 => "diagnostics",
        0x0F => "write_multiple_coils",
        0x10 => "write_multiple_registers",
        0x11 => "report_server_id",
        0x16 => "mask_write_register",
        0x17 => "read_write_multiple_registers",
        0x2B => "encapsulated_interface",
        _ => "other",
    }
}
