//! Opening the serial adapter: 8N1 at the configured baud, exclusive, with
//! the RS-485 direction control the adapter needs.

use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};

use super::rs485;
pub use super::rs485::{Direction, Rs485Settings};

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
