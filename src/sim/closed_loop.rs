//! The drive's closed loops: what acceleration the power stage is asked for
//! so the motor follows the shaped command. Pure code.
//!
//! Both loops are first-order followers, discretised exactly so they stay
//! stable at any step. Their time constants are set so the motor lags the
//! ramp about as much as the manual's measurements show (speed: 0.207 s
//! actual for 0.2047 s planned; position: 0.275 s for 0.2507 s).

/// Time constant of the speed loop, s.
pub(crate) const SPEED_LOOP_TAU: f64 = 0.003;
/// Time constant of the position loop (around the speed loop), s.
pub(crate) const POSITION_LOOP_TAU: f64 = 0.013;

/// Fraction of the error a first-order loop with time constant `tau`
/// removes in `dt`.
fn gain(dt: f64, tau: f64) -> f64 {
    if dt <= 0.0 {
        0.0
    } else {
        1.0 - (-dt / tau).exp()
    }
}

/// Speed loop: the acceleration (rad/s^2) that brings `speed` towards
/// `command` (both rad/s at the motor shaft) over the next `dt`.
pub(crate) fn speed_loop(command: f64, speed: f64, dt: f64) -> f64 {
    if dt <= 0.0 {
        return 0.0;
    }
    (command - speed) * gain(dt, SPEED_LOOP_TAU) / dt
}

/// Position loop: the speed command (rad/s at the motor shaft) that brings
/// `angle` to `command` (rad at the motor shaft). Without feed-forward of the
/// command's rate the motor trails a moving command by about the loop's
/// time constant, as the manual's position measurements show.
pub(crate) fn position_loop(command: f64, angle: f64) -> f64 {
    (command - angle) / POSITION_LOOP_TAU
}

/// Emergency brake: the largest deceleration the drive can ask for; the
/// current limit decides what the motor really does.
pub(crate) fn brake(speed: f64, dt: f64) -> f64 {
    if dt <= 0.0 { 0.0 } else { -speed / dt }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loops_pull_towards_the_command() {
        assert!(speed_loop(10.0, 0.0, 0.001) > 0.0);
        assert!(speed_loop(-10.0, 0.0, 0.001) < 0.0);
        assert_eq!(speed_loop(5.0, 5.0, 0.001), 0.0);
        // Never overshoots in one step, whatever the step.
        for dt in [1e-5, 1e-3, 1.0] {
            let accel = speed_loop(10.0, 0.0, dt);
            assert!(accel * dt <= 10.0);
        }
        assert_eq!(position_loop(1.0, 1.0), 0.0);
        assert!(position_loop(1.0, 0.0) > 0.0);
        assert_eq!(brake(0.0, 0.001), 0.0);
    }
}
