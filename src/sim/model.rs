//! One simulated drive: its registers, RAM and flash, config commands,
//! control modes, protections and faults (manual 1.2 to 1.12). Pure code:
//! time is passed in with [`DriveModel::advance`].
//!
//! This file holds the drive's state and its status block; `registers`
//! reads and writes it as the bus does, `commands` carries out the CONFIG
//! commands, `motion` moves the motor and raises the faults.
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

use super::closed_loop;
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

    /// Swaps the drive for a new one of the same kind, fresh from the
    /// factory and given this one's address (as a technician does before
    /// fitting it): silent for its reboot time, then back with the factory
    /// settings, inactive. Its encoder calibration is as this one's.
    pub fn replace(&mut self) {
        self.flash.settings = Settings::FACTORY;
        self.flash.active = false;
        self.saves_while_moving = 0;
        self.power_cycle();
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
}

/// Position of a status register in the status block (manual 1.7).
fn status_index(register: Register) -> Option<usize> {
    let offset = register.address().checked_sub(STATUS_BLOCK_START)?;
    let index = usize::from(offset / 2);
    (index < usize::from(STATUS_BLOCK_LEN)).then_some(index)
}

mod config_register;
mod motion;
mod registers;
#[cfg(test)]
mod tests;
