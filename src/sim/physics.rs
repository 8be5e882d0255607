//! The motor behind a simulated drive: a permanent-magnet servo with a
//! gearbox, its supply and its heat. Pure code, time passed in.
//!
//! Everything is at the motor shaft unless a name says "output" (the gearbox
//! output, where the manual's speeds and angles are given). The figures in
//! [`MotorParams::DEFAULT`] are those of a small 24 V servo of the kind the
//! manual describes (current sensing to 16 A, "most motors within
//! 1000 rpm" at the output): they make the numbers the drive reports
//! plausible, they are not a datasheet.

/// Electrical, mechanical and thermal constants of the simulated motor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MotorParams {
    /// Torque constant, N·m/A (equal to the back-EMF constant in V·s/rad).
    pub torque_constant: f64,
    /// Winding resistance, ohm.
    pub resistance: f64,
    /// Rotor inertia, kg·m^2; the load adds `ratio` times this (manual 1.11).
    pub rotor_inertia: f64,
    /// Dry friction at the motor shaft, N·m.
    pub coulomb_friction: f64,
    /// Viscous friction at the motor shaft, N·m per rad/s.
    pub viscous_friction: f64,
    /// Largest current the drive can sense and drive: 2047 counts, A.
    pub max_current: f64,
    /// Drive and motor to ambient, K/W.
    pub thermal_resistance: f64,
    /// Heat capacity, J/K (thermal time constant = resistance x capacity).
    pub thermal_capacity: f64,
    /// Losses of the electronics while the power stage is on, W.
    pub idle_power: f64,
    /// Resistance of the supply and its wiring, ohm: the bus sags under load.
    pub source_resistance: f64,
    /// Supply current of the logic alone, A.
    pub logic_current: f64,
}

impl MotorParams {
    /// The simulated motor: no-load speed about 4000 rpm at 24 V, stalls at
    /// 16 A with 0.9 N·m, one minute thermal time constant.
    pub(crate) const DEFAULT: MotorParams = MotorParams {
        torque_constant: 0.057,
        resistance: 0.4,
        rotor_inertia: 3.0e-5,
        coulomb_friction: 0.004,
        viscous_friction: 2.0e-5,
        max_current: 2047.0 / 128.0,
        thermal_resistance: 1.5,
        thermal_capacity: 40.0,
        idle_power: 1.0,
        source_resistance: 0.3,
        logic_current: 0.05,
    };
}

/// Below this speed (rad/s) dry friction can hold the shaft still.
const STANDSTILL: f64 = 1e-6;

/// What the drive's power stage does during a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Drive {
    /// Power stage off: the motor coasts against friction and load.
    Off,
    /// Current loop: drive this current (A), within what the supply allows.
    Current(f64),
    /// Speed loop output: the acceleration wanted (rad/s^2); the current is
    /// what that takes against inertia, friction and load.
    Accelerate(f64),
}

/// The world around the drive, set by tests and the fault suite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Environment {
    /// Load torque at the gearbox output, N·m (positive opposes forward motion).
    pub load_torque: f64,
    /// Open-circuit supply voltage, V (24 V nominal).
    pub supply_voltage: f64,
    /// Ambient temperature, °C.
    pub ambient: f64,
}

impl Default for Environment {
    fn default() -> Self {
        Environment {
            load_torque: 0.0,
            supply_voltage: 24.0,
            ambient: 25.0,
        }
    }
}

/// The state of the motor, its supply and its temperature.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Motor {
    params: MotorParams,
    gear_ratio: f64,
    inertia_ratio: f64,
    /// Motor shaft angle from the encoder's zero, rad (continuous).
    angle: f64,
    /// Motor shaft speed, rad/s.
    speed: f64,
    /// Drive current (q axis), A.
    current: f64,
    /// Drive temperature, °C.
    temperature: f64,
    /// Supply voltage at the drive's terminals, V.
    bus_voltage: f64,
    /// Environment.
    env: Environment,
    powered: bool,
}

impl Motor {
    /// A motor at rest at ambient temperature.
    pub(crate) fn new(params: MotorParams, gear_ratio: f64, env: Environment) -> Self {
        Motor {
            params,
            gear_ratio,
            inertia_ratio: 1.0,
            angle: 0.0,
            speed: 0.0,
            current: 0.0,
            temperature: env.ambient,
            bus_voltage: env.supply_voltage,
            env,
            powered: false,
        }
    }

    /// The gearbox ratio (motor turns per output turn).
    pub(crate) fn gear_ratio(&self) -> f64 {
        self.gear_ratio
    }

    /// Sets the load inertia as a multiple of the rotor's (manual 1.11).
    pub(crate) fn set_inertia_ratio(&mut self, ratio: f64) {
        self.inertia_ratio = ratio.max(0.0);
    }

    /// Total inertia at the motor shaft: rotor x (1 + load ratio).
    pub(crate) fn inertia(&self) -> f64 {
        self.params.rotor_inertia * (1.0 + self.inertia_ratio)
    }

    /// The environment.
    pub(crate) fn environment(&self) -> Environment {
        self.env
    }

    /// Changes the environment (load, supply, ambient).
    pub(crate) fn set_environment(&mut self, env: Environment) {
        self.env = env;
    }

    /// Motor shaft angle, rad.
    pub(crate) fn angle(&self) -> f64 {
        self.angle
    }

    /// Moves the motor shaft angle by whole output turns (the drive forgets
    /// its turn count at power-off); `delta` in rad at the motor shaft.
    pub(crate) fn shift_angle(&mut self, delta: f64) {
        self.angle += delta;
    }

    /// Motor shaft speed, rad/s.
    pub(crate) fn speed(&self) -> f64 {
        self.speed
    }

    /// Output angle, rad.
    pub(crate) fn output_angle(&self) -> f64 {
        self.angle / self.gear_ratio
    }

    /// Output speed, rad/s.
    pub(crate) fn output_speed(&self) -> f64 {
        self.speed / self.gear_ratio
    }

    /// Drive current, A.
    pub(crate) fn current(&self) -> f64 {
        self.current
    }

    /// Drive temperature, °C.
    pub(crate) fn temperature(&self) -> f64 {
        self.temperature
    }

    /// Voltage at the drive's supply terminals, V.
    pub(crate) fn bus_voltage(&self) -> f64 {
        self.bus_voltage
    }

    /// Load torque seen at the motor shaft (ideal gearbox), N·m.
    fn load_at_motor(&self) -> f64 {
        self.env.load_torque / self.gear_ratio
    }

    /// Dry and viscous friction opposing motion at `speed`.
    fn friction(&self, speed: f64) -> f64 {
        if speed.abs() <= STANDSTILL {
            0.0
        } else {
            self.params.coulomb_friction * speed.signum() + self.params.viscous_friction * speed
        }
    }

    /// Advances the motor by `dt` seconds (the caller keeps `dt` at 1 ms or less
    /// while anything moves).
    pub(crate) fn step(&mut self, drive: Drive, dt: f64) {
        let p = self.params;
        let j = self.inertia();
        let load = self.load_at_motor();
        self.powered = !matches!(drive, Drive::Off);
        let wanted = match drive {
            Drive::Off => 0.0,
            Drive::Current(amps) => amps,
            Drive::Accelerate(accel) => {
                // Feed-forward of inertia, friction and load: what the speed
                // loop's integral settles to.
                let friction = if self.speed.abs() > STANDSTILL {
                    self.friction(self.speed)
                } else if accel.abs() > 1e-9 {
                    // Break away from standstill, as the loop's integral would.
                    p.coulomb_friction * accel.signum()
                } else {
                    0.0
                };
                (j * accel + friction + load) / p.torque_constant
            }
        };
        self.current = if self.powered {
            self.limit_current(wanted)
        } else {
            0.0
        };

        // Mechanics, with dry friction able to hold the shaft still.
        let drive_torque = p.torque_constant * self.current - load;
        let speed = if self.speed.abs() <= STANDSTILL && drive_torque.abs() <= p.coulomb_friction {
            0.0
        } else {
            let friction_dir = if self.speed.abs() > STANDSTILL {
                self.speed.signum()
            } else {
                drive_torque.signum()
            };
            let friction = p.coulomb_friction * friction_dir + p.viscous_friction * self.speed;
            let next = self.speed + (drive_torque - friction) / j * dt;
            // Friction stops the shaft, it never reverses it.
            if next.signum() != self.speed.signum()
                && self.speed.abs() > STANDSTILL
                && drive_torque.abs() <= p.coulomb_friction
            {
                0.0
            } else {
                next
            }
        };
        self.angle += 0.5 * (self.speed + speed) * dt;
        self.speed = speed;
        self.heat(dt);
    }

    /// Advances a motor that stands still with a constant current (nothing
    /// but temperature changes): any `dt`, exact.
    pub(crate) fn hold(&mut self, dt: f64) {
        self.heat(dt);
    }

    /// Clamps a wanted current to the drive's range and to what the supply
    /// can push against the back-EMF.
    fn limit_current(&self, wanted: f64) -> f64 {
        let p = self.params;
        let emf = p.torque_constant * self.speed;
        let v = self.bus_voltage.max(0.0);
        let high = ((v - emf) / p.resistance).min(p.max_current);
        let low = ((-v - emf) / p.resistance).max(-p.max_current);
        if !wanted.is_finite() {
            return 0.0;
        }
        if low > high {
            return 0.0;
        }
        wanted.clamp(low, high)
    }

    /// Temperature (exact first-order step) and supply sag for the present current.
    fn heat(&mut self, dt: f64) {
        let p = self.params;
        let copper = self.current * self.current * p.resistance;
        let idle = if self.powered { p.idle_power } else { 0.0 };
        let steady = self.env.ambient + (copper + idle) * p.thermal_resistance;
        let tau = p.thermal_resistance * p.thermal_capacity;
        self.temperature = steady + (self.temperature - steady) * (-dt / tau).exp();

        // Electrical power drawn (negative while braking regeneratively).
        let mechanical = p.torque_constant * self.speed * self.current;
        let supply = self.env.supply_voltage.max(1.0);
        let current_in = p.logic_current + (copper + idle + mechanical) / supply;
        self.bus_voltage = (self.env.supply_voltage - current_in * p.source_resistance).max(0.0);
    }

    /// True when the shaft stands still.
    pub(crate) fn at_standstill(&self) -> bool {
        self.speed == 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn motor() -> Motor {
        Motor::new(MotorParams::DEFAULT, 3.75, Environment::default())
    }

    #[test]
    fn coasts_to_a_stop_without_reversing() {
        let mut m = motor();
        for _ in 0..100 {
            m.step(Drive::Current(5.0), 0.001);
        }
        assert!(m.speed() > 10.0);
        let mut t = 0;
        while !m.at_standstill() {
            m.step(Drive::Off, 0.001);
            assert!(m.speed() >= 0.0);
            t += 1;
            assert!(t < 100_000);
        }
        assert_eq!(m.current(), 0.0);
    }

    #[test]
    fn torque_accelerates_up_to_the_back_emf_limit() {
        let mut m = motor();
        for _ in 0..5000 {
            m.step(Drive::Current(4.0), 0.001);
        }
        // No-load speed is about 24 V / 0.057 = 421 rad/s; friction and
        // the supply sag keep it a little lower.
        let top = m.speed();
        assert!(top > 300.0 && top < 421.0, "{top}");
        assert!(
            m.current() < 4.0,
            "the back-EMF leaves less current: {}",
            m.current()
        );
    }

    #[test]
    fn dry_friction_holds_a_small_torque() {
        let mut m = motor();
        m.step(Drive::Current(0.05), 0.001); // 2.85 mN·m < 4 mN·m of friction
        assert_eq!(m.speed(), 0.0);
    }

    #[test]
    fn load_torque_turns_a_free_shaft_backwards() {
        let mut m = motor();
        m.set_environment(Environment {
            load_torque: 0.5,
            ..Environment::default()
        });
        for _ in 0..100 {
            m.step(Drive::Off, 0.001);
        }
        assert!(m.speed() < 0.0);
    }

    #[test]
    fn heats_towards_the_steady_temperature_and_sags_the_supply() {
        let mut m = motor();
        // A load that balances 15 A exactly: the shaft stays still.
        let p = MotorParams::DEFAULT;
        m.set_environment(Environment {
            load_torque: 15.0 * p.torque_constant * 3.75,
            ..Environment::default()
        });
        for _ in 0..60 {
            m.step(Drive::Current(15.0), 0.001);
            assert_eq!(m.speed(), 0.0);
            m.hold(1.0);
        }
        // 90 W of copper + 1 W idle at 1.5 K/W: 161.5 °C steady, one time
        // constant (60 s) gets 63 % of the way.
        let t = m.temperature();
        assert!((t - (25.0 + 136.5 * 0.632)).abs() < 3.0, "{t}");
        assert!(m.bus_voltage() < 23.0, "{}", m.bus_voltage());
    }
}
