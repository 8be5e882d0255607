//! The drive's registers as the bus sees them: reads (the status block,
//! settings, setpoints), writes and the checks that refuse them, the
//! settings' ramps and the saves to flash (manual 1.4 to 1.6).

use super::*;

impl DriveModel {
    /// The value a read of `register` returns (write-only registers read 0;
    /// the slave refuses them before asking).
    pub fn read(&self, register: Register) -> u16 {
        let s = &self.settings;
        match register {
            Register::SpeedRef => self.setpoints.speed_rpm as u16,
            Register::PositionRef => self.setpoints.position_centideg as u16,
            Register::IqRef => self.setpoints.current_counts as u16,
            Register::StalledCurr => s.stall_current,
            Register::StalledDurationMs => s.stall_duration_ms,
            Register::SpeedTdRHigh => (s.speed_alpha >> 16) as u16,
            Register::SpeedTdRLow => s.speed_alpha as u16,
            Register::PositionTdRHigh => (s.position_alpha >> 16) as u16,
            Register::PositionTdRLow => s.position_alpha as u16,
            Register::InertiaRatio => s.inertia_ratio,
            Register::Use485Control => u16::from(self.rs485_control),
            Register::CycleNum
            | Register::Angle
            | Register::Speed
            | Register::Iq
            | Register::Volt
            | Register::Temp
            | Register::Status => {
                let index = status_index(register).unwrap_or(0);
                self.status().to_registers()[index]
            }
            Register::SlaveAddr
            | Register::Config
            | Register::StalledCurrSaveFlag
            | Register::SpeedTdRSaveFlag
            | Register::PositionTdRSaveFlag
            | Register::InertiaRatioSaveFlag => 0,
        }
    }

    /// Appends the values of `registers` (readable ones), big-endian, as a
    /// read reply carries them; a status block costs one status computation.
    pub fn read_into(&self, registers: &[Register], out: &mut Vec<u8>) {
        let mut status = None;
        for &register in registers {
            let value = match status_index(register) {
                Some(i) => status.get_or_insert_with(|| self.status().to_registers())[i],
                None => self.read(register),
            };
            out.extend_from_slice(&value.to_be_bytes());
        }
    }

    /// Whether the drive would carry out a write of `value` (already within
    /// the manual's range) to `register` now.
    pub fn check_write(&self, register: Register, value: u16) -> Result<(), Refusal> {
        let busy = self.running.map(|r| Refusal::Busy(r.procedure.name()));
        match register {
            Register::SpeedRef | Register::PositionRef | Register::IqRef => {
                if let Some(busy) = busy {
                    return Err(busy);
                }
                if !self.active {
                    return Err(Refusal::NotActive);
                }
            }
            Register::Config => match ConfigCommand::from_code(value) {
                Some(
                    ConfigCommand::Calibrate
                    | ConfigCommand::SpeedMode
                    | ConfigCommand::PositionMode
                    | ConfigCommand::TorqueMode,
                ) => {
                    if let Some(busy) = busy {
                        return Err(busy);
                    }
                }
                Some(ConfigCommand::FineTuneCalibration) => {
                    if let Some(busy) = busy {
                        return Err(busy);
                    }
                    if !self.calibrated {
                        return Err(Refusal::NotCalibrated);
                    }
                }
                _ => {}
            },
            _ => {}
        }
        Ok(())
    }

    /// Carries out a write (checked with [`check_write`](Self::check_write)).
    pub fn write(&mut self, register: Register, value: u16) -> Result<(), Refusal> {
        self.write_register(register, value)?;
        self.apply_alpha();
        Ok(())
    }

    /// Carries out a block write (function 0x10) as the drive does, at once:
    /// a ramp's alpha, split over two registers, reaches the running ramp
    /// whole. Applied half by half, the mix of new high and old low half
    /// can be 0 ("ramp off", manual 1.9) and step the setpoint mid-ramp.
    pub fn write_block(&mut self, writes: &[(Register, u16)]) -> Result<(), Refusal> {
        let written = writes
            .iter()
            .try_for_each(|&(register, value)| self.write_register(register, value));
        self.apply_alpha();
        written
    }

    /// Writes one register; a ramp alpha goes to the settings only (see
    /// [`apply_alpha`](Self::apply_alpha)).
    pub(super) fn write_register(&mut self, register: Register, value: u16) -> Result<(), Refusal> {
        self.check_write(register, value)?;
        match register {
            Register::SlaveAddr => {
                if let Ok(address) = u8::try_from(value)
                    && address != 0
                {
                    self.address = address;
                    self.flash.address = address;
                }
            }
            Register::Config => {
                if let Some(command) = ConfigCommand::from_code(value) {
                    self.command(command);
                }
            }
            Register::SpeedRef => self.set_setpoint(|s| s.speed_rpm = value as i16, Mode::Speed),
            Register::PositionRef => {
                self.set_setpoint(|s| s.position_centideg = value as i16, Mode::Position)
            }
            Register::IqRef => self.set_setpoint(|s| s.current_counts = value as i16, Mode::Torque),
            Register::StalledCurr => self.settings.stall_current = value,
            Register::StalledDurationMs => self.settings.stall_duration_ms = value,
            Register::SpeedTdRHigh => {
                let alpha = (u32::from(value) << 16) | (self.settings.speed_alpha & 0xFFFF);
                self.set_alpha(Mode::Speed, alpha);
            }
            Register::SpeedTdRLow => {
                let alpha = (self.settings.speed_alpha & 0xFFFF_0000) | u32::from(value);
                self.set_alpha(Mode::Speed, alpha);
            }
            Register::PositionTdRHigh => {
                let alpha = (u32::from(value) << 16) | (self.settings.position_alpha & 0xFFFF);
                self.set_alpha(Mode::Position, alpha);
            }
            Register::PositionTdRLow => {
                let alpha = (self.settings.position_alpha & 0xFFFF_0000) | u32::from(value);
                self.set_alpha(Mode::Position, alpha);
            }
            Register::InertiaRatio => {
                self.settings.inertia_ratio = value;
                self.motor.set_inertia_ratio(f64::from(value));
            }
            Register::Use485Control => self.rs485_control = value == 1,
            Register::StalledCurrSaveFlag
            | Register::SpeedTdRSaveFlag
            | Register::PositionTdRSaveFlag
            | Register::InertiaRatioSaveFlag => {
                if value == 1 {
                    self.save(register);
                }
            }
            Register::CycleNum
            | Register::Angle
            | Register::Speed
            | Register::Iq
            | Register::Volt
            | Register::Temp
            | Register::Status => {}
        }
        Ok(())
    }

    pub(super) fn set_setpoint(&mut self, set: impl FnOnce(&mut Setpoints), mode: Mode) {
        if !self.rs485_control {
            return; // CAN is in control (manual 1.12)
        }
        set(&mut self.setpoints);
        self.braking = false;
        if self.ramp_engaged == Some(mode) {
            let target = self.ramp_target(mode);
            self.ramp.set_target(target);
        }
    }

    pub(super) fn set_alpha(&mut self, mode: Mode, alpha: u32) {
        match mode {
            Mode::Speed => self.settings.speed_alpha = alpha,
            _ => self.settings.position_alpha = alpha,
        }
    }

    /// Gives the running ramp its mode's alpha from the settings (no change
    /// when it already has it).
    pub(super) fn apply_alpha(&mut self) {
        let alpha = match self.ramp_engaged {
            Some(Mode::Speed) => self.settings.speed_alpha,
            Some(Mode::Position) => self.settings.position_alpha,
            _ => return,
        };
        self.ramp.set_alpha(alpha);
    }

    pub(super) fn save(&mut self, flag: Register) {
        if !self.motor.at_standstill() {
            self.saves_while_moving += 1;
        }
        let (ram, flash) = (self.settings, &mut self.flash.settings);
        match flag {
            Register::StalledCurrSaveFlag => {
                flash.stall_current = ram.stall_current;
                flash.stall_duration_ms = ram.stall_duration_ms;
            }
            Register::SpeedTdRSaveFlag => flash.speed_alpha = ram.speed_alpha,
            Register::PositionTdRSaveFlag => flash.position_alpha = ram.position_alpha,
            _ => flash.inertia_ratio = ram.inertia_ratio,
        }
    }
}
