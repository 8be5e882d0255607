//! The two places the bus needs the raw file descriptor of the serial port:
//! the kernel's RS-485 mode (TIOCSRS485) and waiting for the transmitter to
//! drain (tcdrain) before dropping RTS by hand.

use std::io;
use std::os::fd::{AsRawFd, BorrowedFd};
use std::time::Duration;

use serde::Deserialize;
use tokio_serial::SerialStream;

/// How the RS-485 transceiver's driver is switched on for sending.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    /// The adapter switches by itself (most USB RS-485 adapters).
    #[default]
    Auto,
    /// The daemon raises RTS while sending and drops it once the frame is out.
    Rts,
    /// The kernel's RS-485 mode (TIOCSRS485) toggles RTS around each send.
    Kernel,
}

/// RS-485 options of a bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Rs485Settings {
    /// Direction control method.
    pub direction: Direction,
    /// RTS level that enables the driver (true: high while sending).
    pub rts_active_high: bool,
    /// Delay between enabling the driver and the first bit, in us.
    pub delay_before_send_us: u32,
    /// Delay between the last bit and releasing the driver, in us.
    pub delay_after_send_us: u32,
}

impl Default for Rs485Settings {
    fn default() -> Self {
        Self {
            direction: Direction::Auto,
            rts_active_high: true,
            delay_before_send_us: 0,
            delay_after_send_us: 0,
        }
    }
}

impl Rs485Settings {
    /// Delay before sending.
    pub fn before(&self) -> Duration {
        Duration::from_micros(u64::from(self.delay_before_send_us))
    }

    /// Delay after sending.
    pub fn after(&self) -> Duration {
        Duration::from_micros(u64::from(self.delay_after_send_us))
    }
}

/// `struct serial_rs485` of `<linux/serial.h>`.
#[repr(C)]
#[derive(Debug, Default)]
struct SerialRs485 {
    flags: u32,
    delay_rts_before_send: u32,
    delay_rts_after_send: u32,
    padding: [u32; 5],
}

const SER_RS485_ENABLED: u32 = 1 << 0;
const SER_RS485_RTS_ON_SEND: u32 = 1 << 1;
const SER_RS485_RTS_AFTER_SEND: u32 = 1 << 2;

nix::ioctl_write_ptr_bad!(
    /// TIOCSRS485: sets the port's RS-485 mode.
    set_rs485,
    nix::libc::TIOCSRS485,
    SerialRs485
);

/// Turns on the kernel's RS-485 mode: the UART driver raises RTS around each
/// transmission itself, with the configured delays (rounded up to ms, the
/// kernel's unit).
pub fn enable_kernel_mode(port: &SerialStream, settings: &Rs485Settings) -> io::Result<()> {
    let mut flags = SER_RS485_ENABLED;
    if settings.rts_active_high {
        flags |= SER_RS485_RTS_ON_SEND;
    } else {
        flags |= SER_RS485_RTS_AFTER_SEND;
    }
    let config = SerialRs485 {
        flags,
        delay_rts_before_send: settings.delay_before_send_us.div_ceil(1000),
        delay_rts_after_send: settings.delay_after_send_us.div_ceil(1000),
        padding: [0; 5],
    };
    // SAFETY: the fd is open for the duration of the call (we hold `port`)
    // and `config` is a valid `struct serial_rs485` that outlives it.
    #[allow(unsafe_code)]
    let result = unsafe { set_rs485(port.as_raw_fd(), &config) };
    result.map(drop).map_err(|errno| {
        if errno == nix::errno::Errno::ENOTTY || errno == nix::errno::Errno::EINVAL {
            io::Error::new(
                io::ErrorKind::Unsupported,
                "the adapter does not support the kernel's RS-485 mode; use direction = \"rts\" or \"auto\"",
            )
        } else {
            io::Error::from(errno)
        }
    })
}

/// Blocks until every byte written to the port has left the UART. Only used
/// for manual RTS control, on the bus's own thread.
pub fn drain(port: &SerialStream) -> io::Result<()> {
    // SAFETY: `port` keeps the fd open for the whole borrow.
    #[allow(unsafe_code)]
    let fd = unsafe { BorrowedFd::borrow_raw(port.as_raw_fd()) };
    nix::sys::termios::tcdrain(fd).map_err(io::Error::from)
}
