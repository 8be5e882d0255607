//! One simulated drive: its registers, RAM and flash, config commands,
//! control modes, protections and faults (manual 1.2 to 1.12). Pure code:
//! time is passed in with [`DriveModel::advance`].
//!
//! Choices where the manual is silent, so the gateway can be tested against
//! a drive that behaves in one definite way:
//! - Flash holds the address, the active flag, the calibrated flag and the
//!   four groups of settings (protection, both ramps, inertia). Power-on loads
//!   them; the factory values are [`Settings::FACTORY`] (ramps 500000, as the
//!   manual's "default after power-on").
//! - USE_485_CONTROL powers on at 1 (RS-485 in control). Written 0, motion
//!   setpoints are still echoed but ignored, as the manual says RS-485 then
//!   does not control the motor.
//! - Setpoint registers keep what was written. Whenever the drive drives the
//!   motor in a mode (after activation, a mode command, a fault reset, a
//!   brake release) it ramps from where the motor is to that mode's register:
//!   zero the setpoints before reactivating a drive that should stand still.
//! - Position setpoints are absolute output angles from the zero point; the
//!   motor unwinds any whole turns it made (a joint, not a spindle).
//! - Saving while the motor moves (the manual asks for standstill) is carried
//!   out and counted in [`SimDriveView::saves_while_moving`].
//! - Calibration (4 s) and fine-tuning (2 s) move the motor even when the
//!   drive is not active; setpoints and mode commands meanwhile are refused
//!   as busy, a fault or the emergency brake aborts them.
//! - Emergency brake: speed and torque setpoints go to zero, the motor is
//!   stopped at full current, then held; any setpoint or mode command releases
//!   the brake.
//! - After power-off the turn count restarts at 0 (the angle within the turn
//!   is absolute) and the zero point is lost (manual 1.3, 0x4).

use super::control;
use super::physics::{Drive, Environment, Motor, MotorParams};
use super::ramp::Ramp;
use crate::drive::registers::{STATUS_BLOCK_LEN, STATUS_BLOCK_START};
use crate::drive::units::{COUNTS_PER_AMP, DEFAULT_RAMP_ALPHA, RPM_PER_RAD_S};
use crate::drive::{ConfigCommand, Fault, Mode, Register, Status};
use std::f64::consts::PI;

/// Longest step of the model while anything moves, s.
pub const MAX_STEP: f64 = 0.001;
/// Longest step while nothing but temperature changes, s.
const REST_STEP: f64 = 1.0;

/// How long calibration takes (manual 1.3: "about 4 s"), s.
pub const CALIBRATION_TIME: f64 = 4.0;
/// How long fine-tuning takes (the motor turns both ways), s.
pub const FINE_TUNE_TIME: f64 = 2.0;
/// Over-temperature trips above this, °C.
pub const OVER_TEMPERATURE: f64 = 85.0;
/// An over-temperature fault can be reset below this, °C.
pub const TEMPERATURE_RECOVERED: f64 = 80.0;
/// Under-voltage trips below this, V.
pub const UNDER_VOLTAGE: f64 = 18.0;
/// Over-voltage trips above this, V.
pub const OVER_VOLTAGE: f64 = 30.0;

/// The settings the save flags write to flash (manual 1.8 to 1.11).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Settings {
    /// STALLED_CURR: current above which the stall timer runs, counts.
    pub stall_current: u16,
    /// STALLED_DURATION_MS: how long the current may stay above it, ms.
    pub stall_duration_ms: u16,
    /// Speed ramp alpha (SPEED_TD_R_HIGH/LOW), 0 = off.
    pub speed_alpha: u32,
    /// Position ramp alpha (POSITION_TD_R_HIGH/LOW), 0 = off.
    pub position_alpha: u32,
    /// INERTIA_RATIO: load inertia as a multiple of the rotor's.
    pub inertia_ratio: u16,
}

impl Settings {
    /// What a factory reset restores: 12 A for 3 s stalls the motor, ramps
    /// at the manual's power-on default, load inertia equal to the rotor's.
    pub const FACTORY: Settings = Settings {
        stall_current: 1536,
        stall_duration_ms: 3000,
        speed_alpha: DEFAULT_RAMP_ALPHA,
        position_alpha: DEFAULT_RAMP_ALPHA,
        inertia_ratio: 1,
    };
}

/// What survives a power cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Flash {
    /// Bus address (manual 1.2).
    pub address: u8,
    /// Activation (manual 1.3, 0x0/0x1: "kept over power loss").
    pub active: bool,
    /// Encoder calibration done.
    pub calibrated: bool,
    /// Saved settings.
    pub settings: Settings,
}

/// The three setpoint registers, as written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Setpoints {
    /// SPEED_REF, rpm at the output.
    pub speed_rpm: i16,
    /// POSITION_REF, 0.01 degree at the output.
    pub position_centideg: i16,
    /// IQ_REF, current counts (1 A = 128).
    pub current_counts: i16,
}

/// A procedure the drive runs by itself after a config command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Procedure {
    /// 0x2: encoder angle calibration, the motor nudges.
    Calibrating,
    /// 0x3: fine-tuning, the motor turns both ways.
    FineTuning,
}

impl Procedure {
    /// Name for messages.
    pub fn name(self) -> &'static str {
        match self {
            Procedure::Calibrating => "calibration",
            Procedure::FineTuning => "fine-tuning",
        }
    }

    fn duration(self) -> f64 {
        match self {
            Procedure::Calibrating => CALIBRATION_TIME,
            Procedure::FineTuning => FINE_TUNE_TIME,
        }
    }

    /// Motor shaft angle around the starting one, rad.
    fn trajectory(self, t: f64) -> f64 {
        let (amplitude, hz) = match self {
            Procedure::Calibrating => (0.25, 1.0),
            Procedure::FineTuning => (PI, 0.5),
        };
        amplitude * (2.0 * PI * hz * t).sin()
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Running {
    procedure: Procedure,
    elapsed: f64,
    origin: f64,
}

/// Why the drive refuses a write it understood (the slave turns these into
/// Modbus exceptions).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// Setpoint to a drive that is not active.
    #[error("the drive is not active: activate it before sending setpoints")]
    NotActive,
    /// A procedure is running.
    #[error("the drive is busy with its {0}: try again when it is done")]
    Busy(&'static str),
    /// Fine-tuning before calibration.
    #[error("fine-tuning needs a calibrated encoder: calibrate first")]
    NotCalibrated,
}

/// Power state.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Power {
    On,
    /// Off or rebooting: silent for the time left, s.
    Booting(f64),
}

/// A snapshot of one simulated drive: what the registers say and what the
/// motor really does.
#[derive(Debug, Clone, PartialEq)]
pub struct SimDriveView {
    /// Bus address now.
    pub address: u8,
    /// False while the drive is off or rebooting (it does not answer).
    pub online: bool,
    /// What a status read returns now.
    pub status: Status,
    /// Control mode.
    pub mode: Mode,
    /// Active flag.
    pub active: bool,
    /// Calibrated flag.
    pub calibrated: bool,
    /// A procedure in progress.
    pub procedure: Option<Procedure>,
    /// Stall latched (needs a fault reset).
    pub stalled: bool,
    /// Fault latched (0 = none).
    pub fault: Fault,
    /// A fault injected by the test harness and not yet cleared.
    pub injected_fault: Option<Fault>,
    /// Emergency brake engaged.
    pub braking: bool,
    /// USE_485_CONTROL.
    pub rs485_control: bool,
    /// The setpoint registers.
    pub setpoints: Setpoints,
    /// Settings in RAM (in force).
    pub settings: Settings,
    /// What flash holds.
    pub flash: Flash,
    /// Gearbox ratio.
    pub gear_ratio: f64,
    /// Output speed, rpm (not rounded).
    pub speed_rpm: f64,
    /// Output position from the zero point, degrees (not wrapped).
    pub position_deg: f64,
    /// Drive current, A.
    pub current_a: f64,
    /// Drive temperature, °C.
    pub temperature_c: f64,
    /// Supply voltage at the drive, V.
    pub bus_voltage_v: f64,
    /// Load, supply and ambient around the drive.
    pub environment: Environment,
    /// Saves written while the motor was moving.
    pub saves_while_moving: u64,
}

/// One simulated drive.
#[derive(Debug, Clone)]
pub struct DriveModel {
    flash: Flash,
    reboot_time: f64,
    power: Power,
    address: u8,
    active: bool,
    calibrated: bool,
    mode: Mode,
    settings: Settings,
    setpoints: Setpoints,
    rs485_control: bool,
    running: Option<Running>,
    braking: bool,
    stalled: bool,
    over_limit_for: f64,
    fault: Fault,
    injected: Option<Fault>,
    /// The zero point, output rad from the encoder's zero.
    zero: f64,
    ramp: Ramp,
    /// The mode whose ramp drove the motor in the last step.
    ramp_engaged: Option<Mode>,
    motor: Motor,
    saves_while_moving: u64,
}

impl DriveModel {
    /// A drive fresh from the factory at `address`, powered on; `calibrated`
    /// says whether its encoder calibration is already in flash;
    /// `reboot_time` (s) is how long it stays silent after a power cycle or
    /// software reset.
    pub fn new(address: u8, gear_ratio: f64, calibrated: bool, reboot_time: f64) -> Self {
        let flash = Flash {
            address,
            active: false,
            calibrated,
            settings: Settings::FACTORY,
        };
        let mut model = DriveModel {
            flash,
            reboot_time: reboot_time.max(0.0),
            power: Power::On,
            address,
            active: false,
            calibrated,
            mode: Mode::OpenLoop,
            settings: Settings::FACTORY,
            setpoints: Setpoints::default(),
            rs485_control: true,
            running: None,
            braking: false,
            stalled: false,
            over_limit_for: 0.0,
            fault: Fault::None,
            injected: None,
            zero: 0.0,
            ramp: Ramp::new(0.0, DEFAULT_RAMP_ALPHA),
            ramp_engaged: None,
            motor: Motor::new(MotorParams::DEFAULT, gear_ratio, Environment::default()),
            saves_while_moving: 0,
        };
        model.boot();
        model
    }

    /// Bus address now.
    pub fn address(&self) -> u8 {
        self.address
    }

    /// False while the drive is off or rebooting: it hears and answers nothing.
    pub fn online(&self) -> bool {
        self.power == Power::On
    }

    /// Loads RAM from flash, as at power-on.
    fn boot(&mut self) {
        self.power = Power::On;
        self.address = self.flash.address;
        self.active = self.flash.active;
        self.calibrated = self.flash.calibrated;
        self.settings = self.flash.settings;
        self.mode = Mode::OpenLoop;
        self.setpoints = Setpoints::default();
        self.rs485_control = true;
        self.running = None;
        self.braking = false;
        self.stalled = false;
        self.over_limit_for = 0.0;
        self.fault = Fault::None;
        self.ramp_engaged = None;
        self.motor
            .set_inertia_ratio(f64::from(self.settings.inertia_ratio));
        // The turn count is lost; the angle within the output turn is absolute.
        let turns = (self.motor.output_angle() / (2.0 * PI)).round();
        self.motor
            .shift_angle(-turns * 2.0 * PI * self.motor.gear_ratio());
        self.zero = 0.0;
        self.check_faults();
    }

    /// Cuts the power: the drive is silent for its reboot time, then comes
    /// back from flash.
    pub fn power_cycle(&mut self) {
        self.power = Power::Booting(self.reboot_time);
        self.running = None;
        if self.reboot_time <= 0.0 {
            self.boot();
        }
    }

    /// Sets the load, supply and ambient around the drive.
    pub fn set_environment(&mut self, env: Environment) {
        self.motor.set_environment(env);
    }

    /// The load, supply and ambient around the drive.
    pub fn environment(&self) -> Environment {
        self.motor.environment()
    }

    /// Injects a hardware fault (current sense, encoder, power stage ...); it
    /// stays until [`clear_injected_fault`](Self::clear_injected_fault), and
    /// the latched fault until a fault reset after that.
    pub fn inject_fault(&mut self, fault: Fault) {
        self.injected = (fault != Fault::None).then_some(fault);
        self.check_faults();
    }

    /// Removes the cause of an injected fault (a fault reset then clears it).
    pub fn clear_injected_fault(&mut self) {
        self.injected = None;
    }

    // ---- registers ----

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
    fn write_register(&mut self, register: Register, value: u16) -> Result<(), Refusal> {
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

    fn set_setpoint(&mut self, set: impl FnOnce(&mut Setpoints), mode: Mode) {
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

    fn set_alpha(&mut self, mode: Mode, alpha: u32) {
        match mode {
            Mode::Speed => self.settings.speed_alpha = alpha,
            _ => self.settings.position_alpha = alpha,
        }
    }

    /// Gives the running ramp its mode's alpha from the settings (no change
    /// when it already has it).
    fn apply_alpha(&mut self) {
        let alpha = match self.ramp_engaged {
            Some(Mode::Speed) => self.settings.speed_alpha,
            Some(Mode::Position) => self.settings.position_alpha,
            _ => return,
        };
        self.ramp.set_alpha(alpha);
    }

    fn save(&mut self, flag: Register) {
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

    fn command(&mut self, command: ConfigCommand) {
        match command {
            ConfigCommand::Activate => {
                self.active = true;
                self.flash.active = true;
            }
            ConfigCommand::Deactivate => {
                self.active = false;
                self.flash.active = false;
            }
            ConfigCommand::Calibrate => self.start(Procedure::Calibrating),
            ConfigCommand::FineTuneCalibration => self.start(Procedure::FineTuning),
            ConfigCommand::SetZero => {
                self.zero = self.motor.output_angle();
                self.setpoints.position_centideg = 0;
                self.ramp_engaged = None; // re-plan in the new frame
            }
            ConfigCommand::EmergencyBrake => {
                self.braking = true;
                self.running = None;
                self.setpoints.speed_rpm = 0;
                self.setpoints.current_counts = 0;
            }
            ConfigCommand::FactoryReset => {
                self.settings = Settings::FACTORY;
                self.flash.settings = Settings::FACTORY;
                self.motor
                    .set_inertia_ratio(f64::from(self.settings.inertia_ratio));
                if let Some(mode) = self.ramp_engaged {
                    self.ramp.set_alpha(self.alpha(mode));
                }
            }
            ConfigCommand::SoftReset => self.power_cycle(),
            ConfigCommand::FaultReset => {
                self.stalled = false;
                self.over_limit_for = 0.0;
                if self.fault != Fault::None && !self.cause_present(self.fault) {
                    self.fault = Fault::None;
                }
                self.check_faults();
            }
            ConfigCommand::SpeedMode => self.enter(Mode::Speed),
            ConfigCommand::PositionMode => self.enter(Mode::Position),
            ConfigCommand::TorqueMode => self.enter(Mode::Torque),
        }
    }

    fn start(&mut self, procedure: Procedure) {
        self.running = Some(Running {
            procedure,
            elapsed: 0.0,
            origin: self.motor.angle(),
        });
    }

    fn enter(&mut self, mode: Mode) {
        self.mode = mode;
        self.braking = false;
    }

    fn alpha(&self, mode: Mode) -> u32 {
        match mode {
            Mode::Speed => self.settings.speed_alpha,
            _ => self.settings.position_alpha,
        }
    }

    /// Where the ramp of `mode` is heading: motor rad/s for speed (converted
    /// with the manual's 9.55), output rad from the zero point for position.
    fn ramp_target(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Speed => {
                f64::from(self.setpoints.speed_rpm) * self.motor.gear_ratio() / RPM_PER_RAD_S
            }
            _ => f64::from(self.setpoints.position_centideg) / 100.0 * PI / 180.0,
        }
    }

    // ---- status ----

    /// The status block as a read returns it now (manual 1.7).
    pub fn status(&self) -> Status {
        let degrees = self.position_deg();
        let turns = (degrees / 360.0).round();
        let angle = ((degrees - 360.0 * turns) * 100.0)
            .round()
            .clamp(-18000.0, 18000.0);
        let speed = (self.motor.speed() * RPM_PER_RAD_S / self.motor.gear_ratio()).round();
        let current = (self.motor.current() * COUNTS_PER_AMP).round();
        Status {
            turns: (turns as i64).rem_euclid(65536) as u16,
            angle_centideg: angle as i16,
            speed_rpm: speed.clamp(-2048.0, 2047.0) as i16,
            current_counts: current.clamp(-2048.0, 2047.0) as i16,
            voltage_v: self.motor.bus_voltage().round().clamp(0.0, 255.0) as u16,
            temperature_c: self.motor.temperature().round().clamp(-128.0, 127.0) as i16,
            flags: Status::flags_from(
                self.active,
                self.calibrated,
                self.stalled,
                self.mode,
                self.fault,
            ),
        }
    }

    /// Output position from the zero point, degrees.
    fn position_deg(&self) -> f64 {
        (self.motor.output_angle() - self.zero).to_degrees()
    }

    /// A snapshot for tests and metrics.
    pub fn view(&self) -> SimDriveView {
        SimDriveView {
            address: self.address,
            online: self.online(),
            status: self.status(),
            mode: self.mode,
            active: self.active,
            calibrated: self.calibrated,
            procedure: self.running.map(|r| r.procedure),
            stalled: self.stalled,
            fault: self.fault,
            injected_fault: self.injected,
            braking: self.braking,
            rs485_control: self.rs485_control,
            setpoints: self.setpoints,
            settings: self.settings,
            flash: self.flash,
            gear_ratio: self.motor.gear_ratio(),
            speed_rpm: self.motor.speed() * RPM_PER_RAD_S / self.motor.gear_ratio(),
            position_deg: self.position_deg(),
            current_a: self.motor.current(),
            temperature_c: self.motor.temperature(),
            bus_voltage_v: self.motor.bus_voltage(),
            environment: self.motor.environment(),
            saves_while_moving: self.saves_while_moving,
        }
    }

    /// The shaped command of the active ramp, if one drives the motor:
    /// motor rad/s in speed mode, output rad in position mode.
    pub fn ramp(&self) -> Option<(Mode, &Ramp)> {
        self.ramp_engaged.map(|mode| (mode, &self.ramp))
    }

    // ---- time ----

    /// Advances the drive by `dt` seconds: 1 ms steps while anything moves,
    /// long exact steps while only the temperature changes.
    pub fn advance(&mut self, dt: f64) {
        let mut left = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
        let mut resting = false;
        while left > 0.0 {
            if resting {
                let h = left.min(self.rest_limit());
                let before = (self.fault, self.stalled, self.power == Power::On);
                self.rest(h);
                left -= h;
                resting = before == (self.fault, self.stalled, self.power == Power::On);
            } else {
                let h = left.min(MAX_STEP);
                let before = (self.motor.angle(), self.motor.speed(), self.motor.current());
                self.step(h);
                left -= h;
                resting = self.is_still(before);
            }
        }
    }

    /// True when the last step changed nothing but heat: the same step would
    /// do the same again.
    fn is_still(&self, before: (f64, f64, f64)) -> bool {
        before.1 == 0.0
            && self.motor.speed() == 0.0
            && self.motor.angle() == before.0
            && self.motor.current() == before.2
            && self.running.is_none()
            && (self.ramp_engaged.is_none() || self.ramp.settled())
    }

    /// Longest rest step that cannot skip over a timer.
    fn rest_limit(&self) -> f64 {
        let mut limit = REST_STEP;
        if let Power::Booting(left) = self.power {
            limit = limit.min(left.max(MAX_STEP));
        }
        if self.over_limit_for > 0.0 {
            let trip = f64::from(self.settings.stall_duration_ms) / 1000.0 - self.over_limit_for;
            limit = limit.min(trip.max(MAX_STEP));
        }
        limit
    }

    fn tick_power(&mut self, h: f64) {
        if let Power::Booting(left) = self.power {
            let left = left - h;
            if left <= 1e-12 {
                self.boot();
            } else {
                self.power = Power::Booting(left);
            }
        }
    }

    fn rest(&mut self, h: f64) {
        self.tick_power(h);
        self.motor.hold(h);
        self.after_motion(h);
    }

    fn step(&mut self, h: f64) {
        self.tick_power(h);
        let drive = self.demand(h);
        self.motor.step(drive, h);
        self.after_motion(h);
    }

    /// The mode whose ramp should drive the motor now, if any.
    fn ramp_mode(&self) -> Option<Mode> {
        let driving = self.online()
            && self.active
            && !self.stalled
            && self.fault == Fault::None
            && self.running.is_none()
            && !self.braking;
        match self.mode {
            Mode::Speed | Mode::Position if driving => Some(self.mode),
            _ => None,
        }
    }

    /// What the power stage is asked to do for the next `h` seconds.
    fn demand(&mut self, h: f64) -> Drive {
        let engaged = self.ramp_mode();
        if engaged != self.ramp_engaged {
            if let Some(mode) = engaged {
                // Bumpless hand-over: start the ramp where the motor is.
                let (value, rate) = match mode {
                    Mode::Speed => (self.motor.speed(), 0.0),
                    _ => (
                        self.motor.output_angle() - self.zero,
                        self.motor.output_speed(),
                    ),
                };
                self.ramp = Ramp::new(value, self.alpha(mode));
                self.ramp.restart_from(value, rate);
                self.ramp.set_target(self.ramp_target(mode));
            }
            self.ramp_engaged = engaged;
        }
        if !self.online() {
            return Drive::Off;
        }
        if self.stalled || self.fault != Fault::None {
            self.running = None; // a fault aborts calibration
            return Drive::Off;
        }
        let r = self.motor.gear_ratio();
        if let Some(running) = self.running.as_mut() {
            running.elapsed += h;
            let running = *running;
            if running.elapsed >= running.procedure.duration() {
                self.running = None;
                if running.procedure == Procedure::Calibrating {
                    self.calibrated = true;
                    self.flash.calibrated = true;
                }
            } else {
                let offset = running.procedure.trajectory(running.elapsed);
                let speed = control::position_loop(running.origin + offset, self.motor.angle());
                return Drive::Accelerate(control::speed_loop(speed, self.motor.speed(), h));
            }
        }
        if !self.active {
            return Drive::Off;
        }
        if self.braking {
            return Drive::Accelerate(control::brake(self.motor.speed(), h));
        }
        match self.ramp_engaged {
            Some(Mode::Speed) => {
                self.ramp.advance(h);
                Drive::Accelerate(control::speed_loop(
                    self.ramp.value(),
                    self.motor.speed(),
                    h,
                ))
            }
            Some(_) => {
                self.ramp.advance(h);
                let command = (self.ramp.value() + self.zero) * r;
                let speed = control::position_loop(command, self.motor.angle());
                Drive::Accelerate(control::speed_loop(speed, self.motor.speed(), h))
            }
            None => match self.mode {
                Mode::Torque => {
                    Drive::Current(f64::from(self.setpoints.current_counts) / COUNTS_PER_AMP)
                }
                _ => Drive::Off, // open loop: no voltage register, the stage idles
            },
        }
    }

    /// Stall protection, faults and the brake's hold point after a step.
    fn after_motion(&mut self, h: f64) {
        let counts = (self.motor.current() * COUNTS_PER_AMP).abs();
        if counts > f64::from(self.settings.stall_current) && !self.stalled {
            self.over_limit_for += h;
            if self.over_limit_for * 1000.0 > f64::from(self.settings.stall_duration_ms) {
                self.stalled = true;
                self.over_limit_for = 0.0;
            }
        } else {
            self.over_limit_for = 0.0;
        }
        if self.braking {
            // Hold where the brake stopped the motor when it is released.
            let centideg = (self.position_deg() * 100.0)
                .round()
                .clamp(-18000.0, 18000.0);
            self.setpoints.position_centideg = centideg as i16;
        }
        self.check_faults();
    }

    /// Whether the condition behind `fault` is still there.
    fn cause_present(&self, fault: Fault) -> bool {
        if self.injected == Some(fault) {
            return true;
        }
        match fault {
            Fault::OverTemperature => self.motor.temperature() >= TEMPERATURE_RECOVERED,
            Fault::UnderVoltage => self.motor.bus_voltage() < UNDER_VOLTAGE,
            Fault::OverVoltage => self.motor.bus_voltage() > OVER_VOLTAGE,
            _ => false,
        }
    }

    /// Latches the first fault whose trip condition holds.
    fn check_faults(&mut self) {
        if self.fault != Fault::None || !self.online() {
            return;
        }
        let t = self.motor.temperature();
        let v = self.motor.bus_voltage();
        self.fault = if let Some(injected) = self.injected {
            injected
        } else if t > OVER_TEMPERATURE {
            Fault::OverTemperature
        } else if v < UNDER_VOLTAGE {
            Fault::UnderVoltage
        } else if v > OVER_VOLTAGE {
            Fault::OverVoltage
        } else {
            Fault::None
        };
    }
}

/// Position of a status register in the status block (manual 1.7).
fn status_index(register: Register) -> Option<usize> {
    let offset = register.address().checked_sub(STATUS_BLOCK_START)?;
    let index = usize::from(offset / 2);
    (index < usize::from(STATUS_BLOCK_LEN)).then_some(index)
}

#[cfg(test)]
mod tests;
