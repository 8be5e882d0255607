//! Opening the serial adapter: 8N1 at the configured baud, exclusive, with
//! the RS-485 direction control the adapter needs.

use std::time::Duration;

use serde::Deserialize;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};

use super::rs485;

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

/// Why the serial port could not be opened or set up.
#[derive(Debug, thiserror::Error)]
pub enum PortError {
    /// The device could not be opened.
    #[error(
        "cannot open serial port {path}: {source} (is the adapter plugged in, and is the daemon in the dialout group?)"
    )]
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

/// Opens `path` at `baud` 8N1, exclusively, and applies the RS-485 settings.
/// Must be called inside the tokio runtime that will use the port.
pub fn open(path: &str, baud: u32, rs485: &Rs485Settings) -> Result<SerialStream, PortError> {
    let mut port = tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None)
        .open_native_async()
        .map_err(|source| PortError::Open {
            path: path.to_string(),
            source,
        })?;
    match rs485.direction {
        Direction::Auto => {}
        Direction::Rts => {
            // Receive until we send.
            port.write_request_to_send(!rs485.rts_active_high)
                .map_err(|source| PortError::Open {
                    path: path.to_string(),
                    source,
                })?;
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
