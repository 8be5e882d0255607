//! A pty pair for tests that play the drives' side of the wire by hand.

use std::os::fd::OwnedFd;

use tokio_serial::{SerialPort, SerialStream};

/// A new pty: its far end, the path of the end the code under test opens,
/// and a handle that keeps that end open without a lock, so the path can
/// be opened exclusively and the far end never reads EIO between opens.
pub fn pty() -> (SerialStream, String, OwnedFd) {
    let (ptm, slave) = SerialStream::pair().unwrap();
    let path = slave.name().unwrap();
    let keep = nix::fcntl::open(
        path.as_str(),
        nix::fcntl::OFlag::O_RDWR | nix::fcntl::OFlag::O_NOCTTY | nix::fcntl::OFlag::O_CLOEXEC,
        nix::sys::stat::Mode::empty(),
    )
    .unwrap();
    drop(slave);
    (ptm, path, keep)
}

/// The RTU master on the pty at `path`, opened at the baud rate of
/// `settings` with its RS-485 settings, as the bus task opens its port.
pub async fn master(
    path: &str,
    settings: drivegate::bus::master::MasterSettings,
) -> drivegate::bus::master::RtuMaster {
    let port = drivegate::bus::port::open(path, settings.line.baud(), &settings.rs485).unwrap();
    drivegate::bus::master::RtuMaster::new(port, settings).unwrap()
}
