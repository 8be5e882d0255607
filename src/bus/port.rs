//! Opening the serial adapter: 8N1 at the configured baud, exclusive, with
//! the RS-485 direction control the adapter needs. A port that does not
//! open says why in a plant engineer's words, the same in the log,
//! `/readyz`, the console and the bus-down alarm: another program that
//! holds it is named with its pid ([`crate::port_holders`]), a missing
//! adapter and a missing permission are told apart.

use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};

use super::rs485;
pub use super::rs485::{Direction, Rs485Settings};
use crate::port_holders::{self, Holder};

/// Why the serial port could not be opened or set up.
#[derive(Debug, thiserror::Error)]
pub enum PortError {
    /// Another program holds the device: its lock, or it opened it
    /// exclusively (a running `drivegate probe`, another daemon, a
    /// terminal program).
    #[error("cannot open serial port {path}: {}", held_words(.path, .holders))]
    Held {
        /// Device path.
        path: String,
        /// Who holds it, as far as the system tells (none: it does not
        /// say to this user).
        holders: Vec<Holder>,
    },
    /// The path leads to the terminal of a login session (a link left
    /// behind by an adapter or a simulator that is gone, now leading to a
    /// pseudo-terminal the kernel gave a shell): never opened, since
    /// frames written there would land in someone's terminal.
    #[error(
        "refusing serial port {path}: it leads to {target}, the terminal of a login session \
         ({command}, pid {session}), not a serial line. A link left behind by an adapter or a \
         simulator that is gone? Point port at the adapter (/dev/serial/by-id/...) or remove \
         the link"
    )]
    Terminal {
        /// Device path, as configured.
        path: String,
        /// Where it leads.
        target: String,
        /// The session leader's pid.
        session: u32,
        /// Its command line.
        command: String,
    },
    /// The device could not be opened.
    #[error("cannot open serial port {path}: {source} ({})", open_hint(.source))]
    Open {
        /// Device path.
        path: String,
        /// What the system said.
        source: tokio_serial::Error,
    },
    /// The adapter refused the RS-485 setting.
    #[error("serial port {path}: {source}")]
    Rs485 {
        /// Device path.
        path: String,
        /// What the system said.
        source: std::io::Error,
    },
}

/// What a port held by `holders` means, and what the bus does about it.
fn held_words(path: &str, holders: &[Holder]) -> String {
    if holders.is_empty() {
        return format!(
            "in use by another program, which holds it exclusively (the system does not say \
             which to this user: `sudo fuser -v {path}` names it). drivegate opens it once that \
             program lets it go"
        );
    }
    let who = if holders.len() == 1 {
        "another program"
    } else {
        "other programs"
    };
    let what = if port_holders::is_drivegate(holders) {
        "a drivegate probe or another drivegate daemon on this line; drivegate opens the \
         port once it lets it go"
    } else {
        "drivegate opens the port once it lets it go: stop it if this line is drivegate's"
    };
    format!("in use by {who}: {}. {what}", port_holders::named(holders))
}

/// What to check for a port that did not open, by what the system said.
fn open_hint(source: &tokio_serial::Error) -> &'static str {
    match source.kind {
        tokio_serial::ErrorKind::Io(std::io::ErrorKind::NotFound) => {
            "no such device: is the adapter plugged in? ls -l /dev/serial/by-id/ lists the \
             adapters"
        }
        tokio_serial::ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => {
            "the daemon's user may not open it: is it in the dialout group?"
        }
        _ => "is the adapter plugged in, and is the daemon in the dialout group?",
    }
}

/// Why `path` did not open, from what the system said: a device held by
/// another program (the system says "busy", or its lock is held) names it.
fn open_error(path: &str, source: tokio_serial::Error) -> PortError {
    if source.kind == tokio_serial::ErrorKind::NoDevice {
        return PortError::Held {
            path: path.to_string(),
            holders: port_holders::holders(path),
        };
    }
    PortError::Open {
        path: path.to_string(),
        source,
    }
}

/// Opens `path` at `baud` 8N1, exclusively, and applies the RS-485 settings.
/// Must be called inside the tokio runtime that will use the port.
pub fn open(path: &str, baud: u32, rs485: &Rs485Settings) -> Result<SerialStream, PortError> {
    if let Some((target, session)) = port_holders::session_terminal(path) {
        return Err(PortError::Terminal {
            path: path.to_string(),
            target: target.display().to_string(),
            session,
            command: port_holders::command_of(session),
        });
    }
    let mut port = tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None)
        .open_native_async()
        .map_err(|source| open_error(path, source))?;
    match rs485.direction {
        Direction::Auto => {}
        Direction::Rts => {
            // Receive until we send.
            port.write_request_to_send(!rs485.rts_active_high)
                .map_err(|source| open_error(path, source))?;
        }
        Direction::Kernel => {
            rs485::enable_kernel_mode(&port, rs485).map_err(|source| PortError::Rs485 {
                path: path.to_string(),
                source,
            })?;
        }
    }
    // Whatever sat in the buffers before we took the port is not ours.
    let _ = port.clear(tokio_serial::ClearBuffer::All);
    Ok(port)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn error(kind: tokio_serial::ErrorKind, what: &str) -> tokio_serial::Error {
        tokio_serial::Error::new(kind, what)
    }

    #[test]
    fn a_held_port_names_its_holder_and_never_the_dialout_group() {
        let flock = Holder {
            pid: 812,
            command: "flock /dev/ttyUSB0 sleep 600".into(),
            locks: true,
        };
        let e = PortError::Held {
            path: "/dev/ttyUSB0".into(),
            holders: vec![flock],
        };
        assert_eq!(
            e.to_string(),
            "cannot open serial port /dev/ttyUSB0: in use by another program: flock \
             /dev/ttyUSB0 sleep 600 (pid 812, holds its lock). drivegate opens the port once it \
             lets it go: stop it if this line is drivegate's"
        );
        let probe = Holder {
            pid: 99,
            command: "drivegate probe --port /dev/ttyUSB0".into(),
            locks: true,
        };
        let e = PortError::Held {
            path: "/dev/ttyUSB0".into(),
            holders: vec![probe],
        };
        assert!(
            e.to_string()
                .contains("a drivegate probe or another drivegate daemon")
        );
        let unknown = PortError::Held {
            path: "/dev/ttyUSB0".into(),
            holders: Vec::new(),
        };
        assert!(unknown.to_string().contains("sudo fuser -v /dev/ttyUSB0"));
        for e in [e, unknown] {
            assert!(!e.to_string().contains("dialout"), "{e}");
        }
    }

    #[test]
    fn a_missing_adapter_and_a_missing_permission_are_told_apart() {
        let gone = open_error(
            "/dev/ttyUSB0",
            error(
                tokio_serial::ErrorKind::Io(std::io::ErrorKind::NotFound),
                "No such file or directory",
            ),
        );
        assert!(
            gone.to_string().ends_with(
                "(no such device: is the adapter plugged in? ls -l /dev/serial/by-id/ lists \
                 the adapters)"
            ),
            "{gone}"
        );
        let denied = open_error(
            "/dev/ttyUSB0",
            error(
                tokio_serial::ErrorKind::Io(std::io::ErrorKind::PermissionDenied),
                "Permission denied",
            ),
        );
        assert!(denied.to_string().contains("dialout group"), "{denied}");
        // "Busy" (the lock held, or TIOCEXCL) is a holder, looked up.
        let busy = open_error(
            "/dev/nonexistent-adapter",
            error(
                tokio_serial::ErrorKind::NoDevice,
                "Unable to acquire exclusive lock",
            ),
        );
        assert!(matches!(busy, PortError::Held { .. }), "{busy}");
    }
}
