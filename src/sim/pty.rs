//! The pseudo-terminal the simulated bus lives behind.
//!
//! The simulator keeps the master end; masters (the daemon, mbpoll, pymodbus)
//! open the slave path like a serial port. `SerialStream::pair()` opens the
//! slave with an exclusive flock, which would stop a master opening it
//! exclusively, so that descriptor is dropped and a plain one (no lock) is
//! held instead: it keeps the slave side open between clients, so the
//! master never reads EIO while nobody has the port open.

use std::io;
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};

use nix::fcntl::{OFlag, open};
use nix::sys::stat::Mode;
use tokio_serial::{SerialPort, SerialStream};

/// A pty pair: the master end as an async stream, the slave's path.
pub struct Pty {
    master: SerialStream,
    path: PathBuf,
    _hold: OwnedFd,
}

impl Pty {
    /// Opens a new pty; must be called inside a tokio runtime (the master is
    /// registered with its reactor).
    pub fn open() -> io::Result<Self> {
        let (master, slave) = SerialStream::pair().map_err(io::Error::from)?;
        let path = slave
            .name()
            .map(PathBuf::from)
            .ok_or_else(|| io::Error::other("the new pty has no slave path"))?;
        let hold = open(
            &path,
            OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC,
            Mode::empty(),
        )
        .map_err(io::Error::from)?;
        drop(slave);
        Ok(Pty {
            master,
            path,
            _hold: hold,
        })
    }

    /// The slave's path, e.g. `/dev/pts/3`.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The master end, where the simulated drives read and write.
    pub fn master(&mut self) -> &mut SerialStream {
        &mut self.master
    }
}
