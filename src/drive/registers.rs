//! The drive's register table (manual appendix).
//!
//! Addressing quirk: the table steps by 2 and the drive counts addresses in
//! bytes but quantities in 16-bit words. A block of `count` registers from
//! `start` therefore covers `start, start + 2, ... start + 2 * (count - 1)`:
//! the status read is 7 registers from 0x00C0 covering 0x00C0..=0x00CC, and a
//! one-register read at 0x00C2 is ANGLE.

use crate::listed::listed_enum;

/// Who may read or write a register.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Write only (commands, save flags).
    Write,
    /// Readable and writable.
    ReadWrite,
    /// Read only (status block).
    Read,
}

impl Access {
    /// True for readable registers.
    pub fn readable(self) -> bool {
        matches!(self, Access::Read | Access::ReadWrite)
    }

    /// True for writable registers.
    pub fn writable(self) -> bool {
        matches!(self, Access::Write | Access::ReadWrite)
    }
}

/// Whether the 16 bits are read as signed or unsigned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValueKind {
    /// UINT16_T in the manual.
    U16,
    /// INT16_T in the manual.
    I16,
}

listed_enum! {
    /// One register of the drive.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    #[allow(missing_docs)] // the variants are the manual's register names
    pub enum Register {
        SlaveAddr,
        Config,
        SpeedRef,
        PositionRef,
        IqRef,
        StalledCurr,
        StalledDurationMs,
        StalledCurrSaveFlag,
        SpeedTdRHigh,
        SpeedTdRLow,
        SpeedTdRSaveFlag,
        PositionTdRHigh,
        PositionTdRLow,
        PositionTdRSaveFlag,
        InertiaRatio,
        InertiaRatioSaveFlag,
        Use485Control,
        CycleNum,
        Angle,
        Speed,
        Iq,
        Volt,
        Temp,
        Status,
    }
}

/// Address of the first status register; the status block is 7 registers.
pub(crate) const STATUS_BLOCK_START: u16 = 0x00C0;
/// Number of registers in the status block.
pub(crate) const STATUS_BLOCK_LEN: u16 = 7;

impl Register {
    /// The register's address as the manual gives it.
    pub const fn address(self) -> u16 {
        match self {
            Register::SlaveAddr => 0x0000,
            Register::Config => 0x0002,
            Register::SpeedRef => 0x0006,
            Register::PositionRef => 0x0008,
            Register::IqRef => 0x000A,
            Register::StalledCurr => 0x000C,
            Register::StalledDurationMs => 0x000E,
            Register::StalledCurrSaveFlag => 0x0010,
            Register::SpeedTdRHigh => 0x0018,
            Register::SpeedTdRLow => 0x001A,
            Register::SpeedTdRSaveFlag => 0x001C,
            Register::PositionTdRHigh => 0x001E,
            Register::PositionTdRLow => 0x0020,
            Register::PositionTdRSaveFlag => 0x0022,
            Register::InertiaRatio => 0x0024,
            Register::InertiaRatioSaveFlag => 0x0026,
            Register::Use485Control => 0x00BE,
            Register::CycleNum => 0x00C0,
            Register::Angle => 0x00C2,
            Register::Speed => 0x00C4,
            Register::Iq => 0x00C6,
            Register::Volt => 0x00C8,
            Register::Temp => 0x00CA,
            Register::Status => 0x00CC,
        }
    }

    /// The register's name in the manual.
    pub const fn name(self) -> &'static str {
        match self {
            Register::SlaveAddr => "SLAVE_ADDR",
            Register::Config => "CONFIG",
            Register::SpeedRef => "SPEED_REF",
            Register::PositionRef => "POSITION_REF",
            Register::IqRef => "IQ_REF",
            Register::StalledCurr => "STALLED_CURR",
            Register::StalledDurationMs => "STALLED_DURATION_MS",
            Register::StalledCurrSaveFlag => "STALLED_CURR_SAVE_FLAG",
            Register::SpeedTdRHigh => "SPEED_TD_R_HIGH",
            Register::SpeedTdRLow => "SPEED_TD_R_LOW",
            Register::SpeedTdRSaveFlag => "SPEED_TD_R_SAVE_FLAG",
            Register::PositionTdRHigh => "POSITION_TD_R_HIGH",
            Register::PositionTdRLow => "POSITION_TD_R_LOW",
            Register::PositionTdRSaveFlag => "POSITION_TD_R_SAVE_FLAG",
            Register::InertiaRatio => "INERTIA_RATIO",
            Register::InertiaRatioSaveFlag => "INERTIA_RATIO_SAVE_FLAG",
            Register::Use485Control => "USE_485_CONTROL",
            Register::CycleNum => "CYCLE_NUM",
            Register::Angle => "ANGLE",
            Register::Speed => "SPEED",
            Register::Iq => "IQ",
            Register::Volt => "VOLT",
            Register::Temp => "TEMP",
            Register::Status => "STATUS",
        }
    }

    /// Read/write access as the manual gives it.
    pub const fn access(self) -> Access {
        match self {
            Register::SlaveAddr
            | Register::Config
            | Register::StalledCurrSaveFlag
            | Register::SpeedTdRSaveFlag
            | Register::PositionTdRSaveFlag
            | Register::InertiaRatioSaveFlag => Access::Write,
            Register::CycleNum
            | Register::Angle
            | Register::Speed
            | Register::Iq
            | Register::Volt
            | Register::Temp
            | Register::Status => Access::Read,
            _ => Access::ReadWrite,
        }
    }

    /// Signed or unsigned, as the manual gives it.
    pub const fn kind(self) -> ValueKind {
        match self {
            Register::SpeedRef
            | Register::PositionRef
            | Register::IqRef
            | Register::Angle
            | Register::Speed
            | Register::Iq
            | Register::Temp => ValueKind::I16,
            _ => ValueKind::U16,
        }
    }

    /// The values a write may carry, as (min, max) of the register read with
    /// its own signedness. CONFIG additionally refuses the unused codes 0x9, 0xD+.
    pub const fn write_range(self) -> (i32, i32) {
        match self {
            Register::SlaveAddr => (1, 255),
            Register::Config => (0x0, 0xC),
            Register::SpeedRef | Register::IqRef => (-2048, 2047),
            Register::PositionRef => (-18000, 18000),
            Register::StalledCurr => (0, 2047),
            Register::StalledDurationMs => (0, 60000),
            Register::StalledCurrSaveFlag
            | Register::SpeedTdRSaveFlag
            | Register::PositionTdRSaveFlag
            | Register::InertiaRatioSaveFlag
            | Register::Use485Control => (0, 1),
            Register::InertiaRatio => (1, 65535),
            _ => (0, 65535),
        }
    }

    /// The register at `address`, if the table has one there.
    pub fn at(address: u16) -> Option<Register> {
        Register::ALL
            .iter()
            .copied()
            .find(|r| r.address() == address)
    }

    /// The registers of a block of `count` registers starting at `start`
    /// (byte addressing, see the module comment); `None` if any address of the
    /// block is not in the table.
    pub fn block(start: u16, count: u16) -> Option<Vec<Register>> {
        if count == 0 {
            return None;
        }
        (0..count)
            .map(|i| {
                let address = start.checked_add(i.checked_mul(2)?)?;
                Register::at(address)
            })
            .collect()
    }

    /// Interprets a raw 16-bit value with this register's signedness.
    pub fn signed_value(self, raw: u16) -> i32 {
        match self.kind() {
            ValueKind::I16 => i32::from(raw as i16),
            ValueKind::U16 => i32::from(raw),
        }
    }

    /// True when `raw` is a value the drive accepts for a write to this register.
    pub fn accepts(self, raw: u16) -> bool {
        let v = self.signed_value(raw);
        let (min, max) = self.write_range();
        let in_range = v >= min && v <= max;
        match self {
            Register::Config => in_range && super::command::ConfigCommand::from_code(raw).is_some(),
            _ => in_range,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_is_in_address_order_and_even() {
        for pair in Register::ALL.windows(2) {
            assert!(pair[0].address() < pair[1].address());
        }
        assert!(Register::ALL.iter().all(|r| r.address() % 2 == 0));
    }

    #[test]
    fn byte_addressing_of_blocks() {
        assert_eq!(Register::block(0x00C2, 1), Some(vec![Register::Angle]));
        let status = Register::block(STATUS_BLOCK_START, STATUS_BLOCK_LEN).unwrap();
        assert_eq!(status.first(), Some(&Register::CycleNum));
        assert_eq!(status.last(), Some(&Register::Status));
        assert_eq!(
            Register::block(0x000C, 3),
            Some(vec![
                Register::StalledCurr,
                Register::StalledDurationMs,
                Register::StalledCurrSaveFlag
            ])
        );
        // 0x0004 is a hole in the table, odd addresses are never registers.
        assert_eq!(Register::block(0x0002, 3), None);
        assert_eq!(Register::block(0x00C1, 1), None);
        assert_eq!(Register::block(0x00C0, 8), None);
        assert_eq!(Register::block(0xFFFE, 2), None);
        assert_eq!(Register::block(0x00C0, 0), None);
    }

    #[test]
    fn write_ranges() {
        assert!(Register::SpeedRef.accepts((-2048i16) as u16));
        assert!(!Register::SpeedRef.accepts(2048));
        assert!(Register::PositionRef.accepts((-18000i16) as u16));
        assert!(!Register::PositionRef.accepts(18001));
        assert!(Register::StalledDurationMs.accepts(60000));
        assert!(!Register::StalledDurationMs.accepts(60001));
        assert!(!Register::InertiaRatio.accepts(0));
        assert!(Register::Config.accepts(0x0C));
        assert!(!Register::Config.accepts(0x09));
        assert!(!Register::SlaveAddr.accepts(0));
    }
}
