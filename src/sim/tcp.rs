//! The simulated bus served on TCP, as a serial device server (Moxa NPort,
//! USR-TCP232) serves a remote RS-485 line in "TCP server" mode: a master
//! connects and exchanges raw RTU bytes; the wire's timing is the same as
//! behind the pty.
//!
//! One master at a time: a newer connection replaces the current one (a
//! master that reconnects after losing its connection is served at once,
//! even if the old connection was never seen to close). Bytes the drives
//! send while nobody is connected are lost, as on a real line.

use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;

/// Asks the line to close its current connection (a device server's
/// reboot, a network cut), for tests of the master's reconnection.
#[derive(Debug, Default)]
pub(crate) struct Disconnects {
    asked: AtomicU64,
    notify: Notify,
}

impl Disconnects {
    /// Closes the connection of the moment, if any.
    pub(crate) fn disconnect(&self) {
        self.asked.fetch_add(1, Ordering::SeqCst);
        self.notify.notify_waiters();
    }

    fn asked(&self) -> u64 {
        self.asked.load(Ordering::SeqCst)
    }
}

/// The listening side and the master's connection.
pub(crate) struct TcpLine {
    listener: TcpListener,
    address: SocketAddr,
    connection: Option<TcpStream>,
    disconnects: Arc<Disconnects>,
    /// Disconnects asked for that have been carried out.
    done: u64,
    /// Connections accepted.
    accepted: u64,
}

impl TcpLine {
    /// Listens on `address` (port 0: one the system picks); must be called
    /// inside the simulator's runtime.
    pub(crate) fn bind(address: SocketAddr) -> io::Result<Self> {
        let std_listener = std::net::TcpListener::bind(address)?;
        std_listener.set_nonblocking(true)?;
        let listener = TcpListener::from_std(std_listener)?;
        let address = listener.local_addr()?;
        Ok(TcpLine {
            listener,
            address,
            connection: None,
            disconnects: Arc::new(Disconnects::default()),
            done: 0,
            accepted: 0,
        })
    }

    /// Where a master connects: `tcp://ip:port`.
    pub(crate) fn endpoint(&self) -> String {
        format!("tcp://{}", self.address)
    }

    /// The handle that closes connections on request.
    pub(crate) fn disconnects(&self) -> Arc<Disconnects> {
        Arc::clone(&self.disconnects)
    }

    /// Connections accepted so far.
    pub(crate) fn accepted(&self) -> u64 {
        self.accepted
    }

    /// Reads what the master sends, waiting for a master to connect when
    /// none is; never returns 0 (a closed connection means waiting for the
    /// next one). Cancel-safe.
    pub(crate) async fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let disconnects = Arc::clone(&self.disconnects);
        loop {
            let notified = disconnects.notify.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            let asked = disconnects.asked();
            if asked != self.done {
                self.done = asked;
                self.connection = None;
            }
            match &mut self.connection {
                None => {
                    tokio::select! {
                        accepted = self.listener.accept() => self.take(accepted),
                        () = &mut notified => {}
                    }
                }
                Some(connection) => {
                    tokio::select! {
                        read = connection.read(buf) => match read {
                            Ok(n) if n > 0 => return Ok(n),
                            _ => self.connection = None,
                        },
                        accepted = self.listener.accept() => self.take(accepted),
                        () = &mut notified => {}
                    }
                }
            }
        }
    }

    /// Sends `bytes` to the master, if one is connected.
    pub(crate) async fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        if let Some(connection) = &mut self.connection
            && connection.write_all(bytes).await.is_err()
        {
            self.connection = None;
        }
        Ok(())
    }

    fn take(&mut self, accepted: io::Result<(TcpStream, SocketAddr)>) {
        // A failed accept (out of descriptors, a connection reset before it
        // was taken) leaves the current connection as it was.
        if let Ok((stream, _)) = accepted {
            // The connection replaced, if any, is closed here.
            let _ = stream.set_nodelay(true);
            self.connection = Some(stream);
            self.accepted += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn serves_one_master_at_a_time_and_closes_on_request() {
        let mut line = TcpLine::bind("127.0.0.1:0".parse().unwrap()).unwrap();
        let address = line.endpoint().strip_prefix("tcp://").unwrap().to_string();
        let disconnects = line.disconnects();
        let mut first = TcpStream::connect(&address).await.unwrap();
        first.write_all(b"ab").await.unwrap();
        let mut buf = [0u8; 8];
        let n = line.read(&mut buf).await.unwrap();
        assert_eq!(&buf[..n], b"ab");
        line.write_all(b"xy").await.unwrap();
        let mut got = [0u8; 2];
        first.read_exact(&mut got).await.unwrap();
        assert_eq!(&got, b"xy");
        // A second master takes over.
        let mut second = TcpStream::connect(&address).await.unwrap();
        second.write_all(b"cd").await.unwrap();
        let n = line.read(&mut buf).await.unwrap();
        assert_eq!(&buf[..n], b"cd");
        assert_eq!(line.accepted(), 2);
        // Asked to, the line drops it: the master reads the close.
        disconnects.disconnect();
        let reading = tokio::spawn(async move {
            let mut buf = [0u8; 8];
            line.read(&mut buf).await.map(|n| buf[..n].to_vec())
        });
        let mut rest = Vec::new();
        tokio::time::timeout(Duration::from_secs(5), second.read_to_end(&mut rest))
            .await
            .expect("closed within 5 s")
            .expect("closed, not reset");
        assert!(rest.is_empty());
        // A new master is served after that.
        let mut third = TcpStream::connect(&address).await.unwrap();
        third.write_all(b"ef").await.unwrap();
        assert_eq!(reading.await.unwrap().unwrap(), b"ef");
    }
}
