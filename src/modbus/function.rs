//! Modbus function codes: the ones the drives use, what every code of the
//! Modbus Application Protocol (V1.1b3) does to the device it goes to, and
//! helpers to read PDUs.
//!
//! [`effect`] is what a gateway needs to know before it lets a request
//! through: whether it only reads (it cannot change the device's state),
//! writes holding registers in a layout the control core decodes, or may
//! change the device in a way nobody can tell from the bytes (coils, files,
//! a diagnostics restart, a vendor's own code). It looks at the
//! sub-function of diagnostics (0x08) and the MEI type of 0x2B, whose
//! reads and writes share one function code.

/// 0x03 Read Holding Registers.
pub(crate) const READ_HOLDING_REGISTERS: u8 = 0x03;
/// 0x06 Write Single Register.
pub(crate) const WRITE_SINGLE_REGISTER: u8 = 0x06;
/// 0x08 Diagnostics (serial line only).
pub(crate) const DIAGNOSTICS: u8 = 0x08;
/// 0x10 Write Multiple Registers.
pub(crate) const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
/// 0x16 Mask Write Register.
pub(crate) const MASK_WRITE_REGISTER: u8 = 0x16;
/// 0x17 Read/Write Multiple Registers.
pub(crate) const READ_WRITE_MULTIPLE_REGISTERS: u8 = 0x17;
/// 0x2B Encapsulated Interface Transport.
pub(crate) const ENCAPSULATED_INTERFACE: u8 = 0x2B;
/// MEI type 0x0E of 0x2B: Read Device Identification.
pub(crate) const READ_DEVICE_IDENTIFICATION: u8 = 0x0E;

/// Bit set in the function code of an exception reply.
pub(crate) const EXCEPTION_BIT: u8 = 0x80;

/// Reads a big-endian u16 at `offset`, if the slice is long enough.
pub(crate) fn be_u16(bytes: &[u8], offset: usize) -> Option<u16> {
    let hi = *bytes.get(offset)?;
    let lo = *bytes.get(offset + 1)?;
    Some(u16::from_be_bytes([hi, lo]))
}

/// What a request does to the device it goes to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Effect {
    /// Only reads: the specification gives it no way to change the
    /// device's state (its outputs, registers, counters or mode).
    Read,
    /// Writes holding registers in a layout that says which registers get
    /// which values: 0x06, 0x10, 0x16 (mask write) and 0x17 (the write of
    /// read/write multiple).
    RegisterWrite,
    /// May change the device in a way the bytes do not explain: coils
    /// (0x05, 0x0F), file records (0x15), the diagnostics that restart,
    /// silence or clear a device (0x08 sub-functions 01, 03, 04, 0A, 14
    /// and the reserved ones), CANopen references (0x2B/0x0D), the
    /// user-defined codes (65-72, 100-110), reserved and undefined codes.
    Other,
}

/// Diagnostics (0x08) sub-functions that only return data: return query
/// data (00), the diagnostic register (02) and the counters (0B to 12).
/// 01 restarts the port (and ends listen-only mode), 03 changes the ASCII
/// delimiter, 04 forces listen-only mode (the device stops answering, so a
/// brake would go unheard), 0A and 14 clear counters; the rest is reserved.
fn diagnostics_reads(sub_function: u16) -> bool {
    matches!(sub_function, 0x0000 | 0x0002 | 0x000B..=0x0012)
}

/// What `pdu` (function code onward) does to its device.
pub(crate) fn effect(pdu: &[u8]) -> Effect {
    let Some(&function) = pdu.first() else {
        return Effect::Other;
    };
    match function {
        // Read coils, discrete inputs, holding and input registers; read
        // exception status, comm event counter and log, report server id,
        // read file record, read FIFO queue.
        0x01..=0x04 | 0x07 | 0x0B | 0x0C | 0x11 | 0x14 | 0x18 => Effect::Read,
        DIAGNOSTICS => match be_u16(pdu, 1) {
            Some(sub) if diagnostics_reads(sub) => Effect::Read,
            _ => Effect::Other,
        },
        ENCAPSULATED_INTERFACE if pdu.get(1) == Some(&READ_DEVICE_IDENTIFICATION) => Effect::Read,
        WRITE_SINGLE_REGISTER
        | WRITE_MULTIPLE_REGISTERS
        | MASK_WRITE_REGISTER
        | READ_WRITE_MULTIPLE_REGISTERS => Effect::RegisterWrite,
        _ => Effect::Other,
    }
}

/// The name the specification gives `function`, for messages and the
/// documentation; "user-defined", "reserved" or "not defined" for the
/// codes it gives no name.
pub(crate) fn name(function: u8) -> &'static str {
    match function {
        0x01 => "Read Coils",
        0x02 => "Read Discrete Inputs",
        0x03 => "Read Holding Registers",
        0x04 => "Read Input Registers",
        0x05 => "Write Single Coil",
        0x06 => "Write Single Register",
        0x07 => "Read Exception Status",
        0x08 => "Diagnostics",
        0x0B => "Get Comm Event Counter",
        0x0C => "Get Comm Event Log",
        0x0F => "Write Multiple Coils",
        0x10 => "Write Multiple Registers",
        0x11 => "Report Server ID",
        0x14 => "Read File Record",
        0x15 => "Write File Record",
        0x16 => "Mask Write Register",
        0x17 => "Read/Write Multiple Registers",
        0x18 => "Read FIFO Queue",
        0x2B => "Encapsulated Interface Transport",
        65..=72 | 100..=110 => "user-defined",
        // Annex A of the specification: kept for legacy products.
        9 | 10 | 13 | 14 | 41 | 42 | 90 | 91 | 125..=127 => "reserved",
        _ => "not defined",
    }
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
        0x0B => "get_comm_event_counter",
        0x0C => "get_comm_event_log",
        0x0F => "write_multiple_coils",
        0x10 => "write_multiple_registers",
        0x11 => "report_server_id",
        0x14 => "read_file_record",
        0x15 => "write_file_record",
        0x16 => "mask_write_register",
        0x17 => "read_write_multiple_registers",
        0x18 => "read_fifo_queue",
        0x2B => "encapsulated_interface",
        _ => "other",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_public_code_has_its_effect() {
        for read in [0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18] {
            assert_eq!(effect(&[read, 0, 0, 0, 1]), Effect::Read, "0x{read:02X}");
        }
        for write in [0x06, 0x10, 0x16, 0x17] {
            assert_eq!(effect(&[write, 0, 0, 0, 1]), Effect::RegisterWrite);
        }
        for other in [0x05, 0x0F, 0x15] {
            assert_eq!(effect(&[other, 0, 0, 0xFF, 0]), Effect::Other);
        }
        // Device identification reads; a CANopen reference may write.
        assert_eq!(effect(&[0x2B, 0x0E, 0x01, 0x00]), Effect::Read);
        assert_eq!(effect(&[0x2B, 0x0D, 0x00]), Effect::Other);
        assert_eq!(effect(&[0x2B]), Effect::Other);
        assert_eq!(effect(&[]), Effect::Other);
    }

    #[test]
    fn diagnostics_that_restart_silence_or_clear_are_not_reads() {
        let diag = |sub: u16| {
            let [hi, lo] = sub.to_be_bytes();
            effect(&[0x08, hi, lo, 0x00, 0x00])
        };
        for read in [0x00, 0x02, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12] {
            assert_eq!(diag(read), Effect::Read, "sub-function {read:02X}");
        }
        // restart, delimiter, listen only, clear counters, clear overrun,
        // and the reserved ones (05-09, 13, 15 up)
        for write in [0x01, 0x03, 0x04, 0x0A, 0x14, 0x05, 0x09, 0x13, 0x15, 0xFFFF] {
            assert_eq!(diag(write), Effect::Other, "sub-function {write:02X}");
        }
        assert_eq!(effect(&[0x08, 0x00]), Effect::Other, "no sub-function");
    }

    #[test]
    fn user_defined_reserved_and_undefined_codes_may_write() {
        for code in (65..=72).chain(100..=110) {
            assert_eq!(name(code), "user-defined");
            assert_eq!(effect(&[code]), Effect::Other);
        }
        for code in [9, 10, 13, 14, 41, 42, 90, 91, 125, 126, 127] {
            assert_eq!(name(code), "reserved");
            assert_eq!(effect(&[code]), Effect::Other);
        }
        assert_eq!(name(0x7B), "not defined");
        assert_eq!(effect(&[0x7B]), Effect::Other);
        assert_eq!(name(0x16), "Mask Write Register");
    }

    /// The table of `docs/modbus-tcp.md` says for each function code what
    /// this module decides: a row whose text begins "read" is a read, one
    /// that begins "decided" a register write, "not decoded" anything else.
    #[test]
    fn the_guide_table_says_what_the_code_does() {
        let guide = include_str!("../../docs/modbus-tcp.md");
        let table = guide
            .split("## Every function code")
            .nth(1)
            .and_then(|t| t.split("\n## ").next())
            .expect("the guide's table of function codes");
        let mut rows = 0;
        for line in table.lines().filter(|l| l.starts_with("| 0x")) {
            let cells: Vec<&str> = line.split('|').map(str::trim).collect();
            let Ok(code) = u8::from_str_radix(cells[1].trim_start_matches("0x"), 16) else {
                continue;
            };
            assert_eq!(cells[2], name(code), "{line}");
            let said = match cells[3] {
                t if t.starts_with("read") => Effect::Read,
                t if t.starts_with("decided") => Effect::RegisterWrite,
                t if t.starts_with("not decoded") => Effect::Other,
                // 0x08 and 0x2B: by sub-function, tested above.
                _ => continue,
            };
            assert_eq!(effect(&[code, 0, 1, 0, 0]), said, "{line}");
            rows += 1;
        }
        assert_eq!(rows, 17, "the rows of one effect (all but 0x08 and 0x2B)");
    }
}
