//! The status block (manual 1.7): seven registers from 0x00C0.

use super::units;
use crate::listed::listed_enum;

listed_enum! {
    /// Control mode, STATUS bits 4..3.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum Mode {
        /// 0: open-loop voltage control (power-on mode before a mode command).
        OpenLoop,
        /// 1: speed closed loop.
        Speed,
        /// 2: position closed loop.
        Position,
        /// 3: torque (current) closed loop.
        Torque,
    }
}

impl Mode {
    /// Mode from its two STATUS bits.
    pub const fn from_bits(bits: u16) -> Self {
        match bits & 0b11 {
            0 => Mode::OpenLoop,
            1 => Mode::Speed,
            2 => Mode::Position,
            _ => Mode::Torque,
        }
    }

    /// The two STATUS bits of this mode.
    pub const fn bits(self) -> u16 {
        match self {
            Mode::OpenLoop => 0,
            Mode::Speed => 1,
            Mode::Position => 2,
            Mode::Torque => 3,
        }
    }

    /// Stable name for the API and metrics.
    pub const fn name(self) -> &'static str {
        match self {
            Mode::OpenLoop => "open_loop",
            Mode::Speed => "speed",
            Mode::Position => "position",
            Mode::Torque => "torque",
        }
    }
}

listed_enum! {
    /// Fault code, STATUS bits 2..0.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
    pub enum Fault {
        /// 0: healthy.
        None,
        /// 1: current feedback signal fault.
        CurrentSense,
        /// 2: encoder feedback signal fault.
        Encoder,
        /// 3: power stage (switching devices) fault.
        PowerStage,
        /// 4: drive over-temperature.
        OverTemperature,
        /// 5: supply under-voltage.
        UnderVoltage,
        /// 6: supply over-voltage.
        OverVoltage,
        /// 7: reserved by the maker.
        Reserved,
    }
}

impl Fault {
    /// Fault from its three STATUS bits.
    pub const fn from_code(code: u16) -> Self {
        match code & 0b111 {
            0 => Fault::None,
            1 => Fault::CurrentSense,
            2 => Fault::Encoder,
            3 => Fault::PowerStage,
            4 => Fault::OverTemperature,
            5 => Fault::UnderVoltage,
            6 => Fault::OverVoltage,
            _ => Fault::Reserved,
        }
    }

    /// The fault's 3-bit code.
    pub const fn code(self) -> u16 {
        match self {
            Fault::None => 0,
            Fault::CurrentSense => 1,
            Fault::Encoder => 2,
            Fault::PowerStage => 3,
            Fault::OverTemperature => 4,
            Fault::UnderVoltage => 5,
            Fault::OverVoltage => 6,
            Fault::Reserved => 7,
        }
    }

    /// Stable name for the API and metrics (`none` when healthy).
    pub const fn name(self) -> &'static str {
        match self {
            Fault::None => "none",
            Fault::CurrentSense => "current_sense",
            Fault::Encoder => "encoder",
            Fault::PowerStage => "power_stage",
            Fault::OverTemperature => "over_temperature",
            Fault::UnderVoltage => "under_voltage",
            Fault::OverVoltage => "over_voltage",
            Fault::Reserved => "reserved",
        }
    }

    /// The fault with this [`name`](Self::name).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|f| f.name() == name)
    }
}

/// STATUS bit 7: drive active.
pub(crate) const FLAG_ACTIVE: u16 = 1 << 7;
/// STATUS bit 6: encoder calibrated.
pub(crate) const FLAG_CALIBRATED: u16 = 1 << 6;
/// STATUS bit 5: stalled (needs a fault reset).
pub(crate) const FLAG_STALLED: u16 = 1 << 5;

/// One decoded status read, in the drive's own units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Status {
    /// CYCLE_NUM: whole turns, 0..65535 (wraps).
    pub turns: u16,
    /// ANGLE: -18000..18000 in 0.01 degree.
    pub angle_centideg: i16,
    /// SPEED: rpm at the gearbox output.
    pub speed_rpm: i16,
    /// IQ: current in counts (1 A = 128).
    pub current_counts: i16,
    /// VOLT: supply voltage in volts.
    pub voltage_v: u16,
    /// TEMP: drive temperature in degrees Celsius.
    pub temperature_c: i16,
    /// STATUS: raw flag word.
    pub flags: u16,
}

impl Status {
    /// Number of bytes of the status block in a reply.
    pub const BYTES: usize = 14;

    /// Decodes the seven registers in order CYCLE_NUM..STATUS.
    pub fn from_registers(r: [u16; 7]) -> Self {
        Status {
            turns: r[0],
            angle_centideg: r[1] as i16,
            speed_rpm: r[2] as i16,
            current_counts: r[3] as i16,
            voltage_v: r[4],
            temperature_c: r[5] as i16,
            flags: r[6],
        }
    }

    /// The seven registers in order CYCLE_NUM..STATUS.
    pub fn to_registers(&self) -> [u16; 7] {
        [
            self.turns,
            self.angle_centideg as u16,
            self.speed_rpm as u16,
            self.current_counts as u16,
            self.voltage_v,
            self.temperature_c as u16,
            self.flags,
        ]
    }

    /// Decodes the 14 data bytes of a status reply (big-endian registers).
    pub fn from_bytes(data: &[u8]) -> Option<Self> {
        if data.len() != Self::BYTES {
            return None;
        }
        let mut regs = [0u16; 7];
        for (i, reg) in regs.iter_mut().enumerate() {
            *reg = u16::from_be_bytes([data[2 * i], data[2 * i + 1]]);
        }
        Some(Self::from_registers(regs))
    }

    /// The 14 data bytes of a status reply.
    pub fn to_bytes(&self) -> [u8; Self::BYTES] {
        let mut out = [0u8; Self::BYTES];
        for (i, reg) in self.to_registers().iter().enumerate() {
            out[2 * i..2 * i + 2].copy_from_slice(&reg.to_be_bytes());
        }
        out
    }

    /// STATUS bit 7.
    pub fn active(&self) -> bool {
        self.flags & FLAG_ACTIVE != 0
    }

    /// STATUS bit 6.
    pub fn calibrated(&self) -> bool {
        self.flags & FLAG_CALIBRATED != 0
    }

    /// STATUS bit 5.
    pub fn stalled(&self) -> bool {
        self.flags & FLAG_STALLED != 0
    }

    /// STATUS bits 4..3.
    pub fn mode(&self) -> Mode {
        Mode::from_bits(self.flags >> 3)
    }

    /// STATUS bits 2..0.
    pub fn fault(&self) -> Fault {
        Fault::from_code(self.flags)
    }

    /// Angle in degrees.
    pub fn angle_deg(&self) -> f64 {
        units::centideg_to_degrees(self.angle_centideg)
    }

    /// Current in amps.
    pub fn current_a(&self) -> f64 {
        units::counts_to_amps(self.current_counts)
    }

    /// Builds the STATUS flag word from its parts.
    pub fn flags_from(
        active: bool,
        calibrated: bool,
        stalled: bool,
        mode: Mode,
        fault: Fault,
    ) -> u16 {
        let mut flags = (mode.bits() << 3) | fault.code();
        if active {
            flags |= FLAG_ACTIVE;
        }
        if calibrated {
            flags |= FLAG_CALIBRATED;
        }
        if stalled {
            flags |= FLAG_STALLED;
        }
        flags
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_the_manual_example() {
        // frames.tsv status_reply data: turns=3 angle=45.00 speed=-120 iq=256 volt=24 temp=41 flags=0x00C8
        let data = [
            0x00, 0x03, 0x11, 0x94, 0xFF, 0x88, 0x01, 0x00, 0x00, 0x18, 0x00, 0x29, 0x00, 0xC8,
        ];
        let s = Status::from_bytes(&data).unwrap();
        assert_eq!(s.turns, 3);
        assert_eq!(s.angle_deg(), 45.0);
        assert_eq!(s.speed_rpm, -120);
        assert_eq!(s.current_a(), 2.0);
        assert_eq!(s.voltage_v, 24);
        assert_eq!(s.temperature_c, 41);
        assert!(s.active() && s.calibrated() && !s.stalled());
        assert_eq!(s.mode(), Mode::Speed);
        assert_eq!(s.fault(), Fault::None);
        assert_eq!(s.to_bytes(), data);
    }

    #[test]
    fn flags_round_trip() {
        for fault in Fault::ALL {
            for mode in [Mode::OpenLoop, Mode::Speed, Mode::Position, Mode::Torque] {
                let flags = Status::flags_from(true, false, true, mode, fault);
                let s = Status {
                    flags,
                    ..Status::default()
                };
                assert_eq!((s.mode(), s.fault()), (mode, fault));
                assert!(s.active() && !s.calibrated() && s.stalled());
                assert_eq!(Fault::from_name(fault.name()), Some(fault));
            }
        }
        assert_eq!(Status::from_bytes(&[0; 13]), None);
    }
}
