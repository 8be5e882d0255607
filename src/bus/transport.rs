//! What carries a bus's bytes: a local serial adapter, or a TCP connection
//! to a serial device server (`tcp://host:port`). The master times the wire
//! the same way over both; only opening, direction control, discarding
//! unread input and the words for a lost line differ.

use std::io;

use socket2::SockRef;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_serial::{SerialPort, SerialStream};

use super::port::{self, PortError, Rs485Settings};
use super::rs485;
use super::tcp_port::{self, ConnectError};

/// A bus's open port.
#[derive(Debug)]
pub enum Transport {
    /// A serial adapter (or a pty).
    Serial(SerialStream),
    /// A serial device server; the address as configured, for messages.
    Tcp {
        /// The connection.
        stream: TcpStream,
        /// `host:port`.
        address: String,
    },
}

/// Why a bus's port could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// A serial adapter.
    #[error(transparent)]
    Serial(#[from] PortError),
    /// A serial device server.
    #[error(transparent)]
    Tcp(#[from] ConnectError),
}

/// Opens `port`: a serial device path at `baud` 8N1 with the RS-485
/// settings, or a `tcp://host:port` serial device server. Must be called
/// inside the runtime that will use the port.
pub async fn open(port: &str, baud: u32, rs485: &Rs485Settings) -> Result<Transport, OpenError> {
    match tcp_port::address(port) {
        Some(address) => {
            // The configuration was checked; a bad address here still gets
            // its message.
            let address = address.map_err(|reason| ConnectError::Connect {
                address: port.to_string(),
                reason,
            })?;
            let stream = tcp_port::connect(address).await?;
            Ok(Transport::Tcp {
                stream,
                address: address.to_string(),
            })
        }
        None => Ok(Transport::Serial(port::open(port, baud, rs485)?)),
    }
}

impl From<SerialStream> for Transport {
    fn from(port: SerialStream) -> Self {
        Transport::Serial(port)
    }
}

impl Transport {
    /// Reads what has arrived, waiting for at least one byte; `Ok(0)` when
    /// the line is gone (see [`closed`](Self::closed)).
    pub async fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self {
            Transport::Serial(port) => port.read(buf).await,
            Transport::Tcp { stream, .. } => stream.read(buf).await,
        }
    }

    /// Reads what has arrived without waiting (`WouldBlock` when nothing).
    /// Asks the system every time, whatever the runtime last heard: a
    /// master spinning through a silence reads bytes that came meanwhile.
    pub fn try_read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self {
            Transport::Serial(port) => port.try_read(buf),
            Transport::Tcp { stream, .. } => {
                // tokio's own try_read answers from the readiness its
                // reactor last saw, which a spinning thread never updates.
                let socket = SockRef::from(&*stream);
                std::io::Read::read(&mut &*socket, buf)
            }
        }
    }

    /// Writes some of `buf`, waiting for room.
    pub async fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        match self {
            Transport::Serial(port) => port.write(buf).await,
            Transport::Tcp { stream, .. } => stream.write(buf).await,
        }
    }

    /// Hands what was written to the line.
    pub async fn flush(&mut self) -> io::Result<()> {
        match self {
            Transport::Serial(port) => port.flush().await,
            Transport::Tcp { stream, .. } => stream.flush().await,
        }
    }

    /// Sets RTS (RS-485 direction by hand); only a serial adapter has it.
    pub fn set_rts(&mut self, level: bool) -> io::Result<()> {
        match self {
            Transport::Serial(port) => port.write_request_to_send(level).map_err(io::Error::other),
            Transport::Tcp { .. } => Err(io::Error::new(
                io::ErrorKind::Unsupported,
                "a serial device server switches the RS-485 direction itself",
            )),
        }
    }

    /// Blocks until the UART has sent everything written (serial only; a
    /// device server's TCP connection has nothing to drain here).
    pub fn drain(&self) -> io::Result<()> {
        match self {
            Transport::Serial(port) => rs485::drain(port),
            Transport::Tcp { .. } => Ok(()),
        }
    }

    /// Discards every byte received and not read yet.
    pub fn clear_input(&mut self) -> io::Result<()> {
        match self {
            Transport::Serial(port) => port
                .clear(tokio_serial::ClearBuffer::Input)
                .map_err(io::Error::other),
            Transport::Tcp { address, .. } => {
                let address = address.clone();
                let mut sink = [0u8; 512];
                loop {
                    match self.try_read(&mut sink) {
                        Ok(0) => return Err(tcp_port::closed(&address)),
                        Ok(_) => {}
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(()),
                        Err(e) => return Err(e),
                    }
                }
            }
        }
    }

    /// The error for a line that is gone (a read of 0 bytes).
    pub fn closed(&self) -> io::Error {
        match self {
            Transport::Serial(_) => io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "the serial port was closed (adapter unplugged?)",
            ),
            Transport::Tcp { address, .. } => tcp_port::closed(address),
        }
    }
}
