//! The CONFIG register's commands (manual 1.3): activation, calibration,
//! zero point, emergency brake, resets and the mode changes, and the mode
//! the motor is driven in after each.

use super::*;

impl DriveModel {
    pub(super) fn command(&mut self, command: ConfigCommand) {
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

    pub(super) fn start(&mut self, procedure: Procedure) {
        self.running = Some(Running {
            procedure,
            elapsed: 0.0,
            origin: self.motor.angle(),
        });
    }

    pub(super) fn enter(&mut self, mode: Mode) {
        self.mode = mode;
        self.braking = false;
    }

    pub(super) fn alpha(&self, mode: Mode) -> u32 {
        match mode {
            Mode::Speed => self.settings.speed_alpha,
            _ => self.settings.position_alpha,
        }
    }

    /// Where the ramp of `mode` is heading: motor rad/s for speed (converted
    /// with the manual's 9.55), output rad from the zero point for position.
    pub(super) fn ramp_target(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Speed => {
                f64::from(self.setpoints.speed_rpm) * self.motor.gear_ratio() / RPM_PER_RAD_S
            }
            _ => f64::from(self.setpoints.position_centideg) / 100.0 * PI / 180.0,
        }
    }
}
