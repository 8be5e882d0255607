//! What the drive's faults mean and what to check, for the plant engineer
//! who reads an alarm: the manual (section 1.7, STATUS bits 5 and 2..0)
//! names each fault; these texts say what it means for the machine and
//! where to look, citing the manual's sections for the commands that
//! clear or prevent it. Pure text, no I/O.

use super::status::Fault;

/// What fault `fault` means and what to check. `Fault::None` has no help.
pub const fn fault(fault: Fault) -> &'static str {
    match fault {
        Fault::None => "",
        Fault::CurrentSense => {
            "The drive reports a current feedback signal fault (STATUS fault 1, manual 1.7): the \
             12-bit current measurement reads implausible values, so the current loop and the \
             stall protection cannot be trusted. Check the motor phase wiring and connector, then \
             power-cycle the drive; the manual warns (1.6) that the sampling circuit deviates \
             near its limits, so do not run torque setpoints or the over-current limit (1.8) at \
             the ends of -2048..2047 counts. Send a fault reset (CONFIG 0x8, manual 1.3) once the \
             cause is removed; if it comes back at once, the drive's current sensing is damaged."
        }
        Fault::Encoder => {
            "The drive reports an encoder feedback signal fault (STATUS fault 2, manual 1.7): it \
             no longer knows the rotor's position, so it cannot commutate or hold a position. \
             Check the encoder cable and connector and the motor's mounting, then send a fault \
             reset (CONFIG 0x8, manual 1.3). If the STATUS 'calibrated' bit (6) is clear, or \
             after the motor or encoder was replaced, calibrate the encoder angle (CONFIG 0x2, \
             about 4 s, the motor turns) and fine-tune it (CONFIG 0x3, the motor turns both \
             ways; only after 0x2), with the load free to move."
        }
        Fault::PowerStage => {
            "The drive reports a power stage fault (STATUS fault 3, manual 1.7): its power \
             switching devices detected an overload or short. Stop the machine and check the \
             motor phases for a short to each other or to earth and the motor cable for damage \
             before anything else; check that the load is not jammed and that the over-current \
             protection (manual 1.8: limit and stall time) suits the motor. Send a fault reset \
             (CONFIG 0x8, manual 1.3) only after the cause is found; a fault that returns at \
             once means the drive needs repair."
        }
        Fault::OverTemperature => {
            "The drive reports over-temperature (STATUS fault 4, manual 1.7; TEMP, register \
             0x00CA, is its temperature in degrees Celsius). Check its cooling (air flow, dust, \
             ambient temperature) and the load: a motor pushing against a jam or a brake, a \
             current limit (manual 1.8) set high, or ramps (1.9, 1.10) so fast that the drive \
             runs at its current limit all the time. Let it cool, then send a fault reset \
             (CONFIG 0x8, manual 1.3)."
        }
        Fault::UnderVoltage => {
            "The drive reports supply under-voltage (STATUS fault 5, manual 1.7; VOLT, register \
             0x00C8, is the supply in volts). Check the power supply's output and rating, the \
             supply wiring and connectors (a loose or thin wire sags under load), and whether \
             several drives accelerating at once pull the supply down; softer ramps (manual 1.9, \
             1.10) lower the peak current. Send a fault reset (CONFIG 0x8, manual 1.3) once the \
             supply holds."
        }
        Fault::OverVoltage => {
            "The drive reports supply over-voltage (STATUS fault 6, manual 1.7; VOLT, register \
             0x00C8, is the supply in volts). Most often the motor feeds energy back while it \
             brakes a large or falling load and the supply cannot absorb it: use softer \
             deceleration ramps (manual 1.9, 1.10), set the load inertia ratio (1.11), or add a \
             braking resistor or a supply that takes energy back. Check also that the supply is \
             the one the drive is rated for. Send a fault reset (CONFIG 0x8, manual 1.3) \
             afterwards."
        }
        Fault::Reserved => {
            "The drive reports fault code 7, which the manual lists as reserved (STATUS fault 7, \
             manual 1.7): it is not a fault the maker documents. Read the status again; if it stays, note the drive's \
             firmware and the raw STATUS word, power-cycle the drive and ask the maker. A fault \
             reset (CONFIG 0x8, manual 1.3) may clear it."
        }
    }
}

/// What a stalled motor (STATUS bit 5) means and what to check.
pub const STALL: &str = "The motor stalled (STATUS bit 5, manual 1.7): its current stayed above \
     the over-current protection's limit for longer than the stall time (manual 1.8) and the \
     drive stopped driving it. It stays stopped until it gets a fault reset (CONFIG 0x8, manual \
     1.3), as the manual says. Before the reset, check what blocked the motor (a jam, a brake \
     still closed, an end stop, a load heavier than planned) and that the protection's current \
     limit and stall time suit the motor and the load; too low a limit or too fast a ramp (1.9, \
     1.10) trips it on an ordinary start.";

/// What a drive that stopped answering means and what to check.
pub const OFFLINE: &str = "The drive stopped answering its status reads. Check its power supply \
     (VOLT was its last reading), the RS-485 wiring (A/B not swapped, the shield, termination at \
     both ends of the line) and its connector. Check that it still has the unit address drivegate \
     polls (set with a broadcast to address 0 with only that drive on the bus, manual 1.2) and \
     the line's settings (115200 bit/s, 8 data bits, no parity, 1 stop bit, manual 1.1). \
     drivegate keeps probing it and clears this alarm when it answers again.";

/// What a drive that has not answered once since its bus opened means and
/// what to check: most often the line's settings or the address, not the
/// drive.
pub const NEVER_ANSWERED: &str = "The drive has not answered a single status read since its bus \
     opened, so drivegate has never heard it: this is most often the bus's settings, not the \
     drive. Check the bus's baud rate (the drives speak 115200 bit/s, 8 data bits, no parity, 1 \
     stop bit, manual 1.1; baud in the [[bus]] section) and the unit address drivegate polls \
     against the one the drive has (set with a broadcast to address 0 with only that drive on \
     the bus, manual 1.2). `drivegate probe --port PORT --try-bauds` (with drivegate stopped) \
     finds the drives on the line and the rate they answer at. Then check the drive's power and \
     the RS-485 wiring (A/B not swapped, termination at both ends). drivegate keeps polling it \
     and clears this alarm when it answers.";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_fault_but_none_has_help_citing_the_manual() {
        for f in Fault::ALL {
            let text = fault(f);
            if f == Fault::None {
                assert!(text.is_empty());
            } else {
                assert!(text.contains("manual 1.7"), "{f:?}: {text}");
                assert!(text.contains("CONFIG 0x8"), "{f:?}: {text}");
            }
        }
        assert!(STALL.contains("fault reset"));
        assert!(OFFLINE.contains("1.2"));
        assert!(
            NEVER_ANSWERED.contains("baud rate")
                && NEVER_ANSWERED.contains("unit address")
                && NEVER_ANSWERED.contains("1.1")
                && NEVER_ANSWERED.contains("1.2")
                && NEVER_ANSWERED.contains("--try-bauds")
        );
    }
}
