//! Time passing: the drive's power, the ramps and the motor's motion in
//! 1 ms steps (long exact steps at rest), and the protections that raise
//! and clear faults (manual 1.8 to 1.12).

use super::*;

impl DriveModel {
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
    pub(super) fn is_still(&self, before: (f64, f64, f64)) -> bool {
        before.1 == 0.0
            && self.motor.speed() == 0.0
            && self.motor.angle() == before.0
            && self.motor.current() == before.2
            && self.running.is_none()
            && (self.ramp_engaged.is_none() || self.ramp.settled())
    }

    /// Longest rest step that cannot skip over a timer.
    pub(super) fn rest_limit(&self) -> f64 {
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

    pub(super) fn tick_power(&mut self, h: f64) {
        if let Power::Booting(left) = self.power {
            let left = left - h;
            if left <= 1e-12 {
                self.boot();
            } else {
                self.power = Power::Booting(left);
            }
        }
    }

    pub(super) fn rest(&mut self, h: f64) {
        self.tick_power(h);
        self.motor.hold(h);
        self.after_motion(h);
    }

    pub(super) fn step(&mut self, h: f64) {
        self.tick_power(h);
        let drive = self.demand(h);
        self.motor.step(drive, h);
        self.after_motion(h);
    }

    /// The mode whose ramp should drive the motor now, if any.
    pub(super) fn ramp_mode(&self) -> Option<Mode> {
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
    pub(super) fn demand(&mut self, h: f64) -> Drive {
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
                let speed = closed_loop::position_loop(running.origin + offset, self.motor.angle());
                return Drive::Accelerate(closed_loop::speed_loop(speed, self.motor.speed(), h));
            }
        }
        if !self.active {
            return Drive::Off;
        }
        if self.braking {
            return Drive::Accelerate(closed_loop::brake(self.motor.speed(), h));
        }
        match self.ramp_engaged {
            Some(Mode::Speed) => {
                self.ramp.advance(h);
                Drive::Accelerate(closed_loop::speed_loop(
                    self.ramp.value(),
                    self.motor.speed(),
                    h,
                ))
            }
            Some(_) => {
                self.ramp.advance(h);
                let command = (self.ramp.value() + self.zero) * r;
                let speed = closed_loop::position_loop(command, self.motor.angle());
                Drive::Accelerate(closed_loop::speed_loop(speed, self.motor.speed(), h))
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
    pub(super) fn after_motion(&mut self, h: f64) {
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
    pub(super) fn cause_present(&self, fault: Fault) -> bool {
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
    pub(super) fn check_faults(&mut self) {
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
