//! The drive's setpoint ramp (manual 1.9, 1.10): a time-optimal bang-bang
//! shaper.
//!
//! The register names (`SPEED_TD_R_*`, `POSITION_TD_R_*`) say "tracking
//! differentiator, speed factor r": the shaped command `x` is a double
//! integrator whose second derivative is limited to `±alpha`, driven to the
//! target along the fastest path (accelerate with `+alpha`, then brake with
//! `-alpha`). From standstill over a distance `d` this takes
//! `t = 2 * sqrt(d / alpha)`, which is the manual's formulas (2) and (3):
//! - speed mode: `x` is the motor's speed command in rad/s (so `d = r * n_ref
//!   / 9.55`) and alpha is in rad/s^3;
//! - position mode: `x` is the output angle command in rad (`d = pi *
//!   theta_ref / 180`) and alpha is in rad/s^2.
//!
//! The profile is computed in closed form, not integrated, so the rise time
//! does not depend on the step size. A new target or alpha mid-ramp re-plans
//! from the current value and rate: the command never jumps.

/// One constant-acceleration piece of a plan.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Phase {
    /// Second derivative of the command during the phase.
    accel: f64,
    /// Time left in the phase, s.
    left: f64,
}

impl Phase {
    const DONE: Phase = Phase {
        accel: 0.0,
        left: 0.0,
    };
}

/// A setpoint shaper with peak second derivative `alpha` (0 = ramp off).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ramp {
    value: f64,
    rate: f64,
    target: f64,
    alpha: f64,
    phases: [Phase; 2],
}

impl Ramp {
    /// A ramp resting at `value`.
    pub fn new(value: f64, alpha: u32) -> Self {
        Ramp {
            value,
            rate: 0.0,
            target: value,
            alpha: f64::from(alpha),
            phases: [Phase::DONE; 2],
        }
    }

    /// The shaped command.
    pub fn value(&self) -> f64 {
        self.value
    }

    /// The shaped command's first derivative.
    pub fn rate(&self) -> f64 {
        self.rate
    }

    /// Where the ramp is going.
    pub fn target(&self) -> f64 {
        self.target
    }

    /// True when the command has reached its target and stopped.
    pub fn settled(&self) -> bool {
        self.phases.iter().all(|p| p.left <= 0.0) && self.value == self.target && self.rate == 0.0
    }

    /// Time left until the command settles on its target, s.
    pub fn time_left(&self) -> f64 {
        self.phases.iter().map(|p| p.left.max(0.0)).sum()
    }

    /// Aims at a new target, re-planning from the current value and rate.
    pub fn set_target(&mut self, target: f64) {
        if target != self.target || !self.settled() {
            self.target = target;
            self.plan();
        }
    }

    /// Changes alpha, re-planning the rest of the way.
    pub fn set_alpha(&mut self, alpha: u32) {
        let alpha = f64::from(alpha);
        if alpha != self.alpha {
            self.alpha = alpha;
            self.plan();
        }
    }

    /// Restarts the command from `value` moving at `rate` (bumpless hand-over
    /// from whatever the motor is doing), keeping the target.
    pub fn restart_from(&mut self, value: f64, rate: f64) {
        self.value = value;
        self.rate = rate;
        self.plan();
    }

    /// Advances the command by `dt` seconds.
    pub fn advance(&mut self, dt: f64) {
        let mut left = dt.max(0.0);
        for phase in self.phases.iter_mut() {
            if left <= 0.0 {
                break;
            }
            if phase.left <= 0.0 {
                continue;
            }
            let t = left.min(phase.left);
            self.value += self.rate * t + 0.5 * phase.accel * t * t;
            self.rate += phase.accel * t;
            phase.left -= t;
            left -= t;
        }
        if self.phases.iter().all(|p| p.left <= 0.0) {
            // Land exactly: the closed form leaves rounding dust.
            self.value = self.target;
            self.rate = 0.0;
        }
    }

    /// The fastest path from (value, rate) to (target, 0) with |accel| <= alpha.
    fn plan(&mut self) {
        self.phases = [Phase::DONE; 2];
        let a = self.alpha;
        if a <= 0.0 || !a.is_finite() {
            // alpha 0 turns the ramp off: the command steps.
            self.value = self.target;
            self.rate = 0.0;
            return;
        }
        let e = self.value - self.target;
        let v = self.rate;
        if e == 0.0 && v == 0.0 {
            return;
        }
        // Switching function: s = 0 on the braking curve that ends at rest on
        // the target; above it the command must first accelerate downwards.
        let s = e + v * v.abs() / (2.0 * a);
        if s == 0.0 {
            self.phases[0] = Phase {
                accel: -v.signum() * a,
                left: v.abs() / a,
            };
            return;
        }
        let sign = s.signum();
        // Mirror into the case s > 0 (first phase at -a).
        let (e, v) = (sign * e, sign * v);
        let c = e + v * v / (2.0 * a); // invariant of the first phase, > 0
        let v_switch = -(a * c).sqrt();
        self.phases = [
            Phase {
                accel: -sign * a,
                left: ((v - v_switch) / a).max(0.0),
            },
            Phase {
                accel: sign * a,
                left: -v_switch / a,
            },
        ];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::units;

    const DT: f64 = 0.001;

    /// Steps a ramp in 1 ms until it settles; returns the time taken.
    fn run_until_settled(ramp: &mut Ramp) -> f64 {
        let mut t = 0.0;
        while !ramp.settled() {
            ramp.advance(DT);
            t += DT;
            assert!(t < 100.0, "ramp never settled");
        }
        t
    }

    #[test]
    fn speed_ramp_matches_formula_2() {
        // Manual 1.9: alpha 5000, 133 rpm, r 3.75 -> 0.2047 s; alpha 10 -> 4.5765 s.
        for (alpha, expected) in [(5000, 0.2047), (10, 4.5765)] {
            let motor_rad_s = 3.75 * (500.0 / 3.75) / units::RPM_PER_RAD_S;
            let mut ramp = Ramp::new(0.0, alpha);
            ramp.set_target(motor_rad_s);
            let planned = ramp.time_left();
            assert!((planned - expected).abs() / expected < 0.001, "{planned}");
            let t = run_until_settled(&mut ramp);
            assert!(
                (t - expected).abs() <= DT,
                "alpha {alpha}: {t} s vs {expected} s"
            );
            assert_eq!(ramp.value(), motor_rad_s);
        }
    }

    #[test]
    fn position_ramp_matches_formula_3() {
        // Manual 1.10: alpha 200, 180 deg -> 0.2507 s; alpha 10 -> 1.121 s.
        for (alpha, expected) in [(200, 0.2507), (10, 1.121)] {
            let mut ramp = Ramp::new(0.0, alpha);
            ramp.set_target(std::f64::consts::PI);
            let t = run_until_settled(&mut ramp);
            assert!(
                (t - expected).abs() <= DT + 0.0005,
                "alpha {alpha}: {t} s vs {expected} s"
            );
        }
    }

    #[test]
    fn peak_acceleration_is_alpha() {
        let mut ramp = Ramp::new(0.0, 200);
        ramp.set_target(1.0);
        let mut last_rate = 0.0;
        while !ramp.settled() {
            ramp.advance(DT);
            let accel = (ramp.rate() - last_rate) / DT;
            assert!(accel.abs() <= 200.0 + 1e-6, "{accel}");
            last_rate = ramp.rate();
        }
    }

    #[test]
    fn retarget_mid_ramp_replans_without_a_jump() {
        let mut ramp = Ramp::new(0.0, 1000);
        ramp.set_target(10.0);
        for _ in 0..50 {
            ramp.advance(DT);
        }
        let (value, rate) = (ramp.value(), ramp.rate());
        assert!(value > 0.0 && rate > 0.0);
        // Reverse: the command keeps its value and rate, brakes and comes back.
        ramp.set_target(-5.0);
        assert_eq!((ramp.value(), ramp.rate()), (value, rate));
        // Time-optimal from (value, rate): brake to 0 then go to -5.
        let expected = ramp.time_left();
        let mut max_value = value;
        let mut prev = value;
        let mut t = 0.0;
        while !ramp.settled() {
            ramp.advance(DT);
            t += DT;
            let step = (ramp.value() - prev).abs();
            assert!(step <= 1000.0 * 0.05 * DT * 2.0 + 1e-9, "jump of {step}");
            prev = ramp.value();
            max_value = max_value.max(ramp.value());
        }
        assert_eq!(ramp.value(), -5.0);
        assert!((t - expected).abs() <= DT, "{t} vs {expected}");
        // It overshoots only by its braking distance: rate^2 / (2 alpha).
        assert!(max_value <= value + rate * rate / 2000.0 + 1e-9);
    }

    #[test]
    fn retarget_to_a_closer_target_in_the_same_direction() {
        let mut ramp = Ramp::new(0.0, 1000);
        ramp.set_target(10.0);
        for _ in 0..60 {
            ramp.advance(DT);
        }
        ramp.set_target(ramp.value() + 0.1);
        run_until_settled(&mut ramp);
        assert!((ramp.value() - ramp.target()).abs() < 1e-12);
    }

    #[test]
    fn alpha_zero_steps_and_alpha_change_replans() {
        let mut ramp = Ramp::new(0.0, 0);
        ramp.set_target(42.0);
        assert_eq!(ramp.value(), 42.0);
        assert!(ramp.settled());

        let mut ramp = Ramp::new(0.0, 10);
        ramp.set_target(1.0);
        let slow = ramp.time_left();
        ramp.advance(0.1);
        ramp.set_alpha(1000);
        assert!(ramp.time_left() < slow / 5.0);
        ramp.set_alpha(0);
        assert_eq!(ramp.value(), 1.0);
    }

    #[test]
    fn restart_from_a_moving_state() {
        let mut ramp = Ramp::new(0.0, 100);
        ramp.set_target(0.0);
        ramp.restart_from(1.0, -2.0);
        assert_eq!((ramp.value(), ramp.rate()), (1.0, -2.0));
        run_until_settled(&mut ramp);
        assert_eq!(ramp.value(), 0.0);
    }
}
