//! Plain example tests: each bug the model found, as the shrunk case that
//! showed it, replayed through the same world.

use super::run_case;
use super::steps::{Cmd, Who};
use super::steps::{Setup, Step};
use crate::control::stop_action::StopAction;

fn plant(active: [bool; 2], comm_loss: StopAction) -> Setup {
    Setup {
        on_lease_expiry: StopAction::ZeroSpeed,
        on_unknown_state: StopAction::ZeroSpeed,
        comm_loss: [(200, comm_loss); 3],
        active,
    }
}

fn write(who: Who, drive: usize, cmd: Cmd, lease_ms: Option<u32>) -> Step {
    Step::Write {
        who,
        drive,
        cmd,
        lease_ms,
    }
}

/// A brake and then a leased setpoint, both waiting for the bus: the
/// brake goes first (emergency), the setpoint releases it as asked, and
/// its lease must go on: the brake ended it, and the motor turned with
/// no lease.
#[test]
fn a_brake_does_not_end_a_lease_taken_after_it() {
    let steps = [
        Step::Hold { ms: 50 },
        write(Who::Panel, 1, Cmd::Brake, None),
        write(Who::Panel, 1, Cmd::Speed(150), Some(100)),
        Step::Advance { ms: 50 },
        // Its lease runs out, and stops the motor.
        Step::Advance { ms: 200 },
    ];
    assert_eq!(
        run_case(plant([false, true], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}

/// A PLC's communication-loss brake overtakes an operator's setpoint
/// sent before it: the setpoint releases the brake, which must be applied
/// again (a stop's brake was not numbered by the brake guard).
#[test]
fn a_write_sent_before_a_stop_brake_and_landing_after_it_has_the_brake_again() {
    let steps = [
        write(Who::Plc, 1, Cmd::Speed(150), None),
        Step::Hold { ms: 50 },
        write(Who::Panel, 1, Cmd::Speed(150), None),
        Step::Gone { who: Who::Plc },
        Step::Advance { ms: 50 },
    ];
    assert_eq!(
        run_case(plant([false, true], StopAction::Brake), &steps),
        Ok(())
    );
}

/// A PLC's setpoint waits on the bus; an operator's leased setpoint
/// replaces its lease, and that lease runs out and stops the motor
/// before the PLC's setpoint lands: the stop must go again (only a
/// lease's own stop was repeated).
#[test]
fn a_replaced_lease_setpoint_landing_after_the_stop_has_the_stop_again() {
    let steps = [
        write(Who::Hmi, 0, Cmd::Activate, None),
        Step::Hold { ms: 1469 },
        write(Who::Plc, 0, Cmd::Speed(150), None),
        write(Who::Panel, 0, Cmd::Speed(150), Some(100)),
        Step::Gone { who: Who::Panel },
        Step::Advance { ms: 3000 },
    ];
    assert_eq!(
        run_case(plant([false, false], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}
