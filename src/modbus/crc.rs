//! CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF), sent low byte first.

/// Lookup table for the reflected polynomial, built at compile time.
const TABLE: [u16; 256] = build_table();

const fn build_table() -> [u16; 256] {
    let mut table = [0u16; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = i as u16;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
}

/// CRC-16/MODBUS of `data`.
pub fn crc16(data: &[u8]) -> u16 {
    data.iter().fold(0xFFFF_u16, |crc, &b| {
        (crc >> 8) ^ TABLE[((crc ^ u16::from(b)) & 0xFF) as usize]
    })
}

/// The two CRC bytes as they go on the wire (low byte first).
pub fn crc_bytes(data: &[u8]) -> [u8; 2] {
    crc16(data).to_le_bytes()
}

/// True when the last two bytes of `frame` are the CRC of the rest.
pub fn frame_crc_ok(frame: &[u8]) -> bool {
    match frame.len().checked_sub(2) {
        Some(n) if n > 0 => crc_bytes(&frame[..n]) == [frame[n], frame[n + 1]],
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_value_of_the_catalogue() {
        // CRC-16/MODBUS check value for "123456789".
        assert_eq!(crc16(b"123456789"), 0x4B37);
    }

    #[test]
    fn status_read_request() {
        // unit 1, read 7 registers from 0x00C0 -> CRC 04 34 on the wire.
        assert_eq!(
            crc_bytes(&[0x01, 0x03, 0x00, 0xC0, 0x00, 0x07]),
            [0x04, 0x34]
        );
        assert!(frame_crc_ok(&[
            0x01, 0x03, 0x00, 0xC0, 0x00, 0x07, 0x04, 0x34
        ]));
        assert!(!frame_crc_ok(&[
            0x01, 0x03, 0x00, 0xC0, 0x00, 0x07, 0x04, 0x35
        ]));
        assert!(!frame_crc_ok(&[0x04, 0x34]));
    }
}
