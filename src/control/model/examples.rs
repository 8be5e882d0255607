//! Plain example tests: each bug the model found, as the shrunk case that
//! showed it, replayed through the same world.

use super::steps::{Cmd, Damage, Trouble, Who};
use super::steps::{Setup, Step};
use super::world::World;
use super::{run_case, run_case_then};
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

/// A lease taken with a torque-mode command the drive never got (it was
/// silent) ends while the status read of its stop is lost: the stop
/// zeroed the torque setpoint, by the lease's mode, and the motor went on
/// turning in speed mode. With the mode unknown, both are zeroed.
#[test]
fn a_stop_that_cannot_read_the_mode_zeroes_both_setpoints() {
    let steps = [
        write(Who::Panel, 0, Cmd::Speed(150), None),
        write(Who::Hmi, 0, Cmd::Speed(150), Some(100)),
        Step::Fault {
            drive: 0,
            trouble: Trouble::Dead(100),
        },
        write(Who::Plc, 0, Cmd::TorqueMode, None),
        Step::Fault {
            drive: 0,
            trouble: Trouble::LostRequests(1),
        },
        Step::Advance { ms: 200 },
    ];
    assert_eq!(
        run_case(plant([true, false], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}

/// The journal garbled and the port down at the start: the turning drive
/// did not answer then, and nothing stopped it once it did; then it was
/// stopped, and no alarm said so.
#[test]
fn a_drive_silent_at_a_start_with_the_journal_unknown_is_stopped_when_it_answers() {
    let steps = [
        write(Who::Panel, 1, Cmd::Speed(150), None),
        Step::BusDown { ms: 50 },
        Step::Restart {
            wire: false,
            damage: Damage::Garbled,
            down_ms: 0,
        },
        Step::Advance { ms: 100 },
    ];
    let alarms = run_case_then(
        plant([false, true], StopAction::ZeroSpeed),
        &steps,
        World::unknown_state_alarms,
    );
    let alarms = match alarms {
        Ok(alarms) => alarms,
        Err(broken) => panic!("{broken}"),
    };
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    assert!(
        alarms[0].starts_with("the safety journal could not be read at start"),
        "{alarms:?}"
    );
    assert!(
        alarms[0].ends_with(
            ": lift did not answer at the start; at its first answer it was turning at 150 rpm and was stopped (on_unknown_state = zero-speed)"
        ),
        "{alarms:?}"
    );
}

/// Two setpoints sent before a brake land after it (the brake goes first)
/// and release it; a deactivation sent after the brake then ended the
/// brake being applied again, leaving the drive unbraked.
#[test]
fn a_deactivation_does_not_end_a_brake_owed_again() {
    let steps = [
        write(Who::Panel, 0, Cmd::Activate, None),
        Step::Hold { ms: 1079 },
        write(Who::Hmi, 0, Cmd::Speed(150), None),
        write(Who::Panel, 0, Cmd::Speed(150), None),
        Step::Advance { ms: 555 },
        write(Who::Hmi, 0, Cmd::Brake, None),
        Step::Advance { ms: 177 },
        write(Who::Hmi, 0, Cmd::Deactivate, None),
        Step::Advance { ms: 347 },
    ];
    assert_eq!(
        run_case(plant([false, false], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}

/// An MQTT host's leased setpoint waits on the bus behind an OPC UA
/// client's deactivation and an operator's activation: the deactivation
/// ended the lease, the activation let the setpoint turn the motor, with
/// no lease and no stop.
#[test]
fn a_setpoint_confirmed_after_a_deactivation_ended_its_lease_is_stopped() {
    let steps = [
        Step::Hold { ms: 50 },
        write(Who::Panel, 0, Cmd::Speed(150), None),
        write(Who::Scada, 0, Cmd::Speed(150), None),
        write(Who::Panel, 1, Cmd::Activate, None),
        write(Who::Scada, 1, Cmd::Speed(150), None),
        write(Who::Opcua, 1, Cmd::Deactivate, None),
        Step::Advance { ms: 50 },
    ];
    assert_eq!(
        run_case(plant([false, true], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}

/// A lease ends, and its brake fails on the line; an operator then writes
/// a torque setpoint without a lease while the drive is in speed mode. It
/// sets no motion, yet it ended the stop still being tried: the motor
/// went on at the ended lease's speed with nobody owning it.
#[test]
fn a_setpoint_of_another_mode_does_not_take_over_a_failing_stop() {
    let setup = Setup {
        on_lease_expiry: StopAction::Brake,
        ..plant([true, false], StopAction::ZeroSpeed)
    };
    let steps = [
        write(Who::Panel, 0, Cmd::Speed(150), Some(100)),
        Step::Fault {
            drive: 0,
            trouble: Trouble::LostRequests(3),
        },
        Step::Hold { ms: 566 },
        Step::Advance { ms: 1316 },
        write(Who::Panel, 0, Cmd::Torque(200), None),
        Step::Advance { ms: 6000 },
    ];
    assert_eq!(run_case(setup, &steps), Ok(()));
}

/// The same with a zero-speed stop and a torque setpoint of zero over
/// the stream: three tries of the stop (its read, both setpoints zeroed)
/// are lost, and the setpoint, which leaves the drive in speed mode at
/// the ended lease's speed, ended its tries.
#[test]
fn a_zero_torque_setpoint_does_not_take_over_a_failing_zero_speed_stop() {
    let steps = [
        write(Who::Panel, 0, Cmd::Speed(150), Some(100)),
        Step::Fault {
            drive: 0,
            trouble: Trouble::LostRequests(9),
        },
        Step::Hold { ms: 566 },
        Step::Advance { ms: 1500 },
        write(Who::Hmi, 0, Cmd::Torque(0), None),
        Step::Advance { ms: 6000 },
    ];
    assert_eq!(
        run_case(plant([true, false], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}

/// A lease ends and its stop fails; a new lease's setpoint may have
/// landed (its reply was lost): the stop waits behind the new lease, and
/// the journal holds both. After a `kill -9` the start carried out the
/// stop and dropped the lease, which still had most of its time: now it
/// puts the lease back, the stop behind it.
#[test]
fn a_lease_taken_over_a_failing_stop_is_back_after_a_restart() {
    let steps = [
        write(Who::Panel, 0, Cmd::Speed(150), Some(100)),
        Step::Fault {
            drive: 0,
            trouble: Trouble::LostRequests(3),
        },
        Step::Advance { ms: 150 },
        Step::Fault {
            drive: 0,
            trouble: Trouble::LostReplies(1),
        },
        write(Who::Panel, 0, Cmd::Speed(120), Some(250)),
        Step::Restart {
            wire: false,
            damage: Damage::Intact,
            down_ms: 0,
        },
        // The journal of the new process holds both too.
        Step::Restart {
            wire: false,
            damage: Damage::Intact,
            down_ms: 0,
        },
        // The lease runs out: its stop is sent.
        Step::Advance { ms: 600 },
    ];
    assert_eq!(
        run_case(plant([true, false], StopAction::ZeroSpeed), &steps),
        Ok(())
    );
}
